"""``python -m clppm.cli``: the same as the ``clppm`` command."""
from . import entry

entry()
