"""What the other light paths add to the relief forearm's image (docs/relief.md): the same paths
(seed, pass; the connections draw their trials from their own random stream) traced with the
flat-seeded solution alone (0 trials) and with specular manifold sampling (1 and 2 random trials
per connection); the image sums' ratios are the light carried by the solutions the flat seed
misses, with the noise the trials add.  Small: 8x6 pixels, 64 paths each by default.

    python bench/studies/mnee_sms.py [--spp 64] [--passes 4]
"""
import argparse
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)
from clppm import config as C
from clppm.scene import volume
from clppm.integrators import pathtracer as pt   # noqa: E402
from clppm.compute.device import open_device                       # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--passes", type=int, default=4)
    ap.add_argument("--device", default=None)
    a = ap.parse_args(argv)
    dev = open_device(a.device)
    c = C.load(os.path.join(ROOT, "configs", "forearm.toml"))
    c["camera"]["resolution"] = [8, 6]
    c["render"].update(pt_samples_per_pass=a.spp, specular=False)
    vol = volume.build(c)
    sums, groups = {}, {}
    for K in (0, 1, 2):
        tr = pt.PathTracer.of_config(dev, vol, c)
        tr.e["mnee_trials"] = K
        t0 = time.perf_counter()
        per_pass = []
        for p in range(a.passes):
            before = tr.state_arrays()["pix_sum"].copy()
            tr.run_pass(p)
            per_pass.append(tr.state_arrays()["pix_sum"] - before)
        dt = time.perf_counter() - t0
        m = pt.mnee_report(tr.mnee_totals())
        sums[K] = np.array([x.sum() for x in per_pass])
        groups[K] = sum(per_pass)
        print(f"trials {K}: {tr.npix * tr.nspp * a.passes / dt:.0f} paths/s, found {m['success_rate']:.5f}, "
              f"flat-seeded {m['flat_seeded_rate']:.5f}, other solutions {m['other_solution_share']:.4f} "
              f"per connection, clamped {m['clamped_share']:.4f} of them, "
              f"{m['trials_per_connection']:.3f} trials per connection", flush=True)
    nb = groups[0].shape[-1]
    for K in (1, 2):
        r = sums[K] / sums[0]
        print(f"image sum trials={K} / flat-seeded only: {sums[K].sum() / sums[0].sum():.4f} "
              f"(per pass {np.round(r, 4).tolist()}, +- {r.std(ddof=1) / np.sqrt(len(r)):.4f}); "
              f"first third of the bands {groups[K][:, :nb // 3].sum() / groups[0][:, :nb // 3].sum():.4f}, "
              f"last third {groups[K][:, 2 * nb // 3:].sum() / groups[0][:, 2 * nb // 3:].sum():.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
