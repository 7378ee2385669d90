"""Command-line values the commands share: a fixed number of numbers in one argument.

``--resolution 320x240``, ``--bands 380:780:10``, ``--region 2,1,6,4``: each command's argparse
``type=`` function is :func:`numbers` with its separator, count, type and the one-line message
argparse prints when the value does not parse.
"""
from __future__ import annotations

import argparse


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
