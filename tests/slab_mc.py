"""What the tests of heterogeneous slabs share (test_inclusions.py, test_maps.py,
test_inclusions_ppm.py): a brute-force numpy Monte Carlo that knows nothing of boundaries, the
photon pass's per-band fractions beside it, the tallies' exact balance, a raw config as TOML.

The reference (:func:`delta_tracking`): a normal pencil beam into an index-matched slab, each
photon flying free paths at one majorant over the whole medium; at each tentative collision the
medium at the point decides (mu_t / majorant: real, else a null collision).  Absorption by
weight, Russian roulette below 1e-3.  What the medium is -- layers by depth, inclusions holding
the point, a map's column -- is the caller's ``medium(p)``, written from the config alone.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

from clppm import config as C
from clppm.integrators import photonpass
from clppm.integrators.photonpass import CATEGORIES, NA, W0

BATCHES = 10

# medium(p (n, 3) um) -> (tally index, mu_a, mu_s, g) per point, um^-1
Medium = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]


def layer_of(vol, p: np.ndarray) -> np.ndarray:
    """The layer index at points p (n, 3) by depth."""
    depth = vol.layer_depths()
    return np.clip(np.searchsorted(depth, -p[:, 2], side="right") - 1, 0, vol.nl - 1)


def material_of(vol, p: np.ndarray) -> np.ndarray:
    """Material index at points p (n, 3): the layer by depth, then the first inclusion holding it."""
    m = layer_of(vol, p)
    for i in reversed(range(vol.ninc)):
        m = np.where(vol.inclusions[i].contains(p), vol.nl + i, m)
    return m


def hg_turn(d: np.ndarray, g: np.ndarray, rng) -> np.ndarray:
    """Directions d (n, 3) turned by Henyey-Greenstein(g) polar angles and uniform azimuths."""
    u = rng.random(len(d))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (1 - g * g) / (1 - g + 2 * g * u)
        ct = np.where(np.abs(g) > 1e-6, (1 + g * g - t * t) / (2 * g), 2 * u - 1)
    ct = np.clip(ct, -1.0, 1.0)
    st = np.sqrt(1 - ct * ct)
    phi = 2 * math.pi * rng.random(len(d))
    # an orthonormal basis around d
    a = np.where(np.abs(d[:, [2]]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    b1 = np.cross(d, a)
    b1 /= np.linalg.norm(b1, axis=1)[:, None]
    b2 = np.cross(d, b1)
    out = st[:, None] * (np.cos(phi)[:, None] * b1 + np.sin(phi)[:, None] * b2) + ct[:, None] * d
    return out / np.linalg.norm(out, axis=1)[:, None]


def delta_tracking(medium: Medium, majorant: float, bottom: float, ntally: int, n: int, seed: int,
                   start=(0.0, 0.0), wrap: Callable[[np.ndarray], np.ndarray] | None = None) -> dict:
    """The module's reference: ``n`` photons from ``start`` (um) straight down into a slab
    ``bottom`` um thick, ``medium`` at each tentative collision, ``wrap`` (if given) applied to
    the points' x, y (periodic sides).  Returns per photon fraction means and standard errors:
    Rd, Tt and A0.. A{ntally - 1} (absorbed per tally index)."""
    rng = np.random.default_rng(seed)
    pos = np.zeros((n, 3))
    pos[:, :2] = start
    d = np.tile([0.0, 0.0, -1.0], (n, 1))
    w = np.ones(n)
    rd, tt = np.zeros(n), np.zeros(n)
    ab = np.zeros((n, ntally))
    alive = np.ones(n, bool)
    while alive.any():
        idx = np.flatnonzero(alive)
        p = pos[idx] + (-np.log(1.0 - rng.random(len(idx))) / majorant)[:, None] * d[idx]
        up, down = p[:, 2] > 0, p[:, 2] < -bottom
        rd[idx[up]] += w[idx[up]]
        tt[idx[down]] += w[idx[down]]
        alive[idx[up | down]] = False
        keep = ~(up | down)
        idx, p = idx[keep], p[keep]
        if wrap is not None:
            p[:, :2] = wrap(p[:, :2])
        pos[idx] = p
        m, mua, mus, g = medium(p)
        real = rng.random(len(idx)) * majorant < mua + mus
        r, m, mua, mus, g = idx[real], m[real], mua[real], mus[real], g[real]
        a = mua / (mua + mus)
        np.add.at(ab, (r, m), w[r] * a)
        w[r] *= 1 - a
        d[r] = hg_turn(d[r], g, rng)
        low = r[w[r] < 1e-3]
        win = rng.random(len(low)) < 0.1
        w[low[win]] *= 10.0
        w[low[~win]] = 0.0
        alive[low[~win]] = False
    cols = {"Rd": rd, "Tt": tt, **{f"A{k}": ab[:, k] for k in range(ntally)}}
    return {k: (float(v.mean()), float(v.std(ddof=1) / math.sqrt(n))) for k, v in cols.items()}


def photon_pass_fractions(dev, vol, cfg, band: int, n: int, batches: int = BATCHES):
    """The photon pass's tallies for one band: per-batch fractions' mean and standard error (Rd,
    Tt, A per material), and the summed integer tallies."""
    pp = photonpass.PhotonPass.of_config(dev, vol, cfg)
    pp.p["fixed_band"] = band
    arrs = pp.trace(n, batches=batches)
    sizes = [n // batches + (1 if i < n % batches else 0) for i in range(batches)]
    fr = np.array([a[band] / (W0 * s) for a, s in zip(arrs, sizes)])
    cols = {"Rd": CATEGORIES.index("diffuse"), "Tt": CATEGORIES.index("transmitted"),
            **{f"A{k}": NA + k for k in range(vol.nmat)}}
    out = {k: (float(fr[:, c].mean()), float(fr[:, c].std(ddof=1) / math.sqrt(batches)))
           for k, c in cols.items()}
    return out, sum(a.astype(object) for a in arrs)[band]


def agree(got: dict, ref: dict, tol_se: float, band: int) -> None:
    """Every fraction of the photon pass within ``tol_se`` combined standard errors of the reference's."""
    for k in got:
        (a, sa), (b, sb) = got[k], ref[k]
        tol = tol_se * math.hypot(sa, sb) + 1e-6
        assert abs(a - b) <= tol, \
            f"band {band} {k}: photon pass {a:.5f} ± {sa:.5f}, delta tracking {b:.5f} ± {sb:.5f}"


def exact_balance(tot_row, nmat) -> int:
    """Emitted weight minus what the categories account for (0: exact)."""
    cats = [i for i, c in enumerate(CATEGORIES) if c != "diffuse_cone"] + list(range(NA, NA + nmat))
    return sum(int(tot_row[c]) for c in cats) - 2 * int(tot_row[CATEGORIES.index("rr_gain")])


def raw_toml(raw: dict) -> str:
    """A raw config dict as TOML (sections, then tables such as [[layer]], [[inclusion]], [[map]])."""
    lines = []
    for sec, t in raw.items():
        if isinstance(t, list):
            for row in t:
                lines.append(f"[[{sec}]]")
                lines += [f"{k} = {C.toml_value(v)}" for k, v in row.items() if v is not None]
        else:
            lines.append(f"[{sec}]")
            lines += [f"{k} = {C.toml_value(v)}" for k, v in t.items() if v is not None]
    return "\n".join(lines) + "\n"
