"""Converged reference images, cached on disk.

A reference is the mean of two independent renders ("halves") of the same scene with
different seeds.  Where the scene allows it (flat layers, a point light) it is the unbiased
path tracer (:mod:`clppm.integrators.pathtracer`) with jittered rays, averaged over ``block`` x
``block`` squares of pixels, so that each reference pixel is the exact mean of its square; the
compared image is averaged over the same squares.  Otherwise it is PPM
with many more stored photons per pass and passes than the runs it is compared with.  It is
computed once and stored as
``<cache>/ref-<key>.npz`` + ``.json``, where ``key`` is a SHA-256 over everything that
changes the picture: the scene config (with the reference's own render settings applied),
the reference parameters, the clppm version and the kernel sources.  Any change of these
gives a new key, so a stale reference is never reused.

Its own error is estimated from the two halves: with h1 = t + e1, h2 = t + e2 (e1, e2
independent, zero-mean) the reference (h1 + h2) / 2 deviates from t by (e1 + e2) / 2, which
has the distribution of (e1 - e2) / 2 = (h1 - h2) / 2.  So every error measure of the
reference is estimated as that measure between the halves, halved (exact for the RMSE in
expectation, first order for the CIEDE2000 and chromaticity means).  This covers the Monte
Carlo noise only: for a PPM reference, the density-estimation bias of the finite radius
(which the halves share) is not in it; a path-tracing reference has none.

Skin pixels (the error is taken over them) are the pixels all of whose eye rays hit the
model, from the eye pass of the reference scene.  The error measures themselves, of an image
against a reference, are :mod:`clppm.analysis.metrics`.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import time
from dataclasses import dataclass, field

import numpy as np

from .. import config as C
from ..scene import volume
from ..scene.bands import Bands
from ..version import __version__
from .metrics import accuracy, block_mask, block_mean, skin_mask_from_eye

# ----------------------------------------------------------------------------- reference
@dataclass
class RefSpec:
    """What the reference is made of (besides the scene config).

    ``integrator = "pt"``: ``paths`` eye paths per ``block`` x ``block`` square and half.  ``integrator = "ppm"``: method, photons, passes, K as given, with
    the render ``overrides`` (e.g. config.PAPER_MODE), then averaged over ``block`` squares."""

    integrator: str = "pt"
    resolution: tuple = (80, 60)
    block: int = 10
    paths: int = 500_000
    method: str = "a"
    spacing_um: float | None = None
    photons: int = 405_000              # stored photons per pass
    passes: int = 60
    initial_photons: int = 200          # K of the first search (sets the initial radius)
    overrides: dict = field(default_factory=dict)
    seeds: tuple = (1_000_001, 2_000_003)

    def as_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["resolution"] = list(self.resolution)
        d["seeds"] = list(self.seeds)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "RefSpec":
        d = dict(d)
        d["resolution"] = tuple(d["resolution"])
        d["seeds"] = tuple(d["seeds"])
        return cls(**{k: v for k, v in d.items() if k in {f.name for f in dataclasses.fields(cls)}})


@dataclass
class Reference:
    key: str
    spec: RefSpec
    xyz: np.ndarray                # (h, w, 3) mean of the halves, at resolution / block
    rgb: np.ndarray                # (h, w, 3) linear sRGB
    halves_xyz: np.ndarray         # (2, h, w, 3)
    spectral: np.ndarray           # (h, w, NB) float32 mean
    wl: np.ndarray
    mask: np.ndarray               # (h, w) bool: squares of skin pixels only
    exposure: float
    error: dict                    # own error estimate (accuracy of one half against the other, halved)
    info: dict = field(default_factory=dict)
    cached: bool = False
    path: str = ""
    pixels_xyz: np.ndarray | None = None   # (2, H, W, 3) the halves at full resolution (per-pixel analyses)
    halves_spectral: np.ndarray | None = None   # (2, h, w, NB) the halves per square (band groups' noise)

    @property
    def block(self) -> int:
        return self.spec.block


def kernel_hash(names=None) -> str:
    """SHA-256 of the kernel sources (``names``: only these files)."""
    from ..compute.device import kernel_dir
    h = hashlib.sha256()
    d = kernel_dir()
    for name in sorted(os.listdir(d)):
        if name.endswith((".cl", ".h")) and (names is None or name in names):
            with open(os.path.join(d, name), "rb") as f:
                h.update(name.encode() + b"\0" + f.read())
    return h.hexdigest()[:16]


def pt_possible(cfg: dict) -> bool:
    """Whether the path tracer is a reference for the scene (a point light above the surface;
    relief through manifold next-event estimation, docs/relief.md)."""
    from ..integrators.pathtracer import check_scene
    try:
        check_scene(cfg, "<reference>")
    except Exception:
        return False
    return True


def scene_config(cfg: dict, spec: RefSpec) -> dict:
    """The scene config with the reference's render settings applied (seed: first half)."""
    from ..request import resolved_config
    if spec.integrator == "pt":
        # at the full resolution (a work item per pixel: the device needs many), averaged over
        # the squares afterwards: the same as rendering each square as one jittered pixel
        # at least one path per band in every pixel (a path samples one band): no band of a
        # reference pixel is interpolated
        per_pixel = max(int(math.ceil(spec.paths / spec.block ** 2)), Bands.from_config(cfg, hero=1).nb)
        c = resolved_config(cfg, resolution=spec.resolution, seed=spec.seeds[0])
        spp = int(min(256, per_pixel))
        c = C.override(c, "render", "pt_samples_per_pass", spp)
        c = C.override(c, "render", "passes", int(math.ceil(per_pixel / spp)))
        return c
    c = resolved_config(cfg, method=spec.method, spacing=spec.spacing_um, resolution=spec.resolution,
                        seed=spec.seeds[0], photons=int(spec.photons))
    for k, v in spec.overrides.items():
        c = C.override(c, "render", k, v)
    c = C.override(c, "render", "initial_photons", int(min(spec.initial_photons, spec.photons)))
    c = C.override(c, "render", "passes", int(spec.passes))
    return c


