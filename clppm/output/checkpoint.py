"""Render checkpoints: the pass index and the device state, written atomically.

A checkpoint is one ``.npz`` (numpy arrays + a JSON header).  It is written to a
temporary file in the same folder, flushed to disk and renamed over the old one, so a
kill at any moment leaves either the previous checkpoint or the new one, never half of
one.  Loading checks that the checkpoint was made by the same parameters (everything but
the number of passes), the same device and the same eye pass.

A distributed run (:mod:`clppm.run.executor`) writes the same file.  Its reduced sums cover the
passes before ``pass_index`` (whole chunks, added in order); chunks that finished ahead of a
missing one are kept apart, unreduced, as ``held`` (their passes and counts in the header,
their sums in ``held_pix``/``held_pairs``).  Those are optional: an in-process resume ignores
them and simply runs those passes again.
"""
from __future__ import annotations

import json
import os
import zipfile
import zlib

import numpy as np

from . import paths

VERSION = 2
#: the arrays of a PPM checkpoint
ARRAYS = ("pt_R", "pt_N", "R0", "pix_acc", "chunk_acc", "pix_pairs")
HELD = ("held_pix", "held_pairs")      # optional: chunk sums not yet reduced (distributed runs)
#: the arrays of a path-tracer checkpoint
PT_ARRAYS = ("pix_sum", "pix_sq", "pix_stats", "pix_bins")


class CheckpointError(ValueError):
    pass


def default_path(out: str) -> str:
    base, _ = os.path.splitext(out)
    return base + ".ckpt.npz"


def save(path: str, meta: dict, state: dict, arrays: dict, integrator: str = "ppm") -> None:
    """A checkpoint: ``state`` (JSON-able) and the named arrays; PPM's are :data:`ARRAYS` (and
    :data:`HELD` when ``state["held"]`` lists chunks), the path tracer's :data:`PT_ARRAYS`."""
    if integrator == "pt":
        header = {"version": VERSION, "integrator": "pt", "meta": meta, "state": state}
        _write(path, header, {k: np.asarray(arrays[k]) for k in PT_ARRAYS})
        return
    header = {"version": VERSION, "meta": meta,
              "state": {k: state[k] for k in ("pass_index", "emitted_total", "store_zmin",
                                              "tallies_emitted", "stats", "timing")}}
    held = {}
    if state.get("held"):
        header["state"]["held"] = [dict(h, tallies=[[str(v) for v in row] for row in h["tallies"]])
                                   for h in state["held"]]
        held = {k: np.asarray(arrays[k]) for k in HELD}
    tallies = np.array([[str(v) for v in row] for row in state["tallies"]])   # exact big ints
    _write(path, header, {**{k: np.asarray(arrays[k]) for k in ARRAYS}, "tallies": tallies, **held})


def _write(path: str, header: dict, arrays: dict) -> None:
    """Atomically: a temporary file in the same folder, flushed, renamed over the old one (a full
    disk keeps the old checkpoint and raises :class:`clppm.output.paths.WriteError` naming the
    file)."""
    d = os.path.dirname(os.path.abspath(path))
    os.makedirs(d, exist_ok=True)

    def fill(tmp):
        with open(tmp, "wb") as f:
            np.savez(f, header=np.array(json.dumps(header, default=str)), **arrays)
            f.flush()
            os.fsync(f.fileno())
    paths.write_atomic(path, fill)
    _fsync_dir(d)


def _fsync_dir(d: str) -> None:
    """Make the rename itself durable (POSIX); a no-op where folders cannot be opened."""
    try:
        fd = os.open(d, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _read(path: str, names: tuple[str, ...], want: str) -> tuple[dict, dict, callable]:
    """Header and arrays of a checkpoint file, or a one-line CheckpointError."""
    name = os.path.basename(path)
    if not os.path.isfile(path):
        raise CheckpointError(f"checkpoint {name}: file not found ({path!r})")

    def corrupt(why):
        return CheckpointError(f"checkpoint {name} is corrupt or not a clppm checkpoint ({why})")

    if os.path.getsize(path) == 0:
        raise corrupt("empty file")
    try:
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):      # a lone .npy array
            raise ValueError("not a .npz archive")
        with z:
            header = json.loads(str(z["header"]))
            kind = header.get("integrator", "ppm") if isinstance(header, dict) else "ppm"
            if kind != want:
                raise CheckpointError(f"checkpoint {name} was made by the {kind} integrator; "
                                      f"resume it with --integrator {kind}")
            arrays = {k: z[k] for k in names}
            arrays.update({k: z[k] for k in HELD if k in z.files})
    except ValueError as e:
        if isinstance(e, CheckpointError):
            raise
        if "pickle" in str(e):           # numpy's guess for bytes it does not recognise
            raise corrupt("not a .npz archive") from None
        raise corrupt(_one_line(e)) from None
    except (OSError, KeyError, zipfile.BadZipFile, EOFError, zlib.error, UnicodeDecodeError) as e:
        raise corrupt(_one_line(e) or type(e).__name__) from None
    return header, arrays, corrupt


