"""clppm's version (the run reports, checkpoints, caches and `clppm --version` name it)."""
__version__ = "0.1.0"
