"""What the extra seeds of the manifold connection add to the relief forearm's image
(docs/relief.md): the same paths (seed, pass) traced with K = 0, 8, 16 seeds beyond the flat one
per connection; the image sums' ratios are the light carried by the solutions the fewer seeds
miss (the paths' noise cancels, only the connections differ).  Small: 8x6 pixels, 64 paths each.

    python bench/mnee_seeds.py
"""
import os
import sys
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
os.chdir(ROOT)
import time
from clppm import config as C, volume, pathtracer as pt
from clppm.device import open_device
dev = open_device(None)
c = C.load("configs/forearm.toml"); c["camera"]["resolution"] = [8, 6]; c["render"]["pt_samples_per_pass"] = 64; c["render"]["pt_relief"] = True
c["render"]["specular"] = False
vol = volume.build(c)
res = {}
for K in (0, 8, 16):
    tr = pt.PathTracer(dev, vol, c); tr.e["mnee_seeds"] = K
    t0 = time.perf_counter(); tr.run_pass(0); dt = time.perf_counter() - t0
    s = tr.state_arrays()["pix_sum"]
    res[K] = s
    m = pt.mnee_report(tr.mnee_totals())
    print(K, f"{tr.npix*tr.nspp/dt:.0f} paths/s", "sum", s.sum(), "solutions/conn", m["mean_solutions"], "solved", m["success_rate"], flush=True)
for K in (8, 16):
    print(f"image sum K={K} / K=0: {res[K].sum()/res[0].sum():.4f}; per band group (first/last third):",
          res[K][:, :27].sum()/res[0][:, :27].sum(), res[K][:, 54:].sum()/res[0][:, 54:].sum())