def load(path: str, meta: dict | None = None, integrator: str = "ppm") -> dict:
    """A checkpoint's state and arrays, checked: the integrator that made it, its version, the
    render it belongs to (``meta``: everything but the pass count) and its arrays' shapes."""
    name = os.path.basename(path)
    header, arrays, corrupt = _read(path, PT_ARRAYS if integrator == "pt" else ARRAYS + ("tallies",),
                                    integrator)
    if not isinstance(header, dict):
        raise corrupt("header is not a table")
    if header.get("version") != VERSION:
        raise CheckpointError(f"checkpoint {name} has version {header.get('version')!r}, "
                              f"expected {VERSION}")
    if not isinstance(header.get("meta"), dict) or not isinstance(header.get("state"), dict):
        raise corrupt("header without meta or state")
    if meta is not None and header["meta"] != meta:
        raise _mismatch(name, [d.removeprefix("config.") for d in _diff(header["meta"], meta)])
    st = dict(header["state"])
    if integrator == "pt":
        return _pt_state(name, st, arrays, meta, corrupt)
    missing = [k for k in ("pass_index", "emitted_total", "store_zmin", "tallies_emitted", "stats",
                           "timing") if k not in st]
    if missing:
        raise corrupt(f"state lacks {', '.join(missing)}")
    st.update({k: v for k, v in arrays.items() if k != "tallies"})
    try:
        st["tallies"] = [[int(v) for v in row] for row in arrays["tallies"].tolist()]
    except (TypeError, ValueError) as e:
        raise corrupt(f"tallies: {_one_line(e)}") from None
    _check_held(name, st, arrays, corrupt)
    if not isinstance(st["pass_index"], int) or st["pass_index"] < (0 if st["held"] else 1):
        raise corrupt(f"pass index {st['pass_index']!r}")
    for k in ("pt_R", "pt_N", "R0", "pix_acc", "chunk_acc"):
        if st[k].dtype.kind not in "fiu" or not np.all(np.isfinite(st[k])):
            raise CheckpointError(f"checkpoint {name} holds non-finite or non-numeric values in {k}")
    if meta is not None:
        _check_shapes(name, st, meta)
    return st


def _check_held(name: str, st: dict, arrays: dict, corrupt) -> None:
    """``st["held"]``: the held chunks (each with exact int tallies and its sums), or []."""
    held = st.get("held") or []
    try:
        for h in held:
            h["tallies"] = [[int(v) for v in row] for row in h["tallies"]]
            h["passes"] = [int(p) for p in h["passes"]]
            h["emitted"] = [int(e) for e in h["emitted"]]
            h["stored"] = int(h["stored"])
    except (TypeError, ValueError, KeyError) as e:
        raise corrupt(f"held chunks: {_one_line(e) or type(e).__name__}") from None
    if held:
        if any(k not in arrays for k in HELD):
            raise corrupt("held chunks without their sums")
        pix, pairs = arrays["held_pix"], arrays["held_pairs"]
        if (pix.ndim != 2 or pairs.ndim != 2 or len(pix) != len(held) or len(pairs) != len(held)
                or pix.shape[1] != arrays["pix_acc"].size or pairs.shape[1] != arrays["pix_pairs"].size):
            raise CheckpointError(f"checkpoint {name} is corrupt: held chunk sums of shape "
                                  f"{pix.shape}, {pairs.shape} for {len(held)} chunks")
        if pix.dtype.kind != "f" or not np.all(np.isfinite(pix)):
            raise CheckpointError(f"checkpoint {name} holds non-finite or non-numeric values in held_pix")
    st["held"] = held


def _one_line(e) -> str:
    return " ".join(str(e).split())


