"""Output paths the user names, checked before any work; a render's sidecars; its lock.

A render, trace or comparison that can only fail at its end (or at its first checkpoint,
minutes in) because a folder is missing or read-only wastes the run; these checks make that
failure one line at the start.  A path is checked by doing what the writer will do: make its
folder and a temporary file in it (``os.access`` says yes to root, and CI runs as root).  Folders
the check made are removed again: the writers make them when they write.

A render's outputs follow the extension of ``-o``: ``x.exr`` is the spectral + RGB EXR with the
sRGB PNG beside it (``x.png``); ``x.png`` is the PNG alone.  Either way the run report is
``x.json``, the checkpoint ``x.ckpt.npz``, the preview ``x.preview.png`` and the lock ``x.lock``:
no two of them can be the same file (:func:`render_outputs`).
"""
from __future__ import annotations

import errno
import json
import os
import socket
import tempfile
from dataclasses import dataclass

import numpy as np

from ..config import ConfigError

#: what ``-o`` may end in, and what it then writes
RENDER_FORMATS = {".exr": "the spectral + RGB EXR (with the sRGB PNG beside it)",
                  ".png": "the sRGB PNG alone"}


#: digits of the largest process id (Linux's pid_max is at most 4194304): the staging names hold one
PID_DIGITS = 7


class WriteError(OSError):
    """An output that could not be written once work had begun (a full disk, a lost mount): the
    file, the reason, and what the render keeps (``checkpoint``, ``checkpoint_pass``: set by
    the render loop; None when no checkpoint was written)."""

    def __init__(self, path: str, reason: str):
        self.path, self.reason = path, reason
        self.checkpoint: str | None = None
        self.checkpoint_pass: int | None = None
        super().__init__(f"cannot write {path} ({reason})")

    def kept(self) -> str:
        """What survives, one phrase."""
        if self.checkpoint and self.checkpoint_pass:
            return f"the checkpoint {self.checkpoint} (pass {self.checkpoint_pass}) is kept"
        return "no checkpoint was written yet"


def write_atomic(path: str, fill) -> None:
    """``fill(staging name)`` writes the file, which is then renamed over ``path``; any failure
    leaves no staging file and ``path`` as it was; an OSError becomes a :class:`WriteError`."""
    tmp = staging(path)
    try:
        fill(tmp)
        os.replace(tmp, path)
    except BaseException as e:           # a full disk, a second Ctrl-C: nothing half-written
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(e, OSError):
            raise WriteError(path, e.strerror or str(e)) from None
        raise


def staging(path: str, pid: int | None = None) -> str:
    """The temporary file a writer fills before renaming it over ``path`` (same folder, hidden):
    a kill or a full disk mid-write leaves the old file or nothing, never half a file."""
    d, name = os.path.split(path)
    return os.path.join(d, f".{name}.{os.getpid() if pid is None else pid}.tmp")


def name_max(folder: str) -> int:
    """The longest file name (bytes) the file system of ``folder`` (or its nearest existing
    ancestor) takes; 255 where it cannot be asked."""
    d = os.path.abspath(folder)
    while not os.path.isdir(d) and os.path.dirname(d) != d:
        d = os.path.dirname(d)
    try:
        return int(os.pathconf(d, "PC_NAME_MAX"))
    except (OSError, ValueError):
        return 255


def name_problem(path: str) -> str | None:
    """Why the file ``path`` or its staging name is too long for its folder, or None."""
    limit = name_max(os.path.dirname(os.path.abspath(path)) or ".")
    longest = os.path.basename(staging(path, 10 ** PID_DIGITS - 1))
    n = len(os.fsencode(longest))
    if n <= limit:
        return None
    return (f"the name is too long: its temporary file {longest[:12]}...{longest[-16:]} has {n} bytes, "
            f"the file system takes {limit}")


