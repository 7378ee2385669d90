"""Render checkpoints: the pass index and the device state, written atomically.

A checkpoint is one ``.npz`` (numpy arrays + a JSON header).  It is written to a
temporary file in the same folder, flushed to disk and renamed over the old one, so a
kill at any moment leaves either the previous checkpoint or the new one, never half of
one.  Loading checks that the checkpoint was made by the same parameters (everything but
the number of passes), the same device and the same eye pass.
"""
from __future__ import annotations

import json
import os
import zipfile

import numpy as np

VERSION = 1


class CheckpointError(ValueError):
    pass


def default_path(out: str) -> str:
    base, _ = os.path.splitext(out)
    return base + ".ckpt.npz"


def save(path: str, meta: dict, state: dict, pt_R, pt_N, pix_acc, pix_pairs) -> None:
    header = {"version": VERSION, "meta": meta,
              "state": {k: state[k] for k in ("pass_index", "emitted_total", "store_zmin",
                                              "tallies_emitted", "stats", "timing")}}
    tallies = np.array([[str(v) for v in row] for row in state["tallies"]])   # exact big ints
    d = os.path.dirname(os.path.abspath(path))
    os.makedirs(d, exist_ok=True)
    tmp = os.path.join(d, f".{os.path.basename(path)}.{os.getpid()}.tmp")
    with open(tmp, "wb") as f:
        np.savez(f, header=np.array(json.dumps(header, default=str)), pt_R=np.asarray(pt_R),
                 pt_N=np.asarray(pt_N), pix_acc=np.asarray(pix_acc), pix_pairs=np.asarray(pix_pairs),
                 tallies=tallies)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def load(path: str, meta: dict | None = None) -> dict:
    name = os.path.basename(path)
    if not os.path.isfile(path):
        raise CheckpointError(f"checkpoint {name}: file not found ({path})")
    try:
        with np.load(path, allow_pickle=False) as z:
            header = json.loads(str(z["header"]))
            arrays = {k: z[k] for k in ("pt_R", "pt_N", "pix_acc", "pix_pairs", "tallies")}
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, json.JSONDecodeError, EOFError) as e:
        raise CheckpointError(f"checkpoint {name} is corrupt or not a clppm checkpoint ({e})") from None
    if header.get("version") != VERSION:
        raise CheckpointError(f"checkpoint {name} has version {header.get('version')}, expected {VERSION}")
    if meta is not None and header["meta"] != meta:
        diffs = _diff(header["meta"], meta)
        raise CheckpointError(f"checkpoint {name} was made with different parameters: "
                              + "; ".join(diffs[:8]))
    st = dict(header["state"])
    st.update({k: v for k, v in arrays.items() if k != "tallies"})
    st["tallies"] = [[int(v) for v in row] for row in arrays["tallies"].tolist()]
    if not (np.all(np.isfinite(st["pt_R"])) and np.all(np.isfinite(st["pix_acc"]))):
        raise CheckpointError(f"checkpoint {name} holds non-finite values")
    return st


def _diff(a, b, path="") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            out += _diff(a.get(k), b.get(k), f"{path}.{k}" if path else k)
        return out
    return [] if a == b else [f"{path}: checkpoint {a!r}, now {b!r}"]