def _check_shapes(name: str, st: dict, meta: dict) -> None:
    """Array sizes must match the render the checkpoint claims to belong to."""
    try:
        w, h = meta["config"]["camera"]["resolution"]
        sp = meta["config"]["spectrum"]
        nb = int(round((sp["stop_nm"] - sp["start_nm"]) / sp["step_nm"])) + 1
        npts = int(meta["npoints"])
    except (KeyError, TypeError, ValueError):
        return                              # not a render's identity: nothing to compare with
    # with the global radius R = R0 and N = 0 at every point: no per-point state but R0
    per_point = (0,) if meta["config"].get("render", {}).get("radius") == "global" else (npts,)
    want = {"pt_R": per_point, "pt_N": per_point, "R0": (npts,), "pix_acc": (w * h, nb),
            "chunk_acc": (w * h, nb), "pix_pairs": (w * h,)}
    for k, shape in want.items():
        if k in ("pix_acc", "chunk_acc") and tuple(st[k].shape) == (0, nb):
            continue                        # a sum the render had not made yet: zeros
        if tuple(st[k].shape) != shape:
            raise CheckpointError(f"checkpoint {name} is corrupt: {k} has shape {tuple(st[k].shape)}, "
                                  f"this render needs {shape}")


def _diff(a, b, path="") -> list[str]:
    """The keys (dotted, list items by index: ``layer.0.thickness_um``) where a and b differ."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            out += _diff(a.get(k), b.get(k), f"{path}.{k}" if path else k)
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b) \
            and any(isinstance(x, (dict, list)) for x in a + b):
        out = []
        for i, (x, y) in enumerate(zip(a, b)):
            out += _diff(x, y, f"{path}.{i}")
        return out
    if a == b:
        return []
    if isinstance(a, list) and isinstance(b, list) and len(a) != len(b):
        return [f"{path} (checkpoint {len(a)} items, now {len(b)})"]
    return [f"{path} (checkpoint {_short(a)}, now {_short(b)})"]


def _short(v, limit: int = 40) -> str:
    r = repr(v)
    return r if len(r) <= limit else r[:limit - 3] + "..."


def _mismatch(name: str, diffs: list[str]) -> CheckpointError:
    """One short line naming the differing keys (their values while the line stays short)."""
    line = "; ".join(diffs)
    if len(line) > 240:
        keys = [d.split(" (", 1)[0] for d in diffs]
        line = ", ".join(keys[:12]) + (f" and {len(keys) - 12} more" if len(keys) > 12 else "")
    return CheckpointError(f"checkpoint {name} was made with different parameters: {line}")


def header_meta(path: str) -> dict | None:
    """The run identity a checkpoint was written with (its header alone), or None if unreadable."""
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["header"]))["meta"]
        return meta if isinstance(meta, dict) else None
    except Exception:                    # unreadable: load() says why when the run starts
        return None


def check_matches(path: str, **part) -> None:
    """Before any work: the parts of the run identity known already (``config``, ``device``)
    must be the checkpoint's; the rest (the eye pass's counts) is checked by :func:`load`."""
    if not os.path.isfile(path):
        raise CheckpointError(f"checkpoint {os.path.basename(path)}: file not found ({path!r})")
    meta = header_meta(path)
    if meta is None:
        return
    diffs = []
    for k, v in part.items():
        diffs += _diff(meta.get(k), v, k)
    if diffs:
        raise _mismatch(os.path.basename(path), [d.removeprefix("config.") for d in diffs])


def _pt_state(name: str, st: dict, arrays: dict, meta: dict | None, corrupt) -> dict:
    """A path-tracer checkpoint: pass index, timing and the per-pixel sums."""
    if not isinstance(st.get("pass_index"), int) or st["pass_index"] < 1:
        raise corrupt(f"pass index {st.get('pass_index')!r}")
    st.update(arrays)
    for k in ("pix_sum", "pix_sq", "pix_bins"):
        if st[k].dtype != np.float64 or not np.all(np.isfinite(st[k])):
            raise CheckpointError(f"checkpoint {name} holds non-finite or non-numeric values in {k}")
    if meta is not None:
        npix, nb, nbin = meta["npix"], meta["nb"], meta["nbin"]
        want = {"pix_sum": (npix, nb), "pix_sq": (npix, nb), "pix_stats": (npix, 4),
                "pix_bins": (npix, nbin)}
        for k, shape in want.items():
            if tuple(st[k].shape) != shape:
                raise CheckpointError(f"checkpoint {name} is corrupt: {k} has shape "
                                      f"{tuple(st[k].shape)}, this render needs {shape}")
    return st
