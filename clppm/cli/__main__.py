"""``python -m clppm.cli``: the same as the ``clppm`` command."""
import sys

from . import main

sys.exit(main())
