"""The progressive loop in this process: setup, calibration, passes in chunks, checkpoints.

The passes themselves are :mod:`clppm.ppm`'s pieces.  State between passes stays on the
device (sample-point R and N, the pixel x band accumulators of the closed chunks and of the
open one); the host sees counters, the radii (to size the grid) and, every K passes, the
image.  A checkpoint is the pass index plus that state: photon pass p draws its random
numbers from (seed, p) alone, so a resumed render repeats the remaining passes bit for bit.
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
from . import image, paths, ppm, transport
from .device import Device, DeviceError, open_device

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
    """First SIGINT/SIGTERM: finish the current pass and stop; second: abort.  The signal that
    stopped the last render is kept in ``_Interrupt.received`` (the command's exit code)."""

    received: int | None = None

    def __init__(self):
        self.flag = False
        self.old = {}

    def __enter__(self):
        _Interrupt.received = None

        def handler(sig, frame):
            if self.flag:
                raise KeyboardInterrupt
            self.flag = True
            _Interrupt.received = sig
        for s in (signal.SIGINT, signal.SIGTERM):
            try:
                self.old[s] = signal.signal(s, handler)
            except ValueError:           # not the main thread
                pass
        return self

    def __exit__(self, *a):
        for s, h in self.old.items():
            signal.signal(s, h)


def interrupt_signal() -> int | None:
    """The signal (SIGINT or SIGTERM) that stopped the last render in this process, or None."""
    return _Interrupt.received


class _PlainProgress:
    """Progress as plain lines (stderr is a file or a pipe: a log, a batch job): about every
    10 % of the passes or every 30 s, and at the end."""

    def __init__(self, total: int, initial: int):
        self.total, self.n, self.t0, self.last = total, initial, time.perf_counter(), 0.0
        self.every = max(1, total // 10)
        self.start = initial

    def update(self, k: int = 1) -> None:
        import sys
        self.n += k
        t = time.perf_counter() - self.t0
        if self.n % self.every and self.n != self.total and t - self.last < 30:
            return
        self.last = t
        rate = (self.n - self.start) / t if t > 0 else 0.0
        eta = f", {(self.total - self.n) / rate:.0f} s to go" if rate > 0 and self.n < self.total else ""
        print(f"pass {self.n}/{self.total}: {t:.1f} s{eta}", file=sys.stderr, flush=True)

    def close(self) -> None:
        pass


def say(enabled: bool, msg: str) -> None:
    """A setup status line on stderr (``building the volume...``) unless quiet."""
    if enabled:
        import sys
        print(msg, file=sys.stderr, flush=True)


def _progress(total, initial, enabled):
    import sys
    if not enabled:
        return None
    if not sys.stderr.isatty():
        return _PlainProgress(total, initial)
    try:
        from tqdm import tqdm
        return tqdm(total=total, initial=initial, unit="pass", dynamic_ncols=True, leave=True)
    except ImportError:      # pragma: no cover
        return None


def check_resume_passes(resume: str | None, passes: int, flag: str = "--passes") -> None:
    """Resuming must not ask for fewer passes than the checkpoint holds (it cannot un-render)."""
    if not resume:
        return
    have = ckpt.pass_index(resume)
    if have is not None and passes < have:
        raise C.ConfigError("command line", flag, passes,
                            f"is below the {have} passes checkpoint {os.path.basename(resume)} holds; "
                            f"give --passes {have} or more (or start over without --resume)")


def render(cfg: dict, *, method=None, passes=None, photons=None, resolution=None, seed=None,
           spacing=None, spp=None, device: str | None = None, out: str | None = None,
           progress: bool = False, resume: str | None = None, checkpoint_path: str | None = None,
           snapshot_every: int = 0, on_snapshot=None, dev: Device | None = None,
           source: str = "<config>", stop_after: int | None = None, on_pass=None) -> RenderResult:
    """Render ``cfg`` in this process; return the image and the run report.

    The loop around :mod:`clppm.ppm`'s pieces: setup, calibration (or a checkpoint's state),
    chunks of passes reduced in order, checkpoints, snapshots, previews, progress and the
    first-signal stop.  See ``clppm render --help``."""
    t_start = time.perf_counter()
    cfg = apply_overrides(cfg, method, passes, photons, resolution, seed, spacing, spp)
    rc = cfg["render"]
    ckpath = checkpoint_path or (ckpt.default_path(out) if out else None)
    paths.check_outputs(out=out, checkpoint=ckpath)
    dev = dev or open_device(device)
    import pyopencl as cl
    if resume:
        ckpt.load(resume)                       # fail fast on a missing or corrupt file
        check_resume_passes(resume, int(rc["passes"]), "--passes" if passes is not None else "render.passes")
    say(progress, f"building the volume and the eye pass ({cfg['camera']['resolution'][0]}x"
                  f"{cfg['camera']['resolution'][1]}, method {rc['method']}) on {dev.name}...")
    sc = ppm.setup(cfg, dev, source)
    meta = run_identity(cfg, dev, sc.eye)
    say(progress, f"{sc.eye.npoints} sample points; " + (f"resuming {os.path.basename(resume)}..." if resume
                  else "calibrating the first photon search..."))
    run = RunState.start(sc, meta, resume)
    n_passes = int(rc["passes"])
    k = int(rc["chunk_passes"])
    bar = _progress(n_passes, run.p, progress)
    cp_every = int(rc["checkpoint_every"])
    interrupted = False
    last_ckpt = run.p if resume else None
    with _Interrupt() as intr:
      try:
        while run.p < n_passes:
            p = run.p
            info = ppm.run_pass(sc, run.cal, run.points, p, run.chunk, run.tallies)
            run.emitted.append(info["emitted"])
            run.stored += min(info["stored"], sc.capacity)
            if on_pass is not None:
                on_pass(p, {"pt_R": run.points.R, "pt_N": run.points.N, "pt_M": run.points.M,
                            "emitted": info["emitted"], "radius_scale": info.get("radius_scale", 1.0)})
            run.p = p + 1
            if run.p % k == 0 or run.p == n_passes:
                run.close_chunk()
            if bar is not None:
                bar.update(1)
            stop = intr.flag or (stop_after is not None and run.p >= stop_after)
            if ckpath and ((cp_every and run.p % cp_every == 0) or stop or run.p == n_passes):
                run.save(ckpath, meta)
                last_ckpt = run.p
            if snapshot_every and on_snapshot and (run.p % snapshot_every == 0 or run.p == n_passes or stop):
                on_snapshot(run.p, time.perf_counter() - t_start, image_of(run, t_start, interrupted=False))
            if rc["preview_every"] and out and run.p % rc["preview_every"] == 0 and run.p < n_passes:
                res = image_of(run, t_start, interrupted=False)
                image.write_png(_sibling(out, ".preview.png"), res.rgb, res.exposure)
            if stop:
                interrupted = intr.flag
                break
      except cl.Error as e:
        msg = " ".join(str(e).split())
        keep = (f"checkpoint {ckpath} (pass {last_ckpt}) is kept: resume with --resume {ckpath}"
                if last_ckpt else "no checkpoint was written yet")
        raise DeviceError(f"device '{dev.name}' failed in pass {run.p + 1} of {n_passes} ({msg}); {keep}") from None
    if bar is not None:
        bar.close()
    t0 = time.perf_counter()
    res = image_of(run, t_start, interrupted=interrupted)
    if out:
        write_outputs(out, res)
    res.report["seconds"]["output"] = time.perf_counter() - t0
    if out:
        _write_report(out, res.report)
    return res


@dataclass
class RunState:
    """A render in progress: the scene, its calibration and point state, the reduced total,
    the open chunk, and the counts.  A checkpoint is this, minus the device."""

    sc: ppm.Scene
    cal: ppm.Calibration
    points: ppm.PointState
    total: ppm.Accumulators           # sum of the closed chunks, added in chunk order
    chunk: ppm.Accumulators           # the open chunk
    tallies: transport.Tallies
    p: int = 0                        # passes done
    emitted: list = field(default_factory=list)
    stored: int = 0

    @classmethod
    def start(cls, sc: ppm.Scene, meta: dict, resume: str | None) -> "RunState":
        if not resume:
            t0 = time.perf_counter()
            cal = ppm.calibrate(sc)
            sc.dev.queue.finish()
            sc.timing["calibration"] = time.perf_counter() - t0
            run = cls(sc=sc, cal=cal, points=ppm.point_state(sc, cal), total=ppm.Accumulators.zeros(sc),
                      chunk=ppm.Accumulators.zeros(sc), tallies=transport.Tallies(sc.vol.nb, sc.vol.nl))
        else:
            st = ckpt.load(resume, meta)
            cal = ppm.Calibration(R0=st["R0"].astype(np.float32), store_zmin=st["store_zmin"],
                                  first_search_mean=st["stats"].get("first_search_mean"))
            run = cls(sc=sc, cal=cal, points=ppm.point_state(sc, cal), total=ppm.Accumulators.zeros(sc),
                      chunk=ppm.Accumulators.zeros(sc), tallies=transport.Tallies(sc.vol.nb, sc.vol.nl),
                      p=st["pass_index"], emitted=list(st["stats"]["emitted"]), stored=st["stats"]["stored"])
            if sc.npts:
                run.points.R[:sc.npts].set(st["pt_R"].astype(np.float32))
                run.points.N[:sc.npts].set(st["pt_N"].astype(np.float32))
            run.total.pix.set(st["pix_acc"].reshape(-1))
            run.chunk.pix.set(st["chunk_acc"].reshape(-1))
            run.total.pairs.set(st["pix_pairs"])
            run.tallies.counts = st["tallies"]
            run.tallies.emitted = st["tallies_emitted"]
            sc.timing.update({k: v for k, v in st["timing"].items() if k in ppm.STAGES + ("calibration",)})
        ppm.prepare(sc, cal)
        return run

    def close_chunk(self) -> None:
        self.total.add(self.chunk)
        self.chunk.clear()

    def host_sums(self) -> tuple[np.ndarray, np.ndarray]:
        """The image's sums: the closed chunks plus the open one (which stays open)."""
        pix, pairs = self.total.host()
        cpix, cpairs = self.chunk.host()
        return pix + cpix, pairs + cpairs

    def save(self, path: str, meta: dict) -> None:
        n = self.sc.npts
        stats = {"emitted": self.emitted, "stored": self.stored,
                 "first_search_mean": self.cal.first_search_mean}
        state = dict(pass_index=self.p, emitted_total=sum(self.emitted), store_zmin=self.cal.store_zmin,
                     tallies=self.tallies.counts, tallies_emitted=self.tallies.emitted, stats=stats,
                     timing=self.sc.timing)
        nb = self.sc.vol.nb
        pix, pairs = self.total.host()
        cpix, cpairs = self.chunk.host()
        ckpt.save(path, meta, state, pt_R=self.points.R.get()[:n], pt_N=self.points.N.get()[:n],
                  R0=self.cal.R0, pix_acc=pix.reshape(-1, nb), chunk_acc=cpix.reshape(-1, nb),
                  pix_pairs=pairs + cpairs)


def _sibling(out: str, suffix: str) -> str:
    base, _ = os.path.splitext(out)
    return base + suffix


def run_identity(cfg: dict, dev: Device, eye) -> dict:
    """What a checkpoint must match to be resumed."""
    keep = {k: v for k, v in cfg.items()}
    keep = json.loads(json.dumps(keep, default=str))
    keep["render"] = {k: v for k, v in keep["render"].items() if k not in C.NOT_PICTURE}
    return {"config": keep, "device": dev.name, "npoints": int(eye.npoints),
            "npieces": int(eye.npieces), "nrays": int(eye.nrays)}


def image_of(run: RunState, t_start: float, interrupted: bool) -> RenderResult:
    """The image and run report of the passes done so far."""
    sc = run.sc
    pix, pairs = run.host_sums()
    return finish(sc.cfg, sc.vol, sc.eye, sc.pp, pix, int(pairs.sum()), sum(run.emitted), run.p,
                  sc.timing, {"stored": run.stored, "first_search_mean": run.cal.first_search_mean},
                  sc.dev, t_start, interrupted=interrupted)


def finish(cfg, vol, eye, pp, pix: np.ndarray, pairs: int, emitted_total: int, passes_done: int,
           timing: dict, stats: dict, dev, t_start: float, interrupted: bool) -> RenderResult:
    """Pixel x band sums -> spectral radiance, XYZ, linear sRGB, exposure and the run report."""
    rc = cfg["render"]
    cam = eye.camera
    H, W, nb = cam.height, cam.width, vol.nb
    wl = vol.wl
    dl = float(wl[1] - wl[0]) if len(wl) > 1 else 1.0
    acc = pix.reshape(H * W, nb)
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
    total = time.perf_counter() - t_start
    per_layer = eye.per_layer(vol.nl)
    report = {
        "clppm": __import__("clppm").__version__,
        "config": json.loads(json.dumps(cfg, default=str)),
        "integrator": "ppm",
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
        "seconds_per_pass": {k: timing.get(k, 0.0) / max(passes_done, 1) for k in ppm.STAGES},
        "exposure": exposure,
        "white_reference_Y": Yw,
        "volume": vol.info, "accumulation": FIX_NOTE,
        "nonfinite_values_zeroed": nonfinite,
        "units": "spectral radiance W m^-2 sr^-1 nm^-1 (EXR spectral channels); RGB linear sRGB",
    }
    return RenderResult(spectral=L, xyz=xyz, rgb=rgb, wl=wl, report=report, exposure=exposure)


def write_outputs(out: str, res: RenderResult) -> None:
    """The image at ``out``: ``.exr`` the spectral + RGB EXR and the PNG beside it; ``.png``
    the PNG alone (:func:`clppm.paths.render_outputs`)."""
    d = os.path.dirname(os.path.abspath(out))
    os.makedirs(d, exist_ok=True)
    files = paths.render_outputs(out)
    if "png" in files:
        hdr = {"clppm_report": json.dumps({k: res.report[k] for k in ("method", "scheme", "passes_done",
                                                                       "photons_emitted", "exposure")})}
        tmp = out + ".tmp.exr"
        image.write_exr(tmp, res.rgb.astype(np.float32), spectral=res.spectral.astype(np.float32),
                        wl=res.wl, header=hdr)
        os.replace(tmp, out)
    image.write_png(files.get("png", out), res.rgb, res.exposure)


def _write_report(out: str, report: dict) -> None:
    path = paths.render_outputs(out)["report"]
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(report, f, indent=1, default=str)
    os.replace(tmp, path)