def writable_problem(path: str) -> str | None:
    """Why ``path`` cannot be written as a file (one phrase), or None: tried for real."""
    if not path:
        return "is empty"
    p = os.path.abspath(path)
    if os.path.isdir(p) or path.endswith(os.sep):
        return "is a folder"
    if os.path.exists(p) and not os.path.isfile(p):
        return "exists and is not a regular file"
    return name_problem(p) or _try_folder(os.path.dirname(p))


def folder_problem(path: str) -> str | None:
    """Why files cannot be written into the folder ``path`` (made if missing), or None."""
    if not path:
        return "is empty"
    p = os.path.abspath(path)
    if os.path.exists(p) and not os.path.isdir(p):
        return "is not a folder"
    return _try_folder(p)


def _try_folder(d: str) -> str | None:
    """Make folder ``d`` and a temporary file in it; undo both; the reason it failed, or None."""
    made = []
    q = d
    while not os.path.isdir(q):             # the folders that makedirs would create
        if os.path.lexists(q):
            return f"{q} is not a folder"
        made.append(q)
        parent = os.path.dirname(q)
        if parent == q:
            break
        q = parent
    try:
        os.makedirs(d, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=d, prefix=".clppm-check-")
        os.close(fd)
        os.unlink(tmp)
    except OSError as e:
        if e.errno == errno.ENAMETOOLONG:
            return f"a folder name in {d} is too long"
        if os.path.isdir(d):
            return f"folder {d} does not take new files ({e.strerror or e})"
        return f"folder {d} cannot be made ({e.strerror or e})"
    finally:
        for f in made:                       # deepest first
            try:
                os.rmdir(f)
            except OSError:
                pass
    return None


def check_folder(path: str | None, flag: str, source: str = "command line") -> None:
    """Raise :class:`ConfigError` if files cannot be written into the folder ``path``."""
    _refuse(folder_problem, path, flag, source)


def check_writable(path: str | None, flag: str, source: str = "command line") -> None:
    """Raise :class:`ConfigError` (one line: flag, path, reason) if ``path`` cannot be written."""
    _refuse(writable_problem, path, flag, source)


def _refuse(problem, path: str | None, flag: str, source: str) -> None:
    """Raise :class:`ConfigError` if ``problem(path)`` names one (nothing for no path)."""
    if path is None:
        return
    why = problem(path)
    if why:
        raise ConfigError(source, flag, path, f"cannot be written ({why})")


def check_plot(path: str | None, flag: str = "--plot", source: str = "command line") -> None:
    """A matplotlib figure file: an extension matplotlib can write, and a writable path."""
    if path is None:
        return
    from matplotlib.backend_bases import FigureCanvasBase
    ext = os.path.splitext(path)[1].lower().lstrip(".")
    kinds = FigureCanvasBase.get_supported_filetypes()
    if ext not in kinds:
        raise ConfigError(source, flag, path, "must end in one of "
                          + ", ".join("." + k for k in sorted(kinds)))
    check_writable(path, flag, source)


def check_distinct(source: str = "command line", **named: str | None) -> None:
    """No two of the named output paths (flag -> path) may be the same file."""
    seen = {}
    for flag, p in named.items():
        if not p:
            continue
        key = os.path.normcase(os.path.realpath(p))
        if key in seen:
            raise ConfigError(source, flag, p, f"is the same file as {seen[key]}; "
                              "one output would overwrite the other")
        seen[key] = flag


def render_format(out: str) -> str:
    """``"exr"`` or ``"png"``: what a render writes at ``out``; ValueError for anything else."""
    ext = os.path.splitext(out)[1].lower()
    if ext not in RENDER_FORMATS:
        raise ValueError(out)
    return ext[1:]


def render_outputs(out: str) -> dict[str, str]:
    """Every file a render with ``-o out`` writes (name -> path); all distinct by construction:
    the main file keeps its extension, every sidecar is ``base`` + a suffix no main file has."""
    base = os.path.splitext(out)[0]
    files = {"image": out}
    if render_format(out) == "exr":
        files["png"] = base + ".png"
    files.update(report=base + ".json", checkpoint=base + ".ckpt.npz",
                 preview=base + ".preview.png", lock=base + ".lock")
    return files


