"""Worker for test_implementations.py: on the device PYOPENCL_CTX names, trace a slab and render
a small forearm at two seeds (the first twice); write the tallies and images to one .npz.

    python tests/xdevice_worker.py OUT.npz
"""
import json
import sys

import numpy as np

from clppm import config
from clppm.compute import device
from clppm.integrators import photonpass
from clppm.run import entry
from clppm.checks import tiny
from clppm.scene import volume

SLAB = "mua=10,mus=90,g=0.75,n=1.4,d=0.02"
SLAB_PHOTONS = 40_000
SEEDS = (1, 2)


def main(out: str) -> None:
    dev = device.open_device(None)
    cfg = config.slab_config(SLAB)
    cfg = config.override(cfg, "render", "seed", 11)
    pp = photonpass.PhotonPass.of_config(dev, volume.build(cfg), cfg)
    rep = photonpass.trace_report(pp, SLAB_PHOTONS, batches=20)
    scene = tiny.tiny_config(size_mm=4.0, resolution=(40, 30), step_nm=40.0, photons=20_000)
    scene = config.override(scene, "render", "passes", 2)
    imgs = {}
    for i, seed in enumerate((*SEEDS, SEEDS[0])):
        res = entry.render(config.override(scene, "render", "seed", seed), dev=dev)
        imgs[f"img{i}"] = res.spectral.astype(np.float64)
    info = {"impl": device.implementation(dev.device), "device": dev.name,
            "tally": {k: rep[k] for k in ("specular", "Rd", "Tt", "A")},
            "tally_se": {k: rep[k + "_se"] for k in ("specular", "Rd", "Tt", "A")}}
    np.savez(out, info=json.dumps(info), wl=res.wl, **imgs)


if __name__ == "__main__":
    main(sys.argv[1])
