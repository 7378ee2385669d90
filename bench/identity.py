"""Hashes of small renders that a refactor must leave byte-identical: in-process, stopped and
resumed, on a 2-worker Dask cluster, the path tracer (straight and resumed) and paper mode.

    python bench/identity.py out/identity-before.json            # on the old tree
    python bench/identity.py out/identity-after.json --against out/identity-before.json

Each hash is SHA-256 over the EXR's channels (name and float32 pixels, not the file: the EXR
header holds no time stamp, but this keeps the check to the picture).  Runs the CLI as a user
does, under ``PYOPENCL_CTX`` (default: PoCL).  Exit 1 when ``--against`` finds a difference.
About a minute on 2 idle cores.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile

import numpy as np

BASE = ["forearm", "--resolution", "32x24", "--photons", "20000", "--seed", "3"]
PT = ["forearm_flat", "--integrator", "pt", "--resolution", "12x9", "--seed", "2",
      "--set", "render.pt_samples_per_pass=4"]


def exr_hash(path: str) -> str:
    import OpenEXR
    ch = OpenEXR.File(path).channels()
    h = hashlib.sha256()
    for k in sorted(ch):
        h.update(k.encode())
        h.update(np.ascontiguousarray(ch[k].pixels).tobytes())
    return h.hexdigest()[:16]


def device_index(spec: str) -> str:
    """``P:D`` of the device ``spec`` selects (``--devices`` takes indices)."""
    from clppm.device import list_devices, select_device
    d = select_device(spec)
    return next(f"{ip}:{idev}" for ip, idev, _, dev in list_devices() if dev.int_ptr == d.int_ptr)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", help="JSON file for the hashes")
    ap.add_argument("--against", help="an earlier run's JSON: report every difference")
    a = ap.parse_args(argv)
    clppm = os.path.join(os.path.dirname(sys.executable), "clppm")
    env = dict(os.environ, PYOPENCL_CTX=os.environ.get("PYOPENCL_CTX", "pocl"))
    tmp = tempfile.mkdtemp(prefix="clppm-identity-")
    pd = device_index(env["PYOPENCL_CTX"])

    def render(*args) -> bool:
        r = subprocess.run([clppm, "render", *args, "-q"], env=env, capture_output=True, text=True)
        if r.returncode:
            print(f"failed ({r.returncode}): clppm render {' '.join(args)}\n{r.stderr[-2000:]}", file=sys.stderr)
        return r.returncode == 0

    cases = {
        "in-process": [[*BASE, "--passes", "3", "-o", f"{tmp}/a.exr"]],
        "resumed": [[*BASE, "--passes", "2", "-o", f"{tmp}/b.exr"],
                    [*BASE, "--passes", "3", "-o", f"{tmp}/b.exr", "--resume", f"{tmp}/b.ckpt.npz"]],
        "dask, 2 workers": [[*BASE, "--passes", "3", "--devices", f"{pd},{pd}", "-o", f"{tmp}/c.exr"]],
        "path tracer": [[*PT, "--passes", "2", "-o", f"{tmp}/d.exr"]],
        "path tracer, resumed": [[*PT, "--passes", "1", "-o", f"{tmp}/e.exr"],
                                 [*PT, "--passes", "2", "-o", f"{tmp}/e.exr", "--resume", f"{tmp}/e.ckpt.npz"]],
        "paper mode": [["forearm", "--paper", "--resolution", "24x18", "--photons", "20000", "--passes", "2",
                        "--seed", "4", "-o", f"{tmp}/f.exr"]],
    }
    res = {}
    for name, runs in cases.items():
        if all(render(*r) for r in runs):
            res[name] = exr_hash(runs[-1][runs[-1].index("-o") + 1])
        print(f"{name:22s} {res.get(name, 'FAILED')}", flush=True)
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    with open(a.out, "w") as f:
        json.dump(res, f, indent=1)
    if not a.against:
        return 0 if len(res) == len(cases) else 1
    with open(a.against) as f:
        old = json.load(f)
    diff = [k for k in cases if res.get(k) != old.get(k)]
    print("same bytes in every case" if not diff else f"DIFFERENT: {', '.join(diff)}")
    return 1 if diff else 0


if __name__ == "__main__":
    sys.exit(main())
