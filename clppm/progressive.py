"""The progressive loop: eye pass once, then per pass photon pass -> grid -> gather.

State between passes stays on the device (sample-point R and N, the pixel x band
accumulators); the host sees counters, the radii (to size the grid) and, every K passes,
the image.  A checkpoint is the pass index plus that state: photon pass p draws its
random numbers from (seed, p) alone, so a resumed render repeats the remaining passes
bit for bit.
"""
from __future__ import annotations

import json
import math
import os
import signal
import time
from dataclasses import dataclass, field

import numpy as np

from . import checkpoint as ckpt
from . import config as C
from . import eyepass, hashgrid, image, transport, volume
from .device import Device, DeviceError, check_alloc, open_device

FIX_NOTE = "fixed point 2^32 per unit weight x phase; pixel sums in float64"


@dataclass
class RenderResult:
    spectral: np.ndarray          # (H, W, NB) spectral radiance W m^-2 sr^-1 nm^-1
    xyz: np.ndarray               # (H, W, 3)
    rgb: np.ndarray               # (H, W, 3) linear sRGB
    wl: np.ndarray
    report: dict
    exposure: float = 1.0


def apply_overrides(cfg: dict, method=None, passes=None, photons=None, resolution=None,
                    seed=None, spacing=None, spp=None) -> dict:
    if method is not None:
        cfg = C.override(cfg, "render", "method", method)
    if spacing is not None:
        cfg = C.override(cfg, "render", "spacing_um", float(spacing))
    if passes is not None:
        cfg = C.override(cfg, "render", "passes", int(passes))
    if photons is not None:
        cfg = C.override(cfg, "render", "photons", int(photons))
        if cfg["render"]["initial_photons"] > cfg["render"]["photons"]:
            cfg = C.override(cfg, "render", "initial_photons", cfg["render"]["photons"])
    if resolution is not None:
        cfg = C.override(cfg, "camera", "resolution", [int(resolution[0]), int(resolution[1])])
    if seed is not None:
        cfg = C.override(cfg, "render", "seed", int(seed))
    if spp is not None:
        cfg = C.override(cfg, "camera", "spp", int(spp))
    return cfg


def hg_table(vol: volume.Volume) -> np.ndarray:
    g = vol.g.astype(np.float64)
    t = np.stack([1 + g * g, 2 * g, (1 - g * g) / (4 * math.pi), np.zeros_like(g)], -1)
    return np.ascontiguousarray(t.reshape(-1, 4), np.float32)


def light_scale(cfg: dict, wl: np.ndarray, spectrum: np.ndarray) -> dict:
    """Per-band factors that turn kernel tallies into SI radiance."""
    dl = float(wl[1] - wl[0]) if len(wl) > 1 else 1.0
    P = cfg["light"]["power_w"]
    return {"dl": dl, "P": P, "band_power": P * spectrum}


def white_reference(cfg: dict, cam, wl, spectrum) -> np.ndarray:
    """Spectral radiance of a white Lambertian plane z=0 at the image centre (W m^-2 sr^-1 nm^-1)."""
    L = cfg["light"]
    dl = float(wl[1] - wl[0]) if len(wl) > 1 else 1.0
    d = cam.ray(cam.width / 2, cam.height / 2)
    t = -cam.position[2] / d[2] if d[2] != 0 else 0.0
    x = cam.position + t * d
    Pb = L["power_w"] * spectrum / dl
    if L["kind"] == "point":
        lp = np.asarray(L["position_mm"], float) * 1000.0 - x
        d2 = float(lp @ lp)
        if d2 <= 0:
            return Pb * 0.0
        cos = max(lp[2] / math.sqrt(d2), 0.0)
        E = Pb / (4 * math.pi) * cos / d2 * 1e12
    elif L["kind"] == "wide":
        w = np.asarray(L["width_mm"], float) * 1e-3
        E = Pb / (w[0] * w[1])
    else:
        E = Pb * 0.0
    return E / math.pi


class _Interrupt:
    """First SIGINT/SIGTERM: finish the current pass and stop; second: abort."""

    def __init__(self):
        self.flag = False
        self.old = {}

    def __enter__(self):
        def handler(sig, frame):
            if self.flag:
                raise KeyboardInterrupt
            self.flag = True
        for s in (signal.SIGINT, signal.SIGTERM):
            try:
                self.old[s] = signal.signal(s, handler)
            except ValueError:           # not the main thread
                pass
        return self

    def __exit__(self, *a):
        for s, h in self.old.items():
            signal.signal(s, h)


