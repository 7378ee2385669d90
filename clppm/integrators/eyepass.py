"""Eye-ray pass (kernels/eye.cl): camera rays, refraction, sample points by scheme a-f.

Schemes (paper section 5):
  a, b, c   equal spacing 4, 7, 14 um (or any ``spacing_um``), cut where the
            transmittance from the entry point falls below the threshold;
  d, e, f   Poisson points with mean spacing 1/extinction of the current layer, the
            extinction being the layer's maximum, mean or minimum over the bands; a layer
            visit without a point gets its exit point; same cut.

Sample-point storage on the device (bytes per point, and why):
  pt_pos    16  position (3 x f32) + Fresnel/n^2 throughput factor to the camera
  pt_dir    16  direction to the eye (3 x f32) + layer index (for g of the phase function)
  pt_piece   4  index of the point's first path piece
  pt_slab    8  top and bottom of the point's layer at its column (the estimator's volume)
  pt_R, pt_N 8  progressive radius and accumulated photon count
  pt_M       4  photons found in the last pass (statistics, tests)
  pieces    ~9  (8 per piece, ~1.1 pieces per point): the layer lengths of the point's path
                interval, from which the gather kernel evaluates the per-band weight
                integral of T over the interval exactly
  = about 65 bytes.  The paper's per-point rho(lambda) and Phi(lambda) (2 x 81 floats) are
  not needed: rho is recomputed from the pieces, and Phi/V only ever grows by the pass's
  F/V, which goes straight into the pixel (see kernels/gather.cl).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..compute import structs as S
from ..config import RenderSettings, render_settings
from ..scene.camera import Camera, from_config
from ..scene.light import Light
from ..compute.device import Device, DeviceError, check_alloc, kernel_defines, surface_fp64
from ..compute.constants import EyeMode
from .hashgrid import exclusive_scan
from ..compute.kernelcall import kernels
from ..scene.volume import Volume, VolumeBuffers, volume_params

SPACING = {"a": 4.0, "b": 7.0, "c": 14.0}
EXTINCTION_STAT = {"d": "max", "e": "mean", "f": "min"}


@dataclass(frozen=True)
class Scheme:
    method: str            # a..f or 's' for a custom spacing
    kind: str              # "equal" | "extinction"
    spacing: float = 0.0   # um (equal)
    stat: str = ""         # max | mean | min (extinction)

    def label(self) -> str:
        """The scheme in words (the report's ``scheme``; render's last line: "method " + this)."""
        if self.kind == "equal":
            return f"{self.method}: equal spacing {self.spacing:g} um"
        return f"{self.method}: random spacing, mean 1/extinction ({self.stat} over the bands)"


def scheme(method: str, spacing_um: float | None = None) -> Scheme:
    if spacing_um is not None:
        return Scheme(method=method if method in SPACING else "s", kind="equal", spacing=float(spacing_um))
    if method in SPACING:
        return Scheme(method=method, kind="equal", spacing=SPACING[method])
    return Scheme(method=method, kind="extinction", stat=EXTINCTION_STAT[method])


def layer_rates(vol: Volume, stat: str) -> np.ndarray:
    """Per-layer Poisson rate (um^-1): the layer's extinction statistic over bands."""
    mut = vol.mua + vol.mus
    f = {"max": np.max, "mean": np.mean, "min": np.min}[stat]
    return f(mut, axis=1).astype(np.float32)


@dataclass
class EyeData:
    camera: Camera
    scheme: Scheme
    nrays: int
    npoints: int
    npieces: int
    ray_start: object      # cl arrays
    pt_pos: object
    pt_dir: object
    pt_piece: object
    pieces: object
    ray_spec: np.ndarray   # host, per ray
    ray_hit: np.ndarray    # host, per ray
    pt_slab: object        # cl array float2: top and bottom of each point's layer (um)
    counts: np.ndarray     # host, points per ray
    layers: np.ndarray     # host, layer of each point
    depth: np.ndarray      # host, depth below z=0 of each point (um)
    geo: object = None     # cl array float4 x 2 per piece: (start, length), (direction, layer)
    zmin: float = 0.0      # lowest z any piece reaches (um)
    cone_deg: float = 0.0  # 99th percentile of the sample points' eye directions' angle from +z
    grazing: bool = False  # some piece runs closer to horizontal than 60 degrees from vertical

    def device_bytes(self) -> int:
        return (self.npoints * (16 + 16 + 4 + 8 + 8 + 4) + self.npieces * (8 + (32 if self.geo is not None else 0))
                + (self.nrays + 1) * 4)

    def per_layer(self, nl: int) -> np.ndarray:
        """Mean sample points per eye ray in each layer, over rays that hit the skin."""
        hits = max(int(self.ray_hit.sum()), 1)
        return np.bincount(self.layers.astype(int), minlength=nl)[:nl] / hits