def check_render_output(out: str | None, flag: str = "-o/--output", source: str = "command line") -> None:
    """``-o``: an .exr or .png file name whose files can all be written."""
    if out is None:
        return
    if not out or out.endswith(os.sep) or os.path.isdir(out):
        raise ConfigError(source, flag, out, "must name a file ending in .exr or .png"
                          + (" (it is a folder)" if out and os.path.isdir(out) else ""))
    try:
        files = render_outputs(out)
    except ValueError:
        raise ConfigError(source, flag, out, "must end in " + " or ".join(
            f"{e} ({what})" for e, what in RENDER_FORMATS.items())) from None
    for p in files.values():
        check_writable(p, flag, source)


def check_outputs(out: str | None = None, checkpoint: str | None = None, **more: str | None) -> None:
    """Check a render's outputs: the image and its sidecars, the checkpoint, others."""
    check_render_output(out)
    check_writable(checkpoint, "checkpoint")
    for flag, p in more.items():
        check_writable(p, "--" + flag.replace("_", "-"))


# ----------------------------------------------------------------------------- the lock
def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:                  # someone else's process: alive
        return True
    return True


def _holder(lock: str) -> tuple[int, str] | None:
    """(pid, host) written in an existing lock file, or None if it holds neither."""
    try:
        with open(lock) as f:
            pid, host = (f.read().split() + ["", ""])[:2]
        return int(pid), host
    except (OSError, ValueError):
        return None


class OutputLock:
    """``x.lock`` beside a render's output, held for the whole run: a second writer of the same
    output is refused (one line, exit 2); a lock left by a dead process is taken over."""

    def __init__(self, out: str, flag: str = "-o/--output"):
        self.out, self.flag = out, flag
        self.path = render_outputs(out)["lock"]
        self.held = False

    def __enter__(self) -> "OutputLock":
        d = os.path.dirname(os.path.abspath(self.path))
        self.made = []                       # folders made for the lock: removed with it if empty
        while not os.path.isdir(d):
            self.made.append(d)
            d = os.path.dirname(d)
        os.makedirs(os.path.dirname(os.path.abspath(self.path)), exist_ok=True)
        me = f"{os.getpid()} {socket.gethostname()}\n"
        for _ in range(3):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                h = _holder(self.path)
                if h and (h[1] != socket.gethostname() or _alive(h[0])):
                    raise ConfigError("command line", self.flag, self.out,
                                      f"another clppm (pid {h[0]} on {h[1]}) is writing this output "
                                      f"(lock {self.path}); wait for it or choose another -o") from None
                try:                         # stale (its process is gone) or unreadable: take it over
                    os.unlink(self.path)
                except FileNotFoundError:
                    pass
                continue
            with os.fdopen(fd, "w") as f:
                f.write(me)
            self.held = True
            return self
        raise ConfigError("command line", self.flag, self.out, f"cannot take the lock {self.path}")

    def __exit__(self, *exc) -> None:
        if self.held and _holder(self.path) == (os.getpid(), socket.gethostname()):
            try:
                os.unlink(self.path)
            except OSError:
                pass
            for d in self.made:              # a render that wrote nothing leaves nothing
                try:
                    os.rmdir(d)
                except OSError:
                    break
        self.held = False


def output_set(out: str) -> list[str]:
    """Every file that can belong to the render named by ``out`` (NAME.*): both image formats,
    the report, the checkpoint and the preview, whatever ``out``'s own format writes."""
    base, ext = os.path.splitext(out)
    files = render_outputs(out)
    other = base + (".png" if ext.lower() == ".png" else ".exr")
    images = [out, files.get("png", other)]
    if ext.lower() == ".png":
        images = [base + ".exr", out]
    return images + [files[k] for k in ("report", "checkpoint", "preview")]