def _progress(total, initial, enabled):
    if not enabled:
        return None
    try:
        from tqdm import tqdm
        return tqdm(total=total, initial=initial, unit="pass", dynamic_ncols=True, leave=True)
    except ImportError:      # pragma: no cover
        return None


def render(cfg: dict, *, method=None, passes=None, photons=None, resolution=None, seed=None,
           spacing=None, spp=None, device: str | None = None, out: str | None = None,
           progress: bool = False, resume: str | None = None, checkpoint_path: str | None = None,
           snapshot_every: int = 0, on_snapshot=None, dev: Device | None = None,
           source: str = "<config>", stop_after: int | None = None, on_pass=None) -> RenderResult:
    """Render ``cfg``; return the image and the run report.  See ``clppm render --help``."""
    t_start = time.perf_counter()
    cfg = apply_overrides(cfg, method, passes, photons, resolution, seed, spacing, spp)
    rc = cfg["render"]
    dev = dev or open_device(device)
    import pyopencl as cl
    import pyopencl.array as cla
    q = dev.queue
    timing = {"volume": 0.0, "eye": 0.0, "photon": 0.0, "grid": 0.0, "gather": 0.0, "output": 0.0}

    t0 = time.perf_counter()
    vol = volume.build(cfg, source)
    vbuf = transport.upload_volume(dev, vol)
    timing["volume"] = time.perf_counter() - t0

    from .camera import from_config
    cam0 = from_config(cfg["camera"])
    target = int(rc["photons"])
    capacity = int(target * 1.2) + 4096
    npix0, nrays0 = cam0.width * cam0.height, cam0.width * cam0.height * cam0.spp
    check_alloc(dev, {"stored photons": capacity * 32, "sorted photons": capacity * 36,
                      "grid cells": 4 * (hashgrid.DEFAULT_MAX_CELLS + 1) * 2,
                      "eye rays": (nrays0 + 1) * 8 + nrays0 * 8,
                      "pixel accumulators": npix0 * vol.nb * 8 + npix0 * 8, **vol.device_bytes()})
    if resume:
        ckpt.load(resume)                       # fail fast on a missing or corrupt file
    t0 = time.perf_counter()
    sch = eyepass.scheme(rc["method"], rc["spacing_um"])
    eye = eyepass.run(dev, vol, vbuf, cfg, sch)
    q.finish()
    timing["eye"] = time.perf_counter() - t0
    cam = eye.camera
    npix = cam.width * cam.height
    nb, nl = vol.nb, vol.nl

    needs = {
        "stored photons": capacity * 32,
        "sorted photons": capacity * 36,
        "grid cells": 4 * (hashgrid.DEFAULT_MAX_CELLS + 1) * 2,
        "sample points": eye.device_bytes(),
        "pixel accumulators": npix * nb * 8 + npix * 8,
        **vol.device_bytes(),
    }
    check_alloc(dev, needs)

    pp = transport.PhotonPass(dev, vol, cfg, capacity=capacity, vbuf=vbuf)
    prg = dev.build("gather.cl", {**transport.defines(vol),
                                  "ESTIMATOR": {"sphere": 0, "clip": 1, "layer": 2}[rc["estimator"]]})
    k_gather = cl.Kernel(prg, "gather")
    k_init = cl.Kernel(prg, "init_radius")
    k_count = cl.Kernel(prg, "count_within")
    mf = cl.mem_flags
    hgtab = cl.Buffer(dev.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=hg_table(vol))
    lz = np.stack([np.maximum(vol.iface[1:, 1], -1e30), vol.iface[:-1, 2]], -1).astype(np.float32)
    layer_z = cl.Buffer(dev.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(lz))
    npts = eye.npoints
    pt_R = cla.zeros(q, max(npts, 1), np.float32)
    pt_N = cla.zeros(q, max(npts, 1), np.float32)
    pt_M = cla.zeros(q, max(npts, 1), np.uint32)
    pix_acc = cla.zeros(q, npix * nb, np.float64)
    pix_pairs = cla.zeros(q, npix, np.uint64)
    gbufs = hashgrid.GridBuffers(dev)

    meta = run_identity(cfg, dev, eye)
    start_pass, emitted_total, store_zmin, first_search = 0, 0, None, None
    stats = {"stored": 0, "emitted": [], "first_search_mean": None}
    if resume:
        st = ckpt.load(resume, meta)
        start_pass = st["pass_index"]
        emitted_total = st["emitted_total"]
        store_zmin = st["store_zmin"]
        pt_R.set(st["pt_R"].astype(np.float32)) if npts else None
        pt_N.set(st["pt_N"].astype(np.float32)) if npts else None
        pix_acc.set(st["pix_acc"].reshape(-1))
        pix_pairs.set(st["pix_pairs"])
        pp.tallies.counts = st["tallies"]
        pp.tallies.emitted = st["tallies_emitted"]
        stats = st["stats"]
        timing.update({k: v for k, v in st["timing"].items() if k in timing and k not in ("volume", "eye")})
    if store_zmin is not None:
        pp.p["store_zmin"] = store_zmin

    x0, y0 = vol.x0, vol.y0
    x1, y1 = vol.x0 + vol.nx * vol.dx, vol.y0 + vol.ny * vol.dy
    zdeep = float(-eye.depth.max()) if npts else vol.z_top
    n_passes = int(rc["passes"])
    bar = _progress(n_passes, start_pass, progress)
    cp_every = int(rc["checkpoint_every"])
    ckpath = checkpoint_path or (ckpt.default_path(out) if out else None)
    interrupted = False
    p = start_pass
    global_radius = rc["radius"] == "global"
    alpha = float(rc["alpha"])
    K = float(rc["initial_photons"])
    last_ckpt = start_pass if resume else None
    with _Interrupt() as intr:
      try:
        while p < n_passes:
            # ---- photon pass
            t0 = time.perf_counter()
            info = pp.run_pass(p, target)
            n = min(info["stored"], capacity)
            q.finish()
            timing["photon"] += time.perf_counter() - t0
            emitted_total += info["emitted"]
            stats["emitted"].append(info["emitted"])
            stats["stored"] += n
            # ---- grid over the photons sample points can reach
            t0 = time.perf_counter()
            if npts:
                if p == 0 and not resume:
                    depth = max(vol.z_top - zdeep, 1.0)
                    vbox = (x1 - x0) * (y1 - y0) * (depth + 1.0)
                    r_guess = (3 * K * vbox / (4 * math.pi * max(n, 1))) ** (1 / 3)
                    r_guess = min(r_guess, 0.5 * max(x1 - x0, y1 - y0))
                    rmax = 4.0 * r_guess
                    radii = np.array([r_guess])
                else:
                    radii = pt_R.get()
                    rmax = float(radii.max())
                pad = rmax * 1.001 + 1.0
                lo = (x0 - pad, y0 - pad, zdeep - pad)
                hi = (x1 + pad, y1 + pad, vol.z_top + pad)
                h = hashgrid.choose_cell_size(radii, lo, hi)
                grid = hashgrid.build(dev, pp.pos_w, pp.dir_b, n, lo, hi, h, buffers=gbufs)
                if p == 0 and not resume:
                    k_init(q, (_round(npts),), (64,), grid.params, grid.cell_start.data, eye.pt_pos.data,
                           pt_R.data, np.uint32(npts), np.float32(K), np.float32(r_guess),
                           np.float32(rmax), np.int32(4))
                    h = hashgrid.choose_cell_size(pt_R.get(), lo, hi)
                    grid = hashgrid.build(dev, pp.pos_w, pp.dir_b, n, lo, hi, h, buffers=gbufs)
                    # calibrate: exact counts on a subsample, one global scale so the mean is K
                    stride = max(1, npts // 20000)
                    ns = (npts + stride - 1) // stride
                    cnt = cla.zeros(q, ns, np.uint32)
                    for _ in range(2):
                        k_count(q, (_round(ns),), (64,), grid.params, grid.cell_start.data,
                                grid.spos_w.data, grid.sdir_b.data, eye.pt_pos.data, eye.pt_dir.data,
                                pt_R.data, layer_z, np.uint32(npts),
                                np.uint32(stride), cnt.data)
                        mean_m = float(cnt.get().mean())
                        if mean_m <= 0:
                            break
                        pt_R *= np.float32(min(max((K / mean_m) ** (1 / 3), 0.5), 2.0))
                    radii = pt_R.get()
                    rmax = float(radii.max())
                    h = hashgrid.choose_cell_size(radii, lo, hi)
                    grid = hashgrid.build(dev, pp.pos_w, pp.dir_b, n, lo, hi, h, buffers=gbufs)
                    # photons deeper than any sample point's sphere can never be gathered
                    store_zmin = zdeep - rmax * 1.001
                    pp.p["store_zmin"] = store_zmin
            q.finish()
            timing["grid"] += time.perf_counter() - t0
            # ---- gather into the sample points and pixels
            t0 = time.perf_counter()
            if npts:
                pairs_before = None
                if p == 0 and not resume:
                    pairs_before = pix_pairs.get().sum()
                rf = ((p + alpha) / (p + 1.0)) ** (1.0 / 3.0)
                pass_scale = 1.0 / max(info["emitted"], 1) if global_radius else 1.0
                k_gather(q, (_round(npix),), (64,), grid.params, grid.cell_start.data, grid.spos_w.data,
                         grid.sdir_b.data, hgtab, vbuf.optics, eye.ray_start.data, eye.pt_pos.data,
                         eye.pt_dir.data, eye.pt_piece.data, eye.pieces.data, eye.pt_slab.data, layer_z,
                         pt_R.data, pt_N.data, pt_M.data, pix_acc.data, pix_pairs.data, np.int32(npix), np.int32(cam.spp),
                         np.float32(alpha), np.int32(global_radius), np.float32(rf),
                         np.float64(pass_scale))
                if pairs_before is not None:
                    stats["first_search_mean"] = float((pix_pairs.get().sum() - pairs_before) / npts)
            q.finish()
            timing["gather"] += time.perf_counter() - t0
            if on_pass is not None:
                on_pass(p, {"pt_R": pt_R, "pt_N": pt_N, "pt_M": pt_M, "emitted": info["emitted"]})
            p += 1
            if bar is not None:
                bar.update(1)
            stop = intr.flag or (stop_after is not None and p >= stop_after)
            state = dict(pass_index=p, emitted_total=emitted_total, store_zmin=store_zmin,
                         tallies=pp.tallies.counts, tallies_emitted=pp.tallies.emitted,
                         stats=stats, timing=timing)
            if ckpath and ((cp_every and p % cp_every == 0) or stop or p == n_passes):
                ckpt.save(ckpath, meta, state, pt_R.get()[:npts], pt_N.get()[:npts],
                          pix_acc.get().reshape(npix, nb), pix_pairs.get())
                last_ckpt = p
            if snapshot_every and on_snapshot and (p % snapshot_every == 0 or p == n_passes or stop):
                res = _finish(cfg, vol, eye, pp, pix_acc, pix_pairs, emitted_total, p, timing, stats,
                              dev, t_start, rc, interrupted=False, meta=meta)
                on_snapshot(p, time.perf_counter() - t_start, res)
            if rc["preview_every"] and out and p % rc["preview_every"] == 0 and p < n_passes:
                res = _finish(cfg, vol, eye, pp, pix_acc, pix_pairs, emitted_total, p, timing, stats,
                              dev, t_start, rc, interrupted=False, meta=meta)
                image.write_png(_sibling(out, ".preview.png"), res.rgb, res.exposure)
            if stop:
                interrupted = intr.flag
                break
      except cl.Error as e:
        msg = " ".join(str(e).split())
        keep = (f"checkpoint {ckpath} (pass {last_ckpt}) is kept: resume with --resume {ckpath}"
                if last_ckpt else "no checkpoint was written yet")
        raise DeviceError(f"device '{dev.name}' failed in pass {p + 1} of {n_passes} ({msg}); {keep}") from None
    if bar is not None:
        bar.close()
    t0 = time.perf_counter()
    res = _finish(cfg, vol, eye, pp, pix_acc, pix_pairs, emitted_total, p, timing, stats, dev,
                  t_start, rc, interrupted=interrupted, meta=meta)
    if out:
        write_outputs(out, res)
    res.report["seconds"]["output"] = time.perf_counter() - t0
    if out:
        _write_report(out, res.report)
    return res


def _round(n: int, wg: int = 64) -> int:
    return max(wg, (n + wg - 1) // wg * wg)


def _sibling(out: str, suffix: str) -> str:
    base, _ = os.path.splitext(out)
    return base + suffix


def run_identity(cfg: dict, dev: Device, eye) -> dict:
    """What a checkpoint must match to be resumed."""
    keep = {k: v for k, v in cfg.items()}
    keep = json.loads(json.dumps(keep, default=str))
    keep["render"] = {k: v for k, v in keep["render"].items()
                      if k not in ("passes", "preview_every", "checkpoint_every")}
    return {"config": keep, "device": dev.name, "npoints": int(eye.npoints),
            "npieces": int(eye.npieces), "nrays": int(eye.nrays)}


def _finish(cfg, vol, eye, pp, pix_acc, pix_pairs, emitted_total, passes_done, timing, stats, dev,
            t_start, rc, interrupted, meta) -> RenderResult:
    cam = eye.camera
    H, W, nb = cam.height, cam.width, vol.nb
    wl = vol.wl
    dl = float(wl[1] - wl[0]) if len(wl) > 1 else 1.0
    acc = pix_acc.get().reshape(H * W, nb)
    P = cfg["light"]["power_w"] * pp.power_fraction
    if rc["radius"] == "global":
        scale = P / max(passes_done, 1)
    else:
        scale = P / max(emitted_total, 1)
    L = acc * (scale * 1e12 / dl / cam.spp)
    if rc["specular"]:
        spec = eye.ray_spec.reshape(H * W, cam.spp).mean(1)
        band_I = cfg["light"]["power_w"] * pp.spectrum / dl
        Lk = cfg["light"]["kind"]
        if Lk == "point":
            fac = band_I / (4 * math.pi) * 1e12
        elif Lk == "wide":
            w = np.asarray(cfg["light"]["width_mm"], float) * 1e-3
            cosb = max(-cfg["light"]["direction"][2] / np.linalg.norm(cfg["light"]["direction"]), 1e-6)
            fac = band_I / (w[0] * w[1] * cosb)
        else:
            fac = band_I * 0.0
        L = L + spec[:, None] * fac[None, :]
    nonfinite = int(np.size(L) - np.count_nonzero(np.isfinite(L)))
    L = np.nan_to_num(L, nan=0.0, posinf=0.0, neginf=0.0).reshape(H, W, nb)
    if nb > 1:
        xyz = image.spectral_to_xyz(L, wl)
    else:
        xyz = L * image.cmfs(wl)[None, None, 0, :] * dl
    rgb = image.xyz_to_linear_srgb(xyz)
    white = white_reference(cfg, cam, wl, pp.spectrum)
    if nb > 1:
        Yw = float(image.spectral_to_xyz(white[None, :], wl)[0, 1])
    else:
        Yw = float((white * image.cmfs(wl)[:, 1] * dl).sum())
    exposure = rc["exposure"] if rc["exposure"] is not None else (1.0 / Yw if Yw > 0 else 1.0)
    pairs = int(pix_pairs.get().sum())
    total = time.perf_counter() - t_start
    per_layer = eye.per_layer(vol.nl)
    report = {
        "clppm": __import__("clppm").__version__,
        "config": json.loads(json.dumps(cfg, default=str)),
        "method": rc["method"], "scheme": eye.scheme.label(),
        "device": dev.info(),
        "passes_done": passes_done, "passes_requested": rc["passes"], "interrupted": interrupted,
        "photons_emitted": emitted_total, "photons_stored": stats["stored"],
        "stored_per_pass": rc["photons"], "store_zmin_um": None if pp.p["store_zmin"][0] < -1e37
        else float(pp.p["store_zmin"][0]),
        "sample_points": eye.npoints, "path_pieces": eye.npieces,
        "eye_rays": eye.nrays, "eye_rays_hit": int(eye.ray_hit.sum()),
        "sample_points_per_ray_per_layer": {n: float(v) for n, v in zip(vol.names, per_layer)},
        "first_search_mean_photons": stats["first_search_mean"],
        "gather_pairs": pairs,
        "seconds": dict(timing, total=total),
        "seconds_per_pass": {k: timing[k] / max(passes_done, 1) for k in ("photon", "grid", "gather")},
        "exposure": exposure,
        "white_reference_Y": Yw,
        "volume": vol.info, "accumulation": FIX_NOTE,
        "nonfinite_values_zeroed": nonfinite,
        "units": "spectral radiance W m^-2 sr^-1 nm^-1 (EXR spectral channels); RGB linear sRGB",
    }
    return RenderResult(spectral=L, xyz=xyz, rgb=rgb, wl=wl, report=report, exposure=exposure)


def write_outputs(out: str, res: RenderResult) -> None:
    d = os.path.dirname(os.path.abspath(out))
    os.makedirs(d, exist_ok=True)
    hdr = {"clppm_report": json.dumps({k: res.report[k] for k in ("method", "scheme", "passes_done",
                                                                   "photons_emitted", "exposure")})}
    tmp = out + ".tmp.exr"
    image.write_exr(tmp, res.rgb.astype(np.float32), spectral=res.spectral.astype(np.float32),
                    wl=res.wl, header=hdr)
    os.replace(tmp, out)
    image.write_png(_sibling(out, ".png"), res.rgb, res.exposure)


def _write_report(out: str, report: dict) -> None:
    path = _sibling(out, ".json")
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(report, f, indent=1, default=str)
    os.replace(tmp, path)