def light_fields(e: np.ndarray, light: Light) -> None:
    e["light_kind"] = light.code
    if light.kind == "point":
        e["lx"], e["ly"], e["lz"] = light.position
    else:
        e["lx"], e["ly"], e["lz"] = -light.direction
        e["bx0"], e["by0"] = light.center - light.width / 2
        e["bx1"], e["by1"] = light.center + light.width / 2


def run(dev: Device, vol: Volume, vbuf: VolumeBuffers, cfg: dict,
        sch: Scheme | None = None, max_points: int = 1 << 16, geometry: bool | None = None,
        rs: RenderSettings | None = None, cam: Camera | None = None) -> EyeData:
    """Eye rays, sample points and path pieces; ``geometry`` (default: when the estimator is
    the beam) also writes each piece's start and direction.  ``rs`` and ``cam``: a render
    request's settings and camera (default: ``cfg``'s own).

    The kernel runs twice: it counts each ray's sample points and pieces, the counts become
    offsets by a prefix sum, and it runs again to store them there."""
    import pyopencl.cltypes as cltypes
    rc = rs or render_settings(cfg)
    sch = sch or scheme(rc.method, rc.spacing_um)
    cam = cam or from_config(cfg["camera"])
    rates = layer_rates(vol, sch.stat) if sch.kind == "extinction" else np.zeros(vol.nl, np.float32)
    eye = _EyeKernel(dev, vol, vbuf, eye_params(cfg, cam, sch, max_points, rc), rates, cam)
    if geometry is None:
        geometry = rc.estimator == "beam"
    counts, npoints, npieces = eye.count()
    if npoints >= 2**32 or npieces >= 2**32:
        raise DeviceError(f"{npoints} sample points / {npieces} path pieces exceed 32-bit indices; "
                          "raise render.threshold, use a sparser method or a lower resolution")
    check_alloc(dev, {"sample points": npoints * 56, "path pieces": npieces * 8,
                      "sample point slabs": npoints * 8, "piece geometry": npieces * 32 if geometry else 0})
    eye.offsets()
    out = eye.store(npoints, npieces, geometry)
    pos = out["pt_pos"].get()[:npoints] if npoints else np.zeros(0, cltypes.float4)
    dirs = out["pt_dir"].get()[:npoints] if npoints else np.zeros(0, cltypes.float4)
    zmin, grazing = _depth_reach(out["geo"], npieces, pos)
    return EyeData(camera=cam, scheme=sch, nrays=eye.nrays, npoints=npoints, npieces=npieces, geo=out["geo"],
                   zmin=zmin, grazing=grazing, cone_deg=_view_cone_deg(dirs),
                   ray_start=eye.npts, pt_pos=out["pt_pos"], pt_dir=out["pt_dir"], pt_piece=out["pt_piece"],
                   pieces=out["pieces"], ray_spec=out["ray_spec"].get(), ray_hit=out["ray_hit"].get(),
                   pt_slab=out["pt_slab"], counts=counts,
                   layers=np.asarray(dirs["w"], np.int32) if npoints else np.zeros(0, np.int32),
                   depth=-np.asarray(pos["z"], float) if npoints else np.zeros(0))


def eye_params(cfg: dict, cam: Camera, sch: Scheme, max_points: int,
               rs: RenderSettings | None = None) -> np.ndarray:
    """The kernel's ``EyeParams``: camera, sampling scheme, transmittance cut, voxels, light
    (``rs``: the run's render settings, default ``cfg``'s)."""
    rc = rs or render_settings(cfg)
    e = np.zeros(1, S.EYE_DTYPE)
    e["cam"], e["spp"] = cam.struct(), cam.spp
    e["scheme"] = 0 if sch.kind == "equal" else 1
    e["spacing"] = sch.spacing if sch.kind == "equal" else 1.0
    e["od_cut"] = -math.log(rc.threshold) if rc.threshold > 0 else 1e30
    e["merge"] = 1 if rc.merge == "voxel" else 0
    e["vox_dx"] = cfg["model"]["lateral_voxel_um"]
    e["vox_dz"] = cfg["model"]["voxel_um"]
    e["max_points"] = max_points
    e["max_len"] = 1e5
    e["alpha"] = rc.roughness
    e["seed_lo"], e["seed_hi"] = S.split_seed(rc.seed)
    e["jitter"] = 1 if cam.spp > 1 else 0
    light_fields(e, Light.from_config(cfg))
    return e


