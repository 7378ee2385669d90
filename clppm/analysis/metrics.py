"""Image metrics: the error of a rendered image against a converged reference.

* per pixel (:func:`error_metrics`): RMSE of linear XYZ, CIEDE2000, u'v' and Lab shifts, the
  brightness bias, and LDR-FLIP of the displayed images (:func:`flip_error`);
* per square (:func:`block_mean`, :func:`block_mask`): the images averaged over ``b`` x ``b``
  squares of pixels, where a path-tracing reference pixel is the exact mean of its square;
* :func:`accuracy`: those errors over the squares, plus the relative error of Y per square, the
  CIEDE2000 of the mean skin colour and the relative error of the mean skin radiance per 50-nm
  band group (:func:`band_groups`);
* :func:`accuracy_of_seeds`: the same for the mean of several seeds, with each square's noise
  separated from its bias (:func:`square_standard_errors`) and the squares whose bias exceeds a
  bound beyond doubt (:func:`beyond`).

Skin pixels (the errors are taken over them) are the pixels all of whose eye rays hit the
model (:func:`skin_mask_from_eye`).  The reference itself (its cache, its two halves, its own
noise) is :mod:`clppm.analysis.reference`; these functions read only its arrays (``xyz``,
``spectral``, ``wl``, ``mask``, ``exposure``, ``block``, ``halves_xyz``, ``error``).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..scene import colorimetry


# ----------------------------------------------------------------------------- pixels
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
    out["de2000"] = float(np.mean(colorimetry.delta_e2000(a, b)))
    ua, ub = colorimetry.xyz_to_uv_prime(a), colorimetry.xyz_to_uv_prime(b)
    duv = ua - ub
    out["du"], out["dv"] = float(duv[:, 0].mean()), float(duv[:, 1].mean())
    out["duv"] = float(np.mean(np.hypot(duv[:, 0], duv[:, 1])))
    uma = colorimetry.xyz_to_uv_prime(a.mean(0))
    umb = colorimetry.xyz_to_uv_prime(b.mean(0))
    out["du_mean"], out["dv_mean"] = float(uma[0] - umb[0]), float(uma[1] - umb[1])
    la, lb = colorimetry.xyz_to_lab(a), colorimetry.xyz_to_lab(b)
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
    t = colorimetry.encode_srgb(np.asarray(rgb, float) * exposure).astype(np.float32)
    r = colorimetry.encode_srgb(np.asarray(ref_rgb, float) * exposure).astype(np.float32)
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
    m["de_mean"] = float(colorimetry.delta_e2000(a[None], r[None])[0])
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
                 bias_Y_rms=float(np.sqrt(max(resid, 0.0))),
                 seed_Y_max=[float(accuracy(x, s, sq)["block_Y_max"]) for x, s in images])
        rel = np.mean([x[..., 1] for x, _ in images], 0)[ref.mask] / Yr - 1
        se = square_standard_errors(images, ref)[ref.mask]
        m.update(beyond(rel, se, BIAS_BOUND))
    return m


#: the bias bound per 10x10-pixel square the default mode is held to against the path tracer
#: (bench/studies/bias.py; the README's bias table counts the squares beyond it)
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


#: the bound on the default mode's bias per 50-nm band group against the path tracer
#: (bench/studies/band_bias.py states, at a confidence, whether each group keeps it)
GROUP_BOUND = 0.01


def band_group_confidence(spectra: list, ref, bound: float = GROUP_BOUND, level: float = 0.95) -> dict:
    """Per 50-nm band group, the relative error of the mean skin radiance of ``spectra`` (renders
    of one scheme with different seeds, each (h, w, NB) at the reference's squares) against
    ``ref``, with a ``level`` confidence interval and a verdict against ``bound``.

    The error's variance has two parts: the seeds' scatter of the group mean / n (n - 1 degrees
    of freedom), and the reference's own, from its two halves square by square (its squares'
    paths are independent: var of the mean = sum over skin squares of ((h1 - h2) / 2)^2 / n_sq^2,
    n_sq - 1 degrees of freedom); the interval is Student's t at Welch-Satterthwaite's degrees of
    freedom.  The verdict: ``within`` (the whole interval inside +-bound), ``beyond`` (the whole
    interval outside) or ``open`` (more seeds or reference paths decide it)."""
    from scipy import stats
    if ref.halves_spectral is None:
        raise ValueError("the reference has no spectral halves (made before they were kept): recompute it")
    mask = ref.mask
    n, nsq = len(spectra), int(mask.sum())
    if n < 2:
        raise ValueError("a confidence needs two seeds or more")
    out = {}
    for lo, hi, idx in band_groups(ref.wl):
        x = np.array([np.asarray(s, float)[mask][:, idx].sum(1).mean() for s in spectra])
        a, b = (np.asarray(h, float)[mask][:, idx].sum(1) for h in ref.halves_spectral)
        R = 0.5 * (a.mean() + b.mean())
        v_img = x.var(ddof=1) / n / R ** 2
        v_ref = (x.mean() / R ** 2) ** 2 * float(np.sum(((a - b) / 2) ** 2)) / nsq ** 2
        se = float(np.sqrt(v_img + v_ref))
        dof = se ** 4 / (v_img ** 2 / (n - 1) + v_ref ** 2 / max(nsq - 1, 1))
        e = float(x.mean() / R - 1)
        half = float(stats.t.ppf(0.5 + level / 2, dof)) * se
        verdict = "within" if abs(e) + half <= bound else ("beyond" if abs(e) - half > bound else "open")
        out[f"{lo:.0f}-{hi:.0f}"] = {
            "error": e, "half_width": half, "se": se, "se_seeds": float(np.sqrt(v_img)),
            "se_reference": float(np.sqrt(v_ref)), "dof": float(dof), "verdict": verdict,
            "one_image": [float(v / R - 1) for v in x]}
    return {"level": level, "bound": bound, "seeds": n, "squares": nsq, "groups": out}