def reference_key(cfg: dict, spec: RefSpec) -> str:
    c = json.loads(json.dumps(scene_config(cfg, spec), default=str))
    for k in C.NOT_PICTURE + C.FINISHING + ("seed",):
        c["render"].pop(k, None)
    kernels = None
    if spec.integrator == "pt":           # the path tracer reads none of PPM's settings or kernels
        c["render"] = {k: c["render"][k] for k in ("specular", "roughness", "pt_samples_per_pass")}
        kernels = ("pt.cl", "common.h") if C.is_flat(cfg) else ("pt.cl", "common.h", "mnee.h", "surface.h", "smoothwalk.h")
    blob = json.dumps({"config": c, "spec": spec.as_dict(), "clppm": __version__,
                       "kernels": kernel_hash(kernels)}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def _paths(cache_dir: str, key: str) -> tuple[str, str]:
    base = os.path.join(cache_dir, f"ref-{key}")
    return base + ".npz", base + ".json"


def load_reference(cache_dir: str, key: str):
    npz, js = _paths(cache_dir, key)
    if not (os.path.isfile(npz) and os.path.isfile(js)):
        return None
    try:
        with open(js) as f:
            meta = json.load(f)
        with np.load(npz, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        spec = RefSpec.from_dict(meta["spec"])
    except (OSError, ValueError, KeyError, TypeError, json.JSONDecodeError):
        return None
    if meta.get("key") != key:
        return None
    return Reference(key=key, spec=spec, xyz=arrays["xyz"], rgb=arrays["rgb"],
                     halves_xyz=arrays["halves_xyz"], spectral=arrays["spectral"], wl=arrays["wl"],
                     mask=arrays["mask"].astype(bool), exposure=float(meta["exposure"]),
                     error=meta["error"], info=meta.get("info", {}), cached=True, path=npz,
                     pixels_xyz=arrays.get("pixels_xyz"), halves_spectral=arrays.get("halves_spectral"))


def _save(cache_dir: str, ref: Reference) -> None:
    os.makedirs(cache_dir, exist_ok=True)
    npz, js = _paths(cache_dir, ref.key)
    tmp = npz + f".{os.getpid()}.tmp.npz"
    np.savez_compressed(tmp, xyz=ref.xyz, rgb=ref.rgb, halves_xyz=ref.halves_xyz,
                        spectral=ref.spectral.astype(np.float32), wl=ref.wl, mask=ref.mask,
                        **({} if ref.pixels_xyz is None else {"pixels_xyz": ref.pixels_xyz}),
                        **({} if ref.halves_spectral is None else {"halves_spectral": ref.halves_spectral}))
    os.replace(tmp, npz)
    meta = {"key": ref.key, "spec": ref.spec.as_dict(), "exposure": ref.exposure, "error": ref.error,
            "info": ref.info}
    with open(js + ".tmp", "w") as f:
        json.dump(meta, f, indent=1, default=str)
    os.replace(js + ".tmp", js)
    ref.path = npz


def skin_mask(cfg: dict, dev=None) -> np.ndarray:
    """Skin pixels of ``cfg``'s camera (eye pass only)."""
    from ..integrators import eyepass
    from ..compute.device import open_device
    dev = dev or open_device(None)
    vol = volume.build(cfg)
    vb = volume.upload_volume(dev, vol)
    eye = eyepass.run(dev, vol, vb, cfg, eyepass.scheme(cfg["render"]["method"], cfg["render"]["spacing_um"]),
                      geometry=False)
    return skin_mask_from_eye(eye)


def _render_half(c: dict, spec: RefSpec, seed: int, dev, progress: bool):
    if spec.integrator == "pt":
        from ..run.entry import render_pt
        return render_pt(c, seed=int(seed), dev=dev, progress=progress)
    from ..run.entry import render
    return render(c, seed=int(seed), dev=dev, progress=progress)


def get_reference(cfg: dict, spec: RefSpec, cache_dir: str = "out/cache", dev=None, log=print,
                  force: bool = False, flip: bool = False, progress: bool = False) -> Reference:
    """The cached reference for (cfg, spec), computing (and caching) it if needed."""
    key = reference_key(cfg, spec)
    if not force:
        ref = load_reference(cache_dir, key)
        if ref is not None:
            log(f"reference {key}: cached ({ref.path})")
            log(reference_summary(ref))
            return ref
    c = scene_config(cfg, spec)
    log(f"reference {key}: computing {describe(spec)}, {spec.resolution[0]}x{spec.resolution[1]}, two halves "
        f"(seeds {spec.seeds[0]}, {spec.seeds[1]})")
    t0 = time.perf_counter()
    halves, reports, mask = _render_halves(cfg, c, spec, dev, progress, log)
    ref = _mean_of_halves(key, spec, halves, mask)
    ref.info = {"halves": reports, "seconds": time.perf_counter() - t0,
                "device": halves[0].report["device"]["name"]}
    _save(cache_dir, ref)
    log(f"reference {key}: saved {ref.path} ({ref.info['seconds']:.0f} s)")
    log(reference_summary(ref))
    return ref


def describe(spec: RefSpec) -> str:
    """What the reference renders, in words."""
    if spec.integrator == "pt":
        return f"path tracer, {spec.paths:,} paths per {spec.block}x{spec.block}-pixel square"
    return (f"PPM method {spec.method}, {spec.photons} stored photons/pass, {spec.passes} passes, "
            f"K = {spec.initial_photons}{', ' + str(spec.overrides) if spec.overrides else ''}")


def _render_halves(cfg: dict, c: dict, spec: RefSpec, dev, progress: bool, log):
    """The two halves of the scene config ``c`` (seeds ``spec.seeds``), a report of each, and
    the skin squares of ``cfg``'s camera at the reference's resolution."""
    from ..request import resolved_config
    halves, reports = [], []
    with volume.memoised():
        full = resolved_config(cfg, resolution=spec.resolution)
        mask = block_mask(skin_mask(full, dev), spec.block)
        for s in spec.seeds:
            th = time.perf_counter()
            res = _render_half(c, spec, s, dev, progress)
            halves.append(res)
            r = res.report
            reports.append({"seed": int(s), "seconds": r["seconds"],
                            **{k: r[k] for k in ("photons_emitted", "photons_stored", "gather_pairs",
                                                 "sample_points", "paths_traced") if k in r}})
            log(f"  half seed {s}: {time.perf_counter() - th:.1f} s")
    return halves, reports, mask


def _mean_of_halves(key: str, spec: RefSpec, halves: list, mask) -> Reference:
    """The reference: the mean of the two halves over the squares, with its own noise."""
    b = spec.block
    h = np.stack([block_mean(x.xyz, b) for x in halves])
    sp = [block_mean(x.spectral, b) for x in halves]
    ref = Reference(key=key, spec=spec, xyz=h.mean(0), rgb=np.mean([block_mean(x.rgb, b) for x in halves], axis=0),
                    halves_xyz=h, spectral=np.mean(sp, axis=0).astype(np.float32),
                    wl=np.asarray(halves[0].wl), mask=mask, exposure=float(halves[0].exposure), error={},
                    pixels_xyz=np.stack([x.xyz for x in halves]).astype(np.float32),
                    halves_spectral=np.stack(sp).astype(np.float32))
    ref.error = own_noise(ref, sp)
    return ref


def own_noise(ref: Reference, halves_spectral: list) -> dict:
    """The reference's own noise: the accuracy of one half against the other (at the
    reference's own resolution), halved (see the module docstring)."""
    h, sp = ref.halves_xyz, halves_spectral
    half = dataclasses.replace(ref, xyz=h[1], spectral=sp[1], spec=dataclasses.replace(ref.spec, block=1))
    e = accuracy(h[0], sp[0], half)
    err = {k: (v / 2.0 if isinstance(v, float) else v) for k, v in e.items() if k != "groups"}
    err["groups"] = {k: v / 2.0 for k, v in e["groups"].items()}
    err["note"] = ("noise of the mean of the two halves, estimated as (half1 vs half2) / 2"
                   + ("" if ref.spec.integrator == "pt" else "; excludes the density-estimation bias the halves share"))
    return err


def reference_summary(ref: Reference) -> str:
    e = ref.error
    return (f"reference own noise (from its two halves), per {ref.block}x{ref.block}-pixel square: "
            f"Y {100 * e['block_Y_rms']:.2f} % RMS ({100 * e['block_Y_max']:.2f} % max), mean CIEDE2000 "
            f"{e['de2000']:.3g}, mean skin colour dE00 {e['de_mean']:.3g}, 50-nm band groups "
            f"{100 * e['group_max']:.2f} % max; {int(ref.mask.sum())} skin squares")