class _EyeKernel:
    """kernels/eye.cl's ``eye_pass`` with its constant arguments, and the per-ray counts
    (``npts``, ``npcs``: one entry per ray and one for the total) that become offsets."""

    def __init__(self, dev: Device, vol: Volume, vbuf: VolumeBuffers, e: np.ndarray, rates, cam: Camera):
        import pyopencl as cl
        import pyopencl.array as cla
        p = S.new_params()
        volume_params(p, vol)
        mf = cl.mem_flags
        ctx, self.q = dev.ctx, dev.queue
        ro = mf.READ_ONLY | mf.COPY_HOST_PTR
        self.common = dict(vbuf.named(cl.Buffer(ctx, ro, hostbuf=p)), E=cl.Buffer(ctx, ro, hostbuf=e),
                           rate=cl.Buffer(ctx, ro, hostbuf=rates))
        self.knl = kernels(dev, "eye.cl", ("eye_pass",), kernel_defines(vol, pt_fp64=surface_fp64(dev, vol)))["eye_pass"]
        self.smooth = vbuf.smooth
        self.dev = dev
        self.nrays = cam.width * cam.height * cam.spp
        self.npts = cla.zeros(self.q, self.nrays + 1, np.uint32)
        self.npcs = cla.zeros(self.q, self.nrays + 1, np.uint32)
        self.dummy4 = cl.Buffer(ctx, mf.READ_WRITE, 16)
        self.dummyf = cl.Buffer(ctx, mf.READ_WRITE, 16)

    def _launch(self, mode: EyeMode, outputs: dict) -> None:
        """One eye pass over every ray; the per-ray counts are both the counts it writes
        (EyeMode.COUNT) and the offsets it reads (the two store modes)."""
        self.knl(self.q, self.nrays, **self.common, write=int(mode), n_points=self.npts,
                 n_pieces=self.npcs, pt_start=self.npts, pc_start=self.npcs, **outputs,
                 smooth=self.smooth)

    def count(self) -> tuple[np.ndarray, int, int]:
        """Sample points and pieces per ray (EyeMode.COUNT): the points per ray and both totals."""
        d4, df = self.dummy4, self.dummyf
        self._launch(EyeMode.COUNT, dict(pt_pos=d4, pt_dir=d4, pt_piece=d4, pieces=d4, ray_spec=df,
                                         ray_hit=df, pt_slab=df, geo=d4))
        counts = self.npts.get()[:self.nrays].copy()
        npoints = int(counts.astype(np.int64).sum())
        npieces = int(self.npcs.get()[:self.nrays].astype(np.int64).sum())
        return counts, npoints, npieces

    def offsets(self) -> None:
        """In place: exclusive prefix sums of the counts, entry nrays = the total."""
        scan = exclusive_scan(self.dev)
        scan(self.npts)
        scan(self.npcs)

    def store(self, npoints: int, npieces: int, geometry: bool) -> dict:
        """Sample points and path pieces at their offsets (EyeMode.STORE; STORE_GEOMETRY with the
        pieces' geometry)."""
        import pyopencl as cl
        import pyopencl.array as cla
        import pyopencl.cltypes as cltypes
        q = self.q
        out = {"pt_pos": cla.empty(q, max(npoints, 1), cltypes.float4),
               "pt_dir": cla.empty(q, max(npoints, 1), cltypes.float4),
               "pt_piece": cla.empty(q, npoints + 1, np.uint32),
               "pieces": cla.empty(q, max(npieces, 1), cltypes.float2),
               "ray_spec": cla.empty(q, self.nrays, np.float32),
               "ray_hit": cla.empty(q, self.nrays, np.float32),
               "pt_slab": cla.empty(q, max(npoints, 1), cltypes.float2),
               "geo": cla.empty(q, 2 * max(npieces, 1), cltypes.float4) if geometry else None}
        self._launch(EyeMode.STORE_GEOMETRY if geometry else EyeMode.STORE,
                     {k: self.dummy4 if a is None else a for k, a in out.items()})
        cl.enqueue_copy(q, out["pt_piece"].data, np.array([npieces], np.uint32), dst_offset=4 * npoints)
        return out


def _depth_reach(geo, npieces: int, pos) -> tuple[float, bool]:
    """The lowest z the pieces reach (the sample points' where the pieces' geometry is not
    kept), and whether a piece runs closer to horizontal than 60 degrees from vertical."""
    if geo is not None and npieces:
        g = geo.get()[:2 * npieces]
        s, d = g[0::2], g[1::2]
        zend = np.minimum(s["z"], s["z"] + s["w"] * d["z"])
        return float(zend.min()), bool(np.any(np.abs(d["z"]) < 0.5))
    if len(pos):
        return float(pos["z"].min()), False
    return 0.0, False


def _view_cone_deg(dirs) -> float:
    """99th percentile of the sample points' eye directions' angle from +z."""
    return float(np.degrees(np.arccos(np.clip(np.percentile(dirs["z"], 1.0), -1, 1)))) if len(dirs) else 0.0
