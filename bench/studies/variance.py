"""Where the noise of one image comes from: controlled runs that remove one source at a time.

Each row renders the forearm at 80x60 twice (two photon seeds) with the same number of passes
and reports the per-pixel noise of one image (bench/studies/noise.py's measure: relative RMS of Y and
mean CIEDE2000, from the two images) and the seconds.  Starting from the paper's mode, one
thing changes per row:

* eye placement fixed: both images use the same eye-pass random numbers (the sample points of
  schemes d-f are Poisson), only the photons differ;
* thinning: each event stored with probability 0.1 and weight 10 (ten times the paths per pass
  for the same stored budget: decorrelates the events of one path);
* isotropic gather phase (a diagnostic, biased): the gather weighs every photon by 1/(4 pi)
  instead of HG(g) toward the eye;
* per-point radius -> global radius schedule (radius randomness);
* the estimator (sphere -> beam), the bands per path (1 -> 9), importance-driven storage,
  QMC emission: the new default's parts, one at a time and together.

The "variance removed" column is 1 - (noise / baseline noise)^2 at equal passes (a positive
number: the share of the baseline's variance that source was).

    python bench/studies/variance.py [--passes 40]
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time


ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))   # bench/studies/noise.py

from clppm import config as C
from clppm.integrators import photonpass, ppm
from clppm.run import progressive
from clppm.scene import volume  # noqa: E402
from clppm.scene.bands import Bands                                        # noqa: E402
from clppm.request import RenderRequest                               # noqa: E402
from clppm.analysis.reference import skin_mask                                # noqa: E402
from noise import two_seed_noise                          # noqa: E402

PAPER = dict(C.PAPER_MODE)
ROWS = [
    ("paper mode (baseline)", {}, {}),
    ("eye placement fixed", {}, {"same_eye": True}),
    ("thinning: store 1 event in 10, weight 10", {"storage": "importance", "store_scale": 1e-12,
                                                   "store_min": 0.1}, {}),
    ("isotropic gather phase (biased diagnostic)", {}, {"iso_phase": True}),
    ("isotropic phase + thinning (biased diagnostic)", {"storage": "importance", "store_scale": 1e-12,
                                                        "store_min": 0.1}, {"iso_phase": True}),
    ("global radius instead of per point", {"radius": "global"}, {}),
    ("9 bands per path", {"bands_per_path": 9}, {}),
    ("beam estimator", {"estimator": "beam"}, {}),
    ("importance-driven storage", {"storage": "importance"}, {}),
    ("QMC emission", {"emission": "qmc"}, {}),
    ("all of the default's parts (the default)", "default", {}),
]


def render_one(cfg: dict, seed: int, eye_seed: int, passes: int, iso_phase: bool, dev):
    """The in-process PPM run stepped by hand, with the eye pass's seed and the gather's phase controllable."""
    import pyopencl as cl
    c = C.override(cfg, "render", "seed", eye_seed)
    req = RenderRequest(c)
    sc = ppm.Pipeline.build(req, dev)
    sc.pp = photonpass.PhotonPass.of_config(dev, sc.vol, c, capacity=sc.capacity, vbuf=sc.vbuf,
                                 bands=Bands.from_config(c), seed=seed)
    rc = c["render"]
    sc.pp.set_storage(rc["storage"], sc.eye.cone_deg, rc["store_scale"], rc["store_min"])
    sc.pp.set_emission(rc["emission"])
    if iso_phase:
        t = sc.vol.hg_table()
        t[:, 0], t[:, 1], t[:, 2] = 1.0, 0.0, 1.0 / (4 * math.pi)
        sc.hgtab = cl.Buffer(dev.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=t)
    t0 = time.perf_counter()
    run = progressive.PPMRun.start(sc, progressive.run_identity(req, sc), None, t0)
    for _ in range(passes):
        run.step()
    res = run.image(interrupted=False)
    return res, time.perf_counter() - t0, sum(run.emitted)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config", nargs="?", default=os.path.join(ROOT, "configs", "forearm.toml"))
    ap.add_argument("--passes", type=int, default=40, help="paper-mode passes per image")
    ap.add_argument("--default-passes", type=int, default=4, help="passes per image for rows with "
                    "importance storage (a pass is ~70x more paths)")
    ap.add_argument("--method", default="e")
    ap.add_argument("-o", "--out", default="out/bench")
    a = ap.parse_args(argv)
    from clppm.compute.device import open_device
    dev = open_device(None)
    cfg = C.load(a.config)
    cfg = C.override(cfg, "camera", "resolution", [80, 60])
    cfg = C.override(cfg, "render", "method", a.method)
    cfg = C.override(cfg, "render", "checkpoint_every", 0)
    base = C.paper_mode(cfg)
    rows, t_all = [], time.perf_counter()
    with volume.memoised():
        mask = skin_mask(base, dev)
        for name, edits, opts in ROWS:
            c = cfg if edits == "default" else base
            if edits != "default":
                for k, v in edits.items():
                    c = C.override(c, "render", k, v)
            # importance-driven storage makes a pass ~70x more paths; thinning only 10x: equal passes
            long_pass = c["render"]["storage"] == "importance" and c["render"]["store_scale"] > 1e-6
            passes = a.default_passes if long_pass else a.passes
            imgs = []
            for s in (101, 202):
                eye_seed = 7 if opts.get("same_eye") else s
                res, secs, emitted = render_one(c, s, eye_seed, passes, opts.get("iso_phase", False), dev)
                imgs.append((res, secs, emitted))
            n = two_seed_noise(imgs[0][0].xyz, imgs[1][0].xyz, mask, imgs[0][0].exposure)
            secs = 0.5 * (imgs[0][1] + imgs[1][1])
            row = {"row": name, "passes": passes, "seconds": secs, "paths": imgs[0][2], **n}
            rows.append(row)
            print(f"  {name}: {passes} passes, {secs:.1f} s, {row['paths']:,} paths: noise Y "
                  f"{100 * n['noise_Y']:.2f} %, dE00 {n['noise_dE']:.2f}", flush=True)
    b = rows[0]
    lines = ["| run (80x60, method " + a.method + ") | passes | paths | seconds | noise Y | noise ΔE00 | "
             "Y variance removed | ΔE² removed | Y noise² × paths | ΔE² × paths |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        same = r["passes"] == b["passes"]
        rem_y = 1 - (r["noise_Y"] / b["noise_Y"]) ** 2 if same else float("nan")
        rem_e = 1 - (r["noise_dE"] / b["noise_dE"]) ** 2 if same else float("nan")
        lines.append(f"| {r['row']} | {r['passes']} | {r['paths']:,} | {r['seconds']:.1f} | "
                     f"{100 * r['noise_Y']:.2f} % | {r['noise_dE']:.2f} | "
                     + ("–" if math.isnan(rem_y) else f"{100 * rem_y:+.0f} %") + " | "
                     + ("–" if math.isnan(rem_e) else f"{100 * rem_e:+.0f} %") + " | "
                     f"{r['noise_Y'] ** 2 * r['paths']:.0f} | {r['noise_dE'] ** 2 * r['paths'] / 1e6:.1f}·10⁶ |")
    md = "\n".join(lines)
    print(md)
    os.makedirs(a.out, exist_ok=True)
    with open(os.path.join(a.out, "variance.md"), "w") as f:
        f.write(md + "\n")
    with open(os.path.join(a.out, "variance.json"), "w") as f:
        json.dump({"device": dev.info(), "rows": rows, "wall_seconds": time.perf_counter() - t_all}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