def _same(a: str, b: str) -> bool:
    return os.path.normcase(os.path.realpath(a)) == os.path.normcase(os.path.realpath(b))


@dataclass
class OutputSetPlan:
    """What a render does to the files already under its NAME.*: ``replace`` are removed before
    work (``--force``: the whole earlier set goes, so no file of it outlives the new render)."""

    out: str
    replace: list[str]

    def apply(self) -> str | None:
        """Remove the files to replace; the one line that says so, or None."""
        for p in self.replace:
            try:
                os.unlink(p)
            except FileNotFoundError:
                pass
        if not self.replace:
            return None
        return (f"--force: removed the earlier render's {', '.join(self.replace)} "
                f"(the whole set NAME.* is this render's)")


def check_output_set(out: str, resume: str | None, force: bool) -> OutputSetPlan:
    """An output set is one render.  A fresh render to a NAME with files of an earlier render is
    refused unless ``--force`` (then all of them are replaced); ``--resume`` of NAME's own
    checkpoint continues that render, and is refused when NAME holds an image this run would not
    rewrite (``-o NAME.png`` beside an earlier ``NAME.exr``)."""
    files = render_outputs(out)
    ck = files["checkpoint"]
    existing = [p for p in output_set(out) if os.path.lexists(p)]
    if resume and os.path.exists(ck) and os.path.exists(resume) and os.path.samefile(resume, ck):
        written = set(files.values())
        stale = [p for p in existing if p not in written]
        if stale:
            raise ConfigError("command line", "-o/--output", out,
                              f"{', '.join(stale)} of this render would not be rewritten by -o {out} and "
                              f"would go stale: resume with -o {stale[0]}")
        return OutputSetPlan(out, [])
    if not existing:
        return OutputSetPlan(out, [])
    if force:
        return OutputSetPlan(out, existing)
    if ck in existing:
        check_checkpoint_free(out, resume, force)
    raise ConfigError("command line", "-o/--output", out,
                      f"{', '.join(existing)} of an earlier render exist and would be overwritten or "
                      "left beside this one: give --force to replace the whole set, or another -o")


def check_inputs_not_outputs(out: str, **inputs: str | None) -> None:
    """No input (a config, a height map, a checkpoint other than NAME's own) may be a file the
    render writes: it would be overwritten."""
    outs = output_set(out) + [render_outputs(out)["lock"]]
    own_ck = render_outputs(out)["checkpoint"]
    for flag, p in inputs.items():
        if not p:
            continue
        for o in outs:
            if _same(p, o) and not (flag == "--resume" and o == own_ck):
                raise ConfigError("command line", flag, p, f"is also an output of -o {out} ({o}) "
                                                           "and would be overwritten; give another -o")


def check_checkpoint_free(out: str, resume: str | None, force: bool) -> None:
    """A fresh render must not replace the checkpoint of another run without ``--force``;
    ``--resume`` of that same checkpoint continues it."""
    ck = render_outputs(out)["checkpoint"]
    if force or not os.path.exists(ck):
        return
    if resume and os.path.exists(resume) and os.path.samefile(resume, ck):
        return
    p = pass_index(ck)
    held = f" (pass {p})" if p is not None else ""
    raise ConfigError("command line", "-o/--output", out,
                      f"the checkpoint {ck} of an earlier render{held} would be replaced: continue it "
                      f"with --resume {ck}, or give --force to start over")


def pass_index(path: str) -> int | None:
    """The passes the checkpoint at ``path`` holds (its header alone; :mod:`clppm.output.checkpoint`
    writes it), or None if it cannot be read."""
    try:
        with np.load(path, allow_pickle=False) as z:
            v = json.loads(str(z["header"]))["state"]["pass_index"]
        return v if isinstance(v, int) else None
    except Exception:                    # any unreadable file: the caller says what it needs
        return None
