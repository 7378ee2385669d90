"""What the commands share: exit codes, the help formatter, ``--device``/``-q``/``-v``, value
types, loading a config by name, and writing JSON.

Value types: ``--resolution 320x240``, ``--bands 380:780:10``, ``--region 2,1,6,4``: each
command's argparse ``type=`` function is :func:`numbers` with its separator, count, type and
the one-line message argparse prints when the value does not parse.
"""
from __future__ import annotations

import argparse
import json
import os
import signal

from ..config import ConfigError


def numbers(s: str, sep: str, n: int, cast, message: str) -> tuple:
    """``s`` split at ``sep`` into exactly ``n`` values of type ``cast``; else
    :class:`argparse.ArgumentTypeError` with ``message``."""
    try:
        v = tuple(cast(x) for x in s.split(sep))
    except ValueError:
        v = ()
    if len(v) != n:
        raise argparse.ArgumentTypeError(message)
    return v


def resolution(s: str, message: str) -> tuple[int, int]:
    """``WxH`` (x in either case) as (width, height)."""
    return numbers(s.lower(), "x", 2, int, message)


#: the six sample-point schemes (paper section 5), one line each for --help
METHODS_HELP = {
    "a": "equal spacing 4 um along the eye ray (the paper's densest)",
    "b": "equal spacing 7 um",
    "c": "equal spacing 14 um",
    "d": "random spacing, mean 1/extinction of the layer, extinction the max over the bands",
    "e": "as d with the mean over the bands (the default)",
    "f": "as d with the min over the bands (the sparsest)",
}


def resolution_arg(s: str):
    """``--resolution`` of render and samples."""
    return resolution(s, f"--resolution {s!r}: expected WxH, e.g. 320x240")


class Formatter(argparse.RawDescriptionHelpFormatter):
    """Examples kept as written; each option's default shown unless its help says it."""

    def _get_help_string(self, action):
        h = action.help or ""
        if (action.default not in (None, False, argparse.SUPPRESS) and "default" not in h
                and action.option_strings and action.nargs != 0):
            h += " (default: %(default)s)"
        return h


#: every command's error lines start with this (argparse's usage errors too)
ERROR_PREFIX = "clppm: error:"


class Parser(argparse.ArgumentParser):
    def __init__(self, *a, **k):
        k.setdefault("formatter_class", Formatter)
        super().__init__(*a, **k)

    def error(self, message):
        """A usage error as every other bad input: one line, the common prefix, exit 2."""
        self.exit(EXIT["input"], f"{ERROR_PREFIX} {self.prog}: {' '.join(message.split())} "
                                 f"({self.prog} --help lists the options)\n")


def add_device(p):
    """--device, -q and -v: every command has them (commands in other modules call this too)."""
    p.add_argument("--device", default=None,
                   help="OpenCL device: 'P:D' as `clppm devices` lists, an implementation (pocl, "
                        "intel, nvidia, ...) or part of its platform or device name (default: "
                        "$PYOPENCL_CTX, else the first GPU, else the preferred CPU implementation)")
    if "-q" not in p._option_string_actions:
        p.add_argument("-q", "--quiet", action="store_true", help="no progress or status lines")
    p.add_argument("-v", "--verbose", action="store_true",
                   help="details after an error (the full message, a traceback for internal errors)")


def load_config(path):
    """A config file, or the name of a shipped one (``forearm``)."""
    from .. import config
    return config.load(config.find(path))


def write_json(path: str, obj) -> None:
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        json.dump(obj, f, indent=1)


class InputError(ValueError):
    """Bad input whose message is already the whole line (e.g. the executor's)."""


def method_or_spacing(a) -> None:
    if a.method is not None and a.spacing is not None:
        raise ConfigError("command line", "--method", a.method,
                          f"give --method or --spacing, not both (--spacing {a.spacing:g} is "
                          "equal spacing, i.e. methods a-c at any spacing)")


#: exit codes, as the README's table lists them
EXIT = {"ok": 0, "internal": 1, "input": 2, "device": 3, "sigint": 128 + signal.SIGINT,
        "sigterm": 128 + signal.SIGTERM}
