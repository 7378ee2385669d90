"""Output paths the user names, checked before any work.

A render, trace or comparison that can only fail at its end (or at its first checkpoint,
minutes in) because a folder is missing or read-only wastes the run; these checks make that
failure one line at the start.  A path whose folder does not exist yet is fine when the folder
can be created (clppm creates it), and nothing is created by the check itself.
"""
from __future__ import annotations

import os

from .config import ConfigError


def writable_problem(path: str) -> str | None:
    """Why ``path`` cannot be written as a file (one phrase), or None."""
    p = os.path.abspath(path)
    if os.path.isdir(p):
        return "is a folder"
    if os.path.exists(p):
        return None if os.access(p, os.W_OK) else "exists and is not writable"
    d = os.path.dirname(p)
    while not os.path.isdir(d):             # the nearest folder that exists must take new entries
        if os.path.exists(d):
            return f"{d} is not a folder"
        parent = os.path.dirname(d)
        if parent == d:
            break
        d = parent
    if not os.access(d, os.W_OK | os.X_OK):
        return f"folder {d} is not writable"
    return None


def folder_problem(path: str) -> str | None:
    """Why files cannot be written into the folder ``path`` (made if missing), or None."""
    p = os.path.abspath(path)
    if os.path.exists(p) and not os.path.isdir(p):
        return "is not a folder"
    if os.path.isdir(p):
        return None if os.access(p, os.W_OK | os.X_OK) else "folder is not writable"
    return writable_problem(os.path.join(p, "x"))


def check_folder(path: str | None, flag: str, source: str = "command line") -> None:
    """Raise :class:`ConfigError` if files cannot be written into the folder ``path``."""
    if path is None:
        return
    why = folder_problem(path)
    if why:
        raise ConfigError(source, flag, path, f"cannot be written ({why})")


def check_writable(path: str | None, flag: str, source: str = "command line") -> None:
    """Raise :class:`ConfigError` (one line: flag, path, reason) if ``path`` cannot be written."""
    if path is None:
        return
    why = writable_problem(path)
    if why:
        raise ConfigError(source, flag, path, f"cannot be written ({why})")


def check_outputs(out: str | None = None, checkpoint: str | None = None, **more: str | None) -> None:
    """Check a render's outputs: the EXR and its .png/.json siblings, the checkpoint, others."""
    if out:
        base = os.path.splitext(out)[0]
        for p in (out, base + ".png", base + ".json"):
            check_writable(p, "-o/--output")
    check_writable(checkpoint, "checkpoint")
    for flag, p in more.items():
        check_writable(p, "--" + flag.replace("_", "-"))
