"""Command line: clppm devices | config | trace | render | samples | compare | reflectance | fit | bench.

Every command is declared and reached here, one module each: :mod:`.render`, :mod:`.tools`
(devices, config, trace, samples), :mod:`.compare`, :mod:`.reflectance`, :mod:`.fit`, :mod:`.bench`; what
they share is in :mod:`.options`.  The library modules know nothing of argparse.

Every command takes ``--device`` (else ``PYOPENCL_CTX``, else the first GPU, else the
first device), ``-q`` and ``-v``.  Exit codes (:data:`EXIT`): 0 a finished job; 1 an internal
error; 2 bad input (one line naming the file, key and value, before any work); 3 a device
problem (the device and what to do); 130 / 143 a render stopped by SIGINT / SIGTERM (what it
had is written, with a checkpoint to resume).
"""
from __future__ import annotations

import argparse
import os
import signal
import sys

from ..config import ConfigError
from . import bench, compare, fit, reflectance, render, tools
from .options import ERROR_PREFIX, EXIT, METHODS_HELP, InputError, Parser

def _versions() -> str:
    """clppm, pyopencl and the OpenCL platforms found, one a line."""
    from ..version import __version__
    lines = [f"clppm {__version__}"]
    try:
        import pyopencl as cl
        lines.append(f"pyopencl {cl.VERSION_TEXT}")
        try:
            plats = cl.get_platforms()
        except cl.Error:
            plats = []
        for pl in plats:
            lines.append(f"OpenCL platform: {pl.name.strip()} ({pl.version.strip()})")
        if not plats:
            lines.append("OpenCL platform: none found (pip install 'clppm[pocl]' gives a CPU one)")
    except ImportError as e:
        lines.append(f"pyopencl: not importable ({e})")
    return "\n".join(lines)


class _Version(argparse.Action):
    def __init__(self, option_strings, dest, **k):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **k)

    def __call__(self, parser, namespace, values, option_string=None):
        print(_versions())
        parser.exit(0)


class _Terminated(BaseException):
    """SIGTERM outside a render's passes (a render finishes its pass and exits 143 itself)."""


def _on_sigterm(sig, frame):
    raise _Terminated


TOP_EPILOG = """\
examples:
  clppm render forearm -o out/forearm.exr          the shipped forearm scene (a few minutes)
  clppm render forearm --resolution 64x48 --passes 2 --photons 20000 -o out/smoke.png
                                                   a smoke test (under a minute)
  clppm config --example forearm > my.toml         a complete config to edit
  clppm config --schema                            every config key: type, default, range, meaning
  clppm trace --slab mua=10,mus=90,g=0.75,n=1.0,d=0.02
  clppm bench --quick                              photons/ms and gather pairs/s on this device
  clppm COMMAND --help                             that command's options

exit codes: 0 finished; 1 internal error; 2 bad input; 3 device error;
            130 interrupted (SIGINT); 143 terminated (SIGTERM)
"""


def build_parser() -> argparse.ArgumentParser:
    ap = Parser(prog="clppm", epilog=TOP_EPILOG,
                 description=__doc__.splitlines()[0] + "\n\nsample-point methods (render --method):\n"
                 + "".join(f"  {m}  {t}\n" for m, t in METHODS_HELP.items()))
    ap.add_argument("--version", action=_Version, help="clppm, pyopencl and the OpenCL platforms found")
    sub = ap.add_subparsers(dest="cmd", metavar="COMMAND", parser_class=Parser)
    tools.add_parsers(sub)
    render.add_parser(sub)
    for mod in (compare, reflectance, fit, bench):
        mod.add_parser(sub)
    return ap


def _device_line(e, verbose: bool) -> str:
    """A device error on one line: its indented detail lines only with --verbose."""
    lines = str(e).splitlines()
    if verbose:
        return str(e)
    return " ".join(ln.strip() for ln in lines if ln and not ln[0].isspace())


def main(argv=None) -> int:
    ap = build_parser()
    argv = sys.argv[1:] if argv is None else [str(x) for x in argv]
    if not argv:
        ap.print_help(sys.stderr)
        return EXIT["input"]
    a = ap.parse_args(argv)
    if a.cmd is None:
        ap.error("give a COMMAND")
    from ..output.checkpoint import CheckpointError
    from ..compute.device import DeviceError
    verbose = getattr(a, "verbose", False)
    from ..compute import devicecheck
    devicecheck.PROGRESS["on"] = not getattr(a, "quiet", False)
    try:
        old = signal.signal(signal.SIGTERM, _on_sigterm)
    except ValueError:                       # not the main thread
        old = None
    try:
        return a.func(a)
    except (ConfigError, CheckpointError, InputError) as e:
        print(f"{ERROR_PREFIX} {e}", file=sys.stderr)
        return EXIT["input"]
    except DeviceError as e:
        print(f"clppm: device error: {_device_line(e, verbose)}", file=sys.stderr)
        return EXIT["device"]
    except KeyboardInterrupt:
        print("clppm: interrupted", file=sys.stderr)
        return EXIT["sigint"]
    except _Terminated:
        print("clppm: terminated", file=sys.stderr)
        return EXIT["sigterm"]
    except Exception as e:                   # a bug: one line, the traceback with --verbose
        if verbose:
            import traceback
            traceback.print_exc()
        print(f"clppm: internal error: {type(e).__name__}: {' '.join(str(e).split())}"
              + ("" if verbose else " (--verbose shows the traceback)"), file=sys.stderr)
        return EXIT["internal"]
    finally:
        if old is not None:
            signal.signal(signal.SIGTERM, old)



def entry() -> None:
    """The ``clppm`` command: :func:`main`, whose exit code then ends the process without the
    interpreter's teardown (pip's PoCL 3.0 can abort there, "still have references to IRs",
    and SIGABRT's 134 would replace clppm's code).  Everything is written and closed by then."""
    code = main()
    for f in (sys.stdout, sys.stderr):
        try:
            f.flush()
        except (OSError, ValueError):       # a closed pipe: nothing more can be said
            pass
    os._exit(code)
