"""Converged reference images, cached on disk, and the error of an image against one.

A reference is the mean of two independent renders ("halves") of the same scene with
different seeds.  Where the scene allows it (flat layers, a point light) it is the unbiased
path tracer (:mod:`clppm.pathtracer`) with jittered rays, averaged over ``block`` x ``block``
squares of pixels, so that each reference pixel is the exact mean of its square; the compared
image is averaged over the same squares.  Otherwise it is PPM
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
model, from the eye pass of the reference scene.
"""
from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import math
import os
import time
from dataclasses import dataclass, field

import numpy as np

from . import config as C
from . import image

# ----------------------------------------------------------------------------- volumes
_VOLUME_KEYS = ("model", "spectrum", "relief", "papillae", "layer")


@contextlib.contextmanager
def cached_volumes():
    """While active, ``clppm.volume.build`` returns a memoised volume per geometry.

    Building the forearm volume (2000 x 2000 columns, generated relief) takes 5-10 s on
    the host and does not depend on the method, the camera or the photon counts; a compare
    or benchmark run renders the same volume a dozen times.  The stage timings of the
    renders exclude it anyway (it is ``seconds['volume']``).
    """
    from . import volume
    orig = volume.build
    cache: dict = {}

    def build(cfg, source="<config>"):
        key = json.dumps({k: cfg.get(k) for k in _VOLUME_KEYS}, sort_keys=True, default=str)
        if key not in cache:
            cache[key] = orig(cfg, source)
        return cache[key]

    volume.build = build
    try:
        yield cache
    finally:
        volume.build = orig


# ----------------------------------------------------------------------------- metrics
def skin_mask_from_eye(eye) -> np.ndarray:
    """(H, W) bool: pixels all of whose eye rays hit the model."""
    cam = eye.camera
    hit = np.asarray(eye.ray_hit, float).reshape(cam.height, cam.width, cam.spp)
    return np.all(hit > 0.5, axis=2)


def error_metrics(xyz, ref_xyz, mask, exposure: float, rgb=None, ref_rgb=None,
                  flip: bool = False) -> dict:
    """Errors of ``xyz`` against ``ref_xyz`` over the skin pixels ``mask``.

    Both are scaled by ``exposure`` (a white diffuser at the image centre has Y = 1), so
    the numbers are relative to that white:

    * ``rmse_xyz``: RMSE of linear XYZ over skin pixels and the three channels;
    * ``rel_rmse``: ``rmse_xyz`` / mean reference Y over skin pixels;
    * ``de2000``: mean CIEDE2000 against the reference (white D65, Y = 1);
    * ``du``, ``dv``: mean signed per-pixel u', v' shift (test - reference);
    * ``duv``: mean per-pixel |Δu'v'|;
    * ``du_mean``, ``dv_mean``: u'v' of the mean skin colour minus the reference's
      (robust to noise; the colour of the skin as a whole);
    * ``db``, ``da``, ``dL``: mean signed Δb*, Δa*, ΔL* (b* < 0 is bluer);
    * ``dY``: mean Y / reference mean Y - 1 (brightness bias);
    * ``flip``: mean FLIP (LDR, displayed sRGB images at this exposure) over skin pixels,
      when ``flip`` is set and ``flip-evaluator`` is installed (else absent).
    """
    m = np.asarray(mask, bool)
    n = int(m.sum())
    if n == 0:
        raise ValueError("no skin pixels: the reference's eye rays hit nothing")
    a = np.asarray(xyz, float)[m] * exposure
    b = np.asarray(ref_xyz, float)[m] * exposure
    a = np.nan_to_num(a, nan=0.0, posinf=0.0, neginf=0.0)
    d = a - b
    out = {"skin_pixels": n, "rmse_xyz": float(np.sqrt(np.mean(d * d)))}
    mY = float(b[:, 1].mean())
    out["rel_rmse"] = out["rmse_xyz"] / mY if mY > 0 else float("nan")
    out["dY"] = float(a[:, 1].mean() / mY - 1.0) if mY > 0 else float("nan")
    out["de2000"] = float(np.mean(image.delta_e2000(a, b)))
    ua, ub = image.xyz_to_uv_prime(a), image.xyz_to_uv_prime(b)
    duv = ua - ub
    out["du"], out["dv"] = float(duv[:, 0].mean()), float(duv[:, 1].mean())
    out["duv"] = float(np.mean(np.hypot(duv[:, 0], duv[:, 1])))
    uma = image.xyz_to_uv_prime(a.mean(0))
    umb = image.xyz_to_uv_prime(b.mean(0))
    out["du_mean"], out["dv_mean"] = float(uma[0] - umb[0]), float(uma[1] - umb[1])
    la, lb = image.xyz_to_lab(a), image.xyz_to_lab(b)
    dl = (la - lb).mean(0)
    out["dL"], out["da"], out["db"] = float(dl[0]), float(dl[1]), float(dl[2])
    if flip and rgb is not None and ref_rgb is not None:
        f = flip_error(rgb, ref_rgb, m, exposure)
        if f is not None:
            out["flip"] = f
    return out


