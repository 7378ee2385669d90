"""Throughput on named standard scenes: photons/ms of the photon pass and pairs/s of the gather.

The measurements behind ``clppm bench`` (and bench/photons.py, bench/gather.py):

* :func:`trace_rate`: ``PhotonPass.trace`` (tallies only, nothing stored) of n photons, best and
  median of ``repeats`` timed traces after a warm-up launch (the first launch builds the
  program, which on a CPU runtime takes longer than the trace itself);
* :func:`gather_rate`: the renderer's pipeline on a config, photon pass 0 once, then that pass's
  grid build and gather repeated on the same stored photons: photon-point pairs found over the
  gather's seconds.

Best of N: on a shared machine interference only ever slows a run down, so the fastest run
estimates the device's rate; the median is reported beside it.
"""
from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path

#: the MCML verification slab (cm^-1, cm): tests/test_photonpass.py's and `clppm trace --slab`'s
MCML_SLAB = "mua=10,mus=90,g=0.75,n=1.0,d=0.02"
#: the shipped forearm (9 layers, 81 bands, relief + papillae on 5 um voxels)
FOREARM = "forearm"


@dataclass
class Rate:
    """``count`` items per timed run; ``seconds`` the runs' times (warm-up excluded)."""

    count: int
    seconds: list[float]

    @property
    def best_s(self) -> float:
        return min(self.seconds)

    @property
    def median_s(self) -> float:
        return float(statistics.median(self.seconds))

    def per_s(self, median: bool = False) -> float:
        return self.count / (self.median_s if median else self.best_s)


@dataclass
class TraceResult:
    """Photons/ms of one scene; ``Rd`` a sanity check of what was traced."""

    scene: str
    rate: Rate
    setup_s: float
    Rd: float
    specular: float
    A: float

    def as_dict(self) -> dict:
        r = self.rate
        return {"scene": self.scene, "photons": r.count, "repeats": len(r.seconds),
                "seconds": r.best_s, "seconds_median": r.median_s, "seconds_all": r.seconds,
                "photons_per_ms": r.per_s() / 1000.0,
                "photons_per_ms_median": r.per_s(median=True) / 1000.0,
                "setup_s": self.setup_s, "Rd": self.Rd, "specular": self.specular, "A": self.A}


@dataclass
class GatherResult:
    """Photon-point pairs/s of the gather on one config."""

    scene: str
    rate: Rate
    setup_s: float
    photon_s: float
    grid_s: list[float] = field(default_factory=list)
    layout: str = "gather"

    def as_dict(self) -> dict:
        r = self.rate
        return {"scene": self.scene, "pairs": r.count, "repeats": len(r.seconds),
                "seconds": r.best_s, "seconds_median": r.median_s, "seconds_all": r.seconds,
                "pairs_per_s": r.per_s(), "pairs_per_s_median": r.per_s(median=True),
                "setup_s": self.setup_s, "photon_s": self.photon_s,
                "grid_s": min(self.grid_s) if self.grid_s else None, "layout": self.layout}


def _now() -> float:
    return time.perf_counter()


def scene_config(name: str) -> tuple[dict, str]:
    """(config, source label) of a named scene: ``mcml slab``, ``forearm``, or a config path."""
    from .. import config
    if name == "mcml slab":
        return config.slab_config(MCML_SLAB), "--slab"
    path = config.find(name)
    return config.load(path), Path(path).name


def trace_rate(dev, cfg: dict, vol, n: int, scene: str, repeats: int = 3,
               warmup: int = 4096) -> TraceResult:
    """Best of ``repeats`` traces of ``n`` photons (other pass indices of the same seed), after a
    warm-up trace that builds the program and makes the first launch (not timed)."""
    from ..integrators import photonpass
    t0 = _now()
    pp = photonpass.PhotonPass.of_config(dev, vol, cfg, seed=1)
    pp.trace(min(n, warmup), pass_index=99)
    setup = _now() - t0
    times, tot = [], None
    for k in range(repeats):
        t0 = _now()
        arrs = pp.trace(n, pass_index=k)
        times.append(_now() - t0)
        if tot is None:
            tot = arrs[0].sum(0)
    w = float(photonpass.W0 * n)
    return TraceResult(scene, Rate(n, times), setup, Rd=float(tot[1]) / w,
                       specular=float(tot[0]) / w, A=float(tot[photonpass.NA:].sum()) / w)


