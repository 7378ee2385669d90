"""Same physics on every OpenCL implementation installed (PoCL, Intel's CPU runtime, ...).

Each implementation, in its own process (tests/xdevice_worker.py), traces a slab and renders a
small forearm at seeds 1 and 2 (and 1 again).  Transcendentals round differently, so paths
diverge and the images differ by noise: per band group and 10x10 block, the difference between
implementations at the same seed must be of the size of the difference between two seeds on one
implementation (the seed-to-seed spread, pooled over implementations, is the yardstick), the slab
tallies within 3 sigma, and every implementation byte-identical with itself for the same seed.
Skipped where fewer than two implementations can build kernels (CI installs two)."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

pytestmark = pytest.mark.once      # runs every implementation in its own processes

HERE = os.path.dirname(os.path.abspath(__file__))
BLOCK = 10
GROUPS = 3


def _implementations() -> dict[str, str]:
    from clppm.compute.device import device_problem, implementation, list_devices
    out = {}
    for ip, idev, _, d in list_devices():
        impl = implementation(d)
        if impl not in out and impl != "oclgrind" and device_problem(d, f"{ip}:{idev}") is None:
            out[impl] = f"{ip}:{idev}"
    return out


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    impls = _implementations()
    if len(impls) < 2:
        pytest.skip(f"only {sorted(impls)} installed: needs two OpenCL implementations")
    tmp = tmp_path_factory.mktemp("xdev")
    out = {}
    for impl, spec in impls.items():
        path = tmp / f"{impl}.npz"
        env = {**os.environ, "PYOPENCL_CTX": spec}
        r = subprocess.run([sys.executable, os.path.join(HERE, "xdevice_worker.py"), str(path)],
                           env=env, capture_output=True, text=True, timeout=1200)
        assert r.returncode == 0, f"{impl} ({spec}): {r.stderr[-3000:]}"
        z = np.load(path)
        out[impl] = {"info": json.loads(str(z["info"])), **{k: z[k] for k in ("img0", "img1", "img2")}}
        assert out[impl]["info"]["impl"] == impl
    return out


def _blocks(img: np.ndarray) -> np.ndarray:
    """(groups, blocks): mean radiance per band group and BLOCK x BLOCK pixel block."""
    h, w, nb = img.shape
    hb, wb = h // BLOCK, w // BLOCK
    a = img[:hb * BLOCK, :wb * BLOCK].reshape(hb, BLOCK, wb, BLOCK, nb).mean(axis=(1, 3))
    return np.stack([a[..., g].mean(-1).ravel() for g in np.array_split(np.arange(nb), GROUPS)])


def test_each_implementation_is_byte_identical_with_itself(runs):
    for impl, r in runs.items():
        assert np.array_equal(r["img0"], r["img2"]), f"{impl}: seed 1 twice gave different images"
        assert not np.array_equal(r["img0"], r["img1"]), f"{impl}: seeds 1 and 2 gave the same image"


def test_images_agree_within_the_seed_spread(runs):
    b = {impl: [_blocks(r[k]) for k in ("img0", "img1")] for impl, r in runs.items()}
    seed_d = np.stack([s[0] - s[1] for s in b.values()])             # (impls, groups, blocks)
    sigma = np.sqrt((seed_d ** 2).mean(axis=(0, 2)))                  # per group: two renders' difference
    assert (sigma > 0).all()
    names = sorted(b)
    for i, p in enumerate(names):
        for q in names[i + 1:]:
            for s in (0, 1):
                c = b[p][s] - b[q][s]
                z = np.abs(c) / sigma[:, None]
                assert z.max() < 4.5, (p, q, s, z.max(), np.unravel_index(z.argmax(), z.shape))
                rms = np.sqrt((c ** 2).mean(axis=1)) / sigma
                assert (rms < 1.6).all(), (p, q, s, rms)
                # the whole image's mean per group: no bias beyond the noise of the mean
                nblk = c.shape[1]
                assert (np.abs(c.mean(axis=1)) < 4 * sigma / np.sqrt(nblk)).all(), (p, q, s, c.mean(1), sigma)


def test_slab_tallies_agree_within_3_sigma(runs):
    names = sorted(runs)
    for i, p in enumerate(names):
        for q in names[i + 1:]:
            a, b = runs[p]["info"], runs[q]["info"]
            assert a["tally"]["specular"] == pytest.approx(b["tally"]["specular"], rel=1e-5)
            for k in ("Rd", "Tt", "A"):
                se = np.hypot(a["tally_se"][k], b["tally_se"][k])
                assert se > 0
                assert abs(a["tally"][k] - b["tally"][k]) < 3 * se, (p, q, k, a["tally"][k], b["tally"][k], se)