def flip_error(rgb, ref_rgb, mask, exposure: float):
    """Mean LDR-FLIP over ``mask`` of the displayed (exposed, clipped, sRGB) images, or None.

    FLIP (Andersson et al. 2020) models what a viewer sees flipping between two images; the
    displayed PNGs are what is looked at, so the LDR mode on them is the sound use here.
    """
    try:
        import flip_evaluator as fe
    except Exception:
        return None
    t = image.encode_srgb(np.asarray(rgb, float) * exposure).astype(np.float32)
    r = image.encode_srgb(np.asarray(ref_rgb, float) * exposure).astype(np.float32)
    emap, _, _ = fe.evaluate(np.ascontiguousarray(r), np.ascontiguousarray(t), "LDR",
                             inputsRGB=True, applyMagma=False, computeMeanError=False)
    emap = np.asarray(emap, float)
    if emap.ndim == 3:
        emap = emap[..., 0]
    return float(emap[np.asarray(mask, bool)].mean())


# ----------------------------------------------------------------------------- blocks
def block_mean(a, b: int) -> np.ndarray:
    """Mean over b x b squares of pixels (H, W must be multiples of b)."""
    a = np.asarray(a)
    if b == 1:
        return a
    H, W = a.shape[:2]
    return a.reshape(H // b, b, W // b, b, *a.shape[2:]).mean(axis=(1, 3))


def block_mask(mask, b: int) -> np.ndarray:
    """Squares all of whose pixels are skin."""
    m = np.asarray(mask, bool)
    if b == 1:
        return m
    H, W = m.shape
    return m.reshape(H // b, b, W // b, b).all(axis=(1, 3))


BAND_GROUP_NM = 50.0


def band_groups(wl) -> list[tuple[float, float, np.ndarray]]:
    """50-nm groups of bands from the first band on: (from nm, to nm, band indices)."""
    wl = np.asarray(wl, float)
    g = np.floor((wl - wl[0]) / BAND_GROUP_NM + 1e-9).astype(int)
    if len(wl) > 1 and g[-1] > g[-2]:           # a lone last band (780 nm) joins the group before
        g[-1] = g[-2]
    return [(float(wl[g == k][0]), float(wl[g == k][-1]), np.nonzero(g == k)[0]) for k in np.unique(g)]


def accuracy(xyz, spectral, ref, flip: bool = False, rgb=None) -> dict:
    """Errors of an image (full resolution) against ``ref`` at the reference's resolution.

    :func:`error_metrics` on the block means, plus: the relative error of Y per skin block
    (``block_Y_rms``, ``block_Y_max``: the largest |Y/Y_ref - 1|), the CIEDE2000 of the mean
    skin colour (``de_mean``) and the relative error of the mean skin radiance in each 50-nm
    band group (``groups``, ``group_max``)."""
    b = ref.block
    x = block_mean(xyz, b)
    m = error_metrics(x, ref.xyz, ref.mask, ref.exposure, flip=False)
    mask = ref.mask
    Yt, Yr = x[..., 1][mask], ref.xyz[..., 1][mask]
    rel = Yt / np.where(Yr > 0, Yr, np.nan) - 1
    m["block_Y_rms"] = float(np.sqrt(np.nanmean(rel * rel)))
    m["block_Y_max"] = float(np.nanmax(np.abs(rel)))
    a = x[mask].mean(0) * ref.exposure
    r = ref.xyz[mask].mean(0) * ref.exposure
    m["de_mean"] = float(image.delta_e2000(a[None], r[None])[0])
    if spectral is not None:
        st = block_mean(spectral, b)[mask].mean(0)
        sr = np.asarray(ref.spectral, float)[mask].mean(0)
        groups = {}
        for lo, hi, idx in band_groups(ref.wl):
            den = sr[idx].sum()
            groups[f"{lo:.0f}-{hi:.0f}"] = float(st[idx].sum() / den - 1) if den > 0 else float("nan")
        m["groups"] = groups
        m["group_max"] = float(np.nanmax(np.abs(list(groups.values()))))
    return m


def accuracy_of_seeds(images: list, ref) -> dict:
    """:func:`accuracy` of the mean of several renders of one scheme (``images``: (xyz, spectral)
    pairs already averaged over the reference's squares), which has their bias and 1/sqrt(n) of
    one image's noise; with two or more: the first image's Y per square (``one_Y_rms``,
    ``one_Y_max``), one image's noise per square from the first two ((Y1 - Y2)/sqrt 2:
    ``noise_Y_rms``), and the bias per square with both noises removed in quadrature
    (``bias_Y_rms`` = sqrt(RMS^2 - noise^2/n - the reference's own noise^2), 0 if negative)."""
    sq = dataclasses.replace(ref, spec=dataclasses.replace(ref.spec, block=1))     # already squares
    n = len(images)
    xyz = np.mean([x for x, _ in images], 0)
    spectral = None if images[0][1] is None else np.mean([s for _, s in images], 0)
    m = {"seeds": n, **accuracy(xyz, spectral, sq)}
    if n > 1:
        one = accuracy(images[0][0], images[0][1], sq)
        Yr = ref.xyz[..., 1][ref.mask]
        d = (images[0][0][..., 1] - images[1][0][..., 1])[ref.mask] / Yr
        noise = float(np.sqrt(np.mean(d * d) / 2))
        resid = m["block_Y_rms"] ** 2 - noise ** 2 / n - ref.error["block_Y_rms"] ** 2
        m.update(one_Y_rms=one["block_Y_rms"], one_Y_max=one["block_Y_max"], noise_Y_rms=noise,
                 bias_Y_rms=float(np.sqrt(max(resid, 0.0))))
        rel = np.mean([x[..., 1] for x, _ in images], 0)[ref.mask] / Yr - 1
        se = square_standard_errors(images, ref)[ref.mask]
        m.update(beyond(rel, se, BIAS_BOUND))
    return m


#: the bias bound per 10x10-pixel square that issue 11 holds the default to
BIAS_BOUND = 0.02


def square_standard_errors(images: list, ref) -> np.ndarray:
    """Standard error of Y / Y_ref - 1 per square of the mean of ``images`` (n >= 2): the seeds'
    scatter / sqrt(n), and the reference's own, from its two halves ((h0 - h1)^2 / 4 is the
    variance of their mean), added in quadrature.  Both variances are averaged over the 3x3 skin
    squares around each (noise changes slowly across the image; a square alone has n - 1 and 1
    degrees of freedom, too few to test it by)."""
    Y = np.array([x[..., 1] for x, _ in images], float)
    Yr = ref.xyz[..., 1].astype(float)
    with np.errstate(divide="ignore", invalid="ignore"):
        v_img = Y.var(0, ddof=1) / len(Y) / Yr ** 2
        h = ref.halves_xyz[..., 1].astype(float)
        v_ref = np.where(ref.mask, (h[0] - h[1]) ** 2 / 4 / Yr ** 2, 0.0)
    k = ref.mask.astype(float)
    pad = lambda a: np.pad(a, 1)
    box = lambda a: sum(pad(a)[1 + i:a.shape[0] + 1 + i, 1 + j:a.shape[1] + 1 + j]
                        for i in (-1, 0, 1) for j in (-1, 0, 1))
    v_img = np.where(ref.mask, v_img, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        v = (box(v_img) + box(v_ref)) / box(k)
    return np.where(ref.mask, np.sqrt(v), np.nan)


def beyond(rel: np.ndarray, se: np.ndarray, bound: float, z: float = 3.0) -> dict:
    """Squares whose error |rel| exceeds ``bound`` (``beyond``), and those whose bias exceeds it
    beyond doubt: by more than ``z`` standard errors (``beyond_sig``; z = 3 is a 0.13 % one-sided
    false alarm for a square whose bias is exactly the bound), with the largest |rel| - z se
    (``bias_lower_max``: no square's bias is shown to be larger), and how many noise alone
    would put beyond the bound if no square had any bias (``beyond_noise``)."""
    from math import erfc, sqrt
    e = np.abs(np.asarray(rel, float)) - bound
    # how many squares noise alone would put beyond the bound if no square had any bias
    chance = sum(erfc(bound / (sqrt(2) * s)) for s in np.asarray(se, float).ravel() if s > 0)
    return {"squares": int(e.size), "beyond": int((e > 0).sum()), "beyond_sig": int((e > z * se).sum()),
            "beyond_noise": float(chance), "bias_lower_max": float(np.max(np.abs(rel) - z * se)),
            "z": z, "bound": bound}


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

    @property
    def block(self) -> int:
        return self.spec.block


def kernel_hash(names=None) -> str:
    """SHA-256 of the kernel sources (``names``: only these files)."""
    from .device import kernel_dir
    h = hashlib.sha256()
    d = kernel_dir()
    for name in sorted(os.listdir(d)):
        if name.endswith((".cl", ".h")) and (names is None or name in names):
            with open(os.path.join(d, name), "rb") as f:
                h.update(name.encode() + b"\0" + f.read())
    return h.hexdigest()[:16]


def pt_possible(cfg: dict) -> bool:
    """Whether the path tracer is a reference for the scene (flat, point light above the
    surface): its relief connection is experimental (render.pt_relief) and never one."""
    from .pathtracer import check_scene
    if not C.is_flat(cfg):
        return False
    try:
        check_scene(cfg, "<reference>")
    except Exception:
        return False
    return True


def scene_config(cfg: dict, spec: RefSpec) -> dict:
    """The scene config with the reference's render settings applied (seed: first half)."""
    from .progressive import apply_overrides
    if spec.integrator == "pt":
        # at the full resolution (a work item per pixel: the device needs many), averaged over
        # the squares afterwards: the same as rendering each square as one jittered pixel
        per_pixel = int(math.ceil(spec.paths / spec.block ** 2))
        c = apply_overrides(cfg, resolution=spec.resolution, seed=spec.seeds[0])
        spp = int(min(256, per_pixel))
        c = C.override(c, "render", "pt_samples_per_pass", spp)
        c = C.override(c, "render", "passes", int(math.ceil(per_pixel / spp)))
        return c
    c = apply_overrides(cfg, method=spec.method, spacing=spec.spacing_um, resolution=spec.resolution,
                        seed=spec.seeds[0], photons=int(spec.photons))
    for k, v in spec.overrides.items():
        c = C.override(c, "render", k, v)
    c = C.override(c, "render", "initial_photons", int(min(spec.initial_photons, spec.photons)))
    c = C.override(c, "render", "passes", int(spec.passes))
    return c


def reference_key(cfg: dict, spec: RefSpec) -> str:
    import clppm
    c = json.loads(json.dumps(scene_config(cfg, spec), default=str))
    for k in C.NOT_PICTURE + C.FINISHING + ("seed",):
        c["render"].pop(k, None)
    kernels = None
    if spec.integrator == "pt":           # the path tracer reads none of PPM's settings or kernels
        c["render"] = {k: c["render"][k] for k in ("specular", "roughness", "pt_samples_per_pass")}
        kernels = ("pt.cl", "common.h")
    blob = json.dumps({"config": c, "spec": spec.as_dict(), "clppm": clppm.__version__,
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
                     error=meta["error"], info=meta.get("info", {}), cached=True, path=npz)


def _save(cache_dir: str, ref: Reference) -> None:
    os.makedirs(cache_dir, exist_ok=True)
    npz, js = _paths(cache_dir, ref.key)
    tmp = npz + f".{os.getpid()}.tmp.npz"
    np.savez_compressed(tmp, xyz=ref.xyz, rgb=ref.rgb, halves_xyz=ref.halves_xyz,
                        spectral=ref.spectral.astype(np.float32), wl=ref.wl, mask=ref.mask)
    os.replace(tmp, npz)
    meta = {"key": ref.key, "spec": ref.spec.as_dict(), "exposure": ref.exposure, "error": ref.error,
            "info": ref.info}
    with open(js + ".tmp", "w") as f:
        json.dump(meta, f, indent=1, default=str)
    os.replace(js + ".tmp", js)
    ref.path = npz


def skin_mask(cfg: dict, dev=None) -> np.ndarray:
    """Skin pixels of ``cfg``'s camera (eye pass only)."""
    from . import eyepass, transport, volume
    from .device import open_device
    dev = dev or open_device(None)
    vol = volume.build(cfg)
    vb = transport.upload_volume(dev, vol)
    eye = eyepass.run(dev, vol, vb, cfg, eyepass.scheme(cfg["render"]["method"], cfg["render"]["spacing_um"]),
                      geometry=False)
    return skin_mask_from_eye(eye)


def _render_half(c: dict, spec: RefSpec, seed: int, dev, progress: bool):
    if spec.integrator == "pt":
        from .pathtracer import render_pt
        return render_pt(c, seed=int(seed), dev=dev, progress=progress)
    from .progressive import render
    return render(c, seed=int(seed), dev=dev, progress=progress)


def get_reference(cfg: dict, spec: RefSpec, cache_dir: str = "out/cache", dev=None, log=print,
                  force: bool = False, flip: bool = False, progress: bool = False) -> Reference:
    """The cached reference for (cfg, spec), computing (and caching) it if needed."""
    from .progressive import apply_overrides
    key = reference_key(cfg, spec)
    if not force:
        ref = load_reference(cache_dir, key)
        if ref is not None:
            log(f"reference {key}: cached ({ref.path})")
            log(reference_summary(ref))
            return ref
    c = scene_config(cfg, spec)
    what = (f"path tracer, {spec.paths:,} paths per {spec.block}x{spec.block}-pixel square"
            if spec.integrator == "pt" else
            f"PPM method {spec.method}, {spec.photons} stored photons/pass, {spec.passes} passes, "
            f"K = {spec.initial_photons}{', ' + str(spec.overrides) if spec.overrides else ''}")
    log(f"reference {key}: computing {what}, {spec.resolution[0]}x{spec.resolution[1]}, two halves "
        f"(seeds {spec.seeds[0]}, {spec.seeds[1]})")
    halves, reports = [], []
    t0 = time.perf_counter()
    with cached_volumes():
        full = apply_overrides(cfg, resolution=spec.resolution)
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
    b = spec.block
    exposure = float(halves[0].exposure)
    h = np.stack([block_mean(x.xyz, b) for x in halves])
    sp = [block_mean(x.spectral, b) for x in halves]
    xyz = h.mean(0)
    rgb = np.mean([block_mean(x.rgb, b) for x in halves], axis=0)
    spectral = np.mean(sp, axis=0).astype(np.float32)
    ref = Reference(key=key, spec=spec, xyz=xyz, rgb=rgb, halves_xyz=h, spectral=spectral,
                    wl=np.asarray(halves[0].wl), mask=mask, exposure=exposure, error={},
                    info={"halves": reports, "seconds": time.perf_counter() - t0,
                          "device": halves[0].report["device"]["name"]})
    # own noise: one half against the other, halved (at the reference's own resolution)
    half = dataclasses.replace(ref, xyz=h[1], spectral=sp[1], spec=dataclasses.replace(spec, block=1))
    e = accuracy(h[0], sp[0], half)
    err = {k: (v / 2.0 if isinstance(v, float) else v) for k, v in e.items() if k != "groups"}
    err["groups"] = {k: v / 2.0 for k, v in e["groups"].items()}
    err["note"] = ("noise of the mean of the two halves, estimated as (half1 vs half2) / 2"
                   + ("" if spec.integrator == "pt" else "; excludes the density-estimation bias the halves share"))
    ref.error = err
    _save(cache_dir, ref)
    log(f"reference {key}: saved {ref.path} ({ref.info['seconds']:.0f} s)")
    log(reference_summary(ref))
    return ref


def reference_summary(ref: Reference) -> str:
    e = ref.error
    return (f"reference own noise (from its two halves), per {ref.block}x{ref.block}-pixel square: "
            f"Y {100 * e['block_Y_rms']:.2f} % RMS ({100 * e['block_Y_max']:.2f} % max), mean CIEDE2000 "
            f"{e['de2000']:.3g}, mean skin colour dE00 {e['de_mean']:.3g}, 50-nm band groups "
            f"{100 * e['group_max']:.2f} % max; {int(ref.mask.sum())} skin squares")