def gather_rate(dev, cfg: dict, scene: str, repeats: int = 3) -> GatherResult:
    """The gather of photon pass 0 repeated ``repeats`` times on the same stored photons (the
    pass's photons stay in their buffers; its grid build is repeated with it): pairs over the
    gather's seconds.  The first gather (with the pass) builds the programs and is not timed."""
    from ..integrators import photonpass, ppm
    t0 = _now()
    sc = ppm.Pipeline.build(cfg, dev)
    cal = sc.calibrate()
    sc.apply(cal)
    setup = _now() - t0
    st = sc.point_state(cal)
    acc = ppm.Accumulators.zeros(sc)
    tal = photonpass.Tallies(sc.vol.nb, sc.vol.nmat)
    info = sc.run_pass(cal, st, 0, acc, tal)
    photon_s = sc.timing["photon"]
    sc.pp.run_pass = lambda p, n, tallies=None: info        # the same photons again
    grid_s, gather_s = [], []
    for _ in range(repeats):
        before = dict(sc.timing)
        acc.clear()
        sc.run_pass(cal, st, 0, acc, tal)
        grid_s.append(sc.timing["grid"] - before["grid"])
        gather_s.append(sc.timing["gather"] - before["gather"])
    pairs = int(acc.host()[1].astype("int64").sum())
    lay = getattr(getattr(sc.estimator, "layout", None), "name", "gather")
    return GatherResult(scene, Rate(pairs, gather_s), setup, photon_s, grid_s, lay)


@dataclass
class Sizes:
    """Photons per trace and the gather's image and photons per pass; ``quick``: a short run."""

    slab_photons: int = 4_000_000
    forearm_photons: int = 200_000
    repeats: int = 5
    gather_resolution: tuple[int, int] = (160, 120)
    gather_photons: int = 202_500

    @classmethod
    def quick(cls) -> "Sizes":
        return cls(slab_photons=200_000, forearm_photons=10_000, repeats=3,
                   gather_resolution=(32, 24), gather_photons=20_000)


def device_bench(dev, sizes: Sizes, spec: str = "", gather: bool = True) -> dict:
    """Every standard scene on one device: the device, its implementation and version, each
    scene's photons/ms and the forearm gather's pairs/s."""
    from .. import config
    from ..compute.device import describe, short_version
    from ..scene import volume
    d = describe(dev.device)
    out = {"spec": spec, "device": d["name"], "implementation": d["implementation"],
           "version": short_version(dev.device), "driver_version": d["driver_version"],
           "type": d["type"], "compute_units": d["compute_units"], "scenes": []}
    fore_cfg, fore_src = scene_config(FOREARM)
    for scene, n in (("mcml slab", sizes.slab_photons), (FOREARM, sizes.forearm_photons)):
        cfg, src = scene_config(scene)
        vol = volume.build(cfg, src)
        out["scenes"].append(trace_rate(dev, cfg, vol, n, scene, sizes.repeats).as_dict())
    if gather:
        g = config.override(fore_cfg, "camera", "resolution", list(sizes.gather_resolution))
        g = config.override(g, "render", "photons", sizes.gather_photons)
        res = gather_rate(dev, g, FOREARM, sizes.repeats)
        out["gather"] = {**res.as_dict(), "resolution": list(sizes.gather_resolution),
                         "photons_per_pass": sizes.gather_photons}
    return out


def speed_lines(entry: dict) -> list[str]:
    """One device's results as MCX prints its speed ("simulation speed: N photons/ms")."""
    lines = [f"{entry['spec']}  {entry['device']}  [{entry['implementation']}: {entry['version']}; "
             f"{entry['type']}; {entry['compute_units']} CUs]"]
    for s in entry["scenes"]:
        lines.append(f"  {s['scene']:10s} simulation speed: {s['photons_per_ms']:.2f} photons/ms "
                     f"(median {s['photons_per_ms_median']:.2f}; {s['photons']} photons, "
                     f"best of {s['repeats']} {s['seconds']:.3f} s)")
    g = entry.get("gather")
    if g:
        lines.append(f"  {g['scene']:10s} gather speed: {g['pairs_per_s']:.3g} pairs/s "
                     f"(median {g['pairs_per_s_median']:.3g}; {g['pairs']} pairs, best of "
                     f"{g['repeats']} {g['seconds']:.3f} s, {g['layout']} layout)")
    return lines


__all__ = ["MCML_SLAB", "Rate", "TraceResult", "GatherResult", "Sizes", "trace_rate",
           "gather_rate", "device_bench", "speed_lines", "scene_config"]
