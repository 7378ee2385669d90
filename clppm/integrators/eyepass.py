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
from ..scene.scene import Scene
from ..scene.camera import Camera
from ..scene.light import Light
from ..compute.device import Device, DeviceError, check_alloc, kernel_defines, surface_fp64
from ..compute.constants import EyeMode
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
    """Per-material Poisson rate (um^-1): the extinction statistic over bands of each layer,
    then of each inclusion (an eye ray inside one places its points at the inclusion's rate)."""
    mua, mus, _ = vol.material_optics()
    mut = mua + mus
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
    piece_extent: float | None = None   # median depth extent of the pieces (um; None: no geometry)
    pix0: int = 0          # the pixels these points belong to: [pix0, pix1) (a tile, or the image)
    pix1: int | None = None

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


#: tiles of sample points start at multiples of this many pixels: a launch over a tile then
#: covers whole work groups (local sizes up to 64), so its rounded-up range never reaches into
#: the next tile's rays (the eye kernel guards only the image's end)
TILE_ALIGN = 64


def run(dev: Device, vol: Volume, vbuf: VolumeBuffers, cfg: dict,
        sch: Scheme | None = None, max_points: int = 1 << 16, geometry: bool | None = None) -> EyeData:
    """Eye rays, sample points and path pieces of the whole image of a config rendered with its
    own values (on the model ``vol`` built from it): the tools' and tests' way in; a render
    counts its :class:`EyeTiles` of its :class:`~clppm.scene.scene.Scene`.  ``geometry``
    (default: when the estimator is the beam) also writes each piece's start and direction."""
    tiles = EyeTiles.count(dev, vbuf, Scene.of_config(cfg, volume=vol), sch, max_points, geometry)
    tiles.plan(None)
    return tiles.summarise()[0]


@dataclass
class EyeTiles:
    """The eye pass in tiles of pixels: each ray's point and piece counts (host) from one
    counting run, and a tile's sample points stored on demand (:meth:`load`).

    The kernel runs twice: it counts each ray's sample points and pieces (once, every ray),
    a tile's counts become offsets by a prefix sum, and it runs again over the tile's rays
    (launched at their global ids, so each ray draws the same random numbers as untiled) to
    store them there.  The per-ray start array is one array of the whole image's rays; a load
    writes its tile's part, so a tile's points are indexed from 0 (``ray_start`` minus
    nothing)."""

    kernel: "_EyeKernel"
    camera: Camera
    scheme: Scheme
    geometry: bool
    counts: np.ndarray               # points per ray
    pcounts: np.ndarray              # pieces per ray
    tiles: list = None               # (first pixel, end pixel) of each tile
    ray_host: tuple = (None, None)   # ray_spec, ray_hit on the host (after summarise)

    @classmethod
    def count(cls, dev: Device, vbuf: VolumeBuffers, scene: Scene, sch: Scheme | None = None,
              max_points: int = 1 << 16, geometry: bool | None = None) -> "EyeTiles":
        """Every ray's sample points and pieces counted (``sch``: default the scene's method)."""
        vol, rc, cam = scene.volume, scene.settings, scene.camera
        sch = sch or scheme(rc.method, rc.spacing_um)
        rates = layer_rates(vol, sch.stat) if sch.kind == "extinction" else np.zeros(vol.nmat, np.float32)
        eye = _EyeKernel(dev, vol, vbuf, eye_params(scene, sch, max_points), rates, cam)
        counts, pcounts = eye.count()
        npoints, npieces = int(counts.sum(dtype=np.int64)), int(pcounts.sum(dtype=np.int64))
        if npoints >= 2**32 or npieces >= 2**32:
            raise DeviceError(f"{npoints} sample points / {npieces} path pieces exceed 32-bit indices; "
                              "raise render.threshold, use a sparser method or a lower resolution")
        return cls(kernel=eye, camera=cam, scheme=sch, counts=counts, pcounts=pcounts,
                   geometry=rc.estimator == "beam" if geometry is None else bool(geometry))

    @property
    def npix(self) -> int:
        return self.camera.width * self.camera.height

    def pixel_sums(self, per_ray: np.ndarray) -> np.ndarray:
        return per_ray.reshape(self.npix, self.camera.spp).sum(1, dtype=np.int64)

    def plan(self, max_points: int | None) -> list:
        """Contiguous pixel ranges of at most ``max_points`` sample points each (None: one tile),
        cut at multiples of TILE_ALIGN pixels; a block of TILE_ALIGN pixels is never split."""
        if max_points is None:
            self.tiles = [(0, self.npix)]
            return self.tiles
        per_pix = self.pixel_sums(self.counts)
        edges = np.arange(0, self.npix, TILE_ALIGN)
        blocks = np.add.reduceat(per_pix, edges) if self.npix else np.zeros(0, np.int64)
        tiles, p0, n = [], 0, 0
        for b, c in zip(edges, blocks):
            if n and n + c > max_points:
                tiles.append((p0, int(b)))
                p0, n = int(b), 0
            n += int(c)
        tiles.append((p0, self.npix))
        self.tiles = tiles
        return tiles

    def use(self, plan: list) -> list:
        """Tiles given as pixel ranges (another device's :meth:`plan` of the same image): they
        must cover the pixels in order, each once."""
        tiles = [(int(a), int(b)) for a, b in plan]
        if (not tiles or tiles[0][0] != 0 or tiles[-1][1] != self.npix
                or any(a >= b for a, b in tiles) or any(x[1] != y[0] for x, y in zip(tiles, tiles[1:]))):
            raise ValueError(f"tiles {tiles[:3]}... do not cover the {self.npix} pixels in order")
        self.tiles = tiles
        return tiles

    def sizes(self, t: int) -> tuple[int, int]:
        """Sample points and pieces of tile ``t``."""
        r0, r1 = (p * self.camera.spp for p in self.tiles[t])
        return int(self.counts[r0:r1].sum(dtype=np.int64)), int(self.pcounts[r0:r1].sum(dtype=np.int64))

    def max_sizes(self) -> tuple[int, int]:
        s = [self.sizes(t) for t in range(len(self.tiles))]
        return max(a for a, _ in s), max(b for _, b in s)

    def point_range(self, t: int) -> tuple[int, int]:
        """Tile ``t``'s sample points' indices in the whole image's point order."""
        r0, r1 = (p * self.camera.spp for p in self.tiles[t])
        a = int(self.counts[:r0].sum(dtype=np.int64))
        return a, a + int(self.counts[r0:r1].sum(dtype=np.int64))

    def load(self, t: int, reuse: EyeData | None = None) -> EyeData:
        """Tile ``t``'s sample points and pieces on the device (``reuse``: a loaded tile whose
        buffers are large enough are written over).  Global fields (zmin, cone, ...) are left
        at their defaults: :meth:`summarise` sets them."""
        p0, p1 = self.tiles[t]
        spp = self.camera.spp
        r0, r1 = p0 * spp, p1 * spp
        npoints, npieces = self.sizes(t)
        check_alloc(self.kernel.dev, {"sample points": npoints * 56, "path pieces": npieces * 8,
                                      "sample point slabs": npoints * 8,
                                      "piece geometry": npieces * 32 if self.geometry else 0})
        self.kernel.offsets(r0, self.counts[r0:r1], self.pcounts[r0:r1])
        out = self.kernel.store(npoints, npieces, self.geometry, r0, r1 - r0, reuse)
        return EyeData(camera=self.camera, scheme=self.scheme, nrays=self.kernel.nrays, npoints=npoints,
                       npieces=npieces, geo=out["geo"], ray_start=self.kernel.npts, pt_pos=out["pt_pos"],
                       pt_dir=out["pt_dir"], pt_piece=out["pt_piece"], pieces=out["pieces"],
                       ray_spec=self.ray_host[0], ray_hit=self.ray_host[1], pt_slab=out["pt_slab"],
                       counts=self.counts, layers=np.zeros(0, np.int8), depth=np.zeros(0), pix0=p0, pix1=p1)

    def summarise(self, on_tile=None) -> tuple[EyeData, EyeData]:
        """Every tile loaded once, for what the whole image's points decide (the deepest piece,
        the view cone, grazing pieces, the pieces' median depth extent, points per layer).
        Returns the whole image's EyeData (buffers: the last tile's; with one tile, all of it)
        and the last tile loaded.  ``on_tile(t, eye)`` after each tile is loaded."""
        import pyopencl.cltypes as cltypes
        zs, layers, depth, exts, zmin, grazing, eye = [], [], [], [], None, False, None
        for t in range(len(self.tiles)):
            eye = self.load(t, eye)
            n = eye.npoints
            pos = eye.pt_pos.get()[:n] if n else np.zeros(0, cltypes.float4)
            dirs = eye.pt_dir.get()[:n] if n else np.zeros(0, cltypes.float4)
            z, g, ext = _depth_reach(eye.geo, eye.npieces, pos)
            if z is not None:
                zmin = z if zmin is None else min(zmin, z)
            grazing = grazing or g
            exts.append(ext)
            zs.append(np.asarray(dirs["z"], np.float32))
            layers.append(np.asarray(dirs["w"], np.int8))
            if len(self.tiles) == 1:
                depth.append(-np.asarray(pos["z"], float))
            if on_tile is not None:
                on_tile(t, eye)
        dz = np.concatenate(zs)
        nr = self.kernel.nrays
        self.ray_host = (self.kernel.ray_spec.get()[:nr], self.kernel.ray_hit.get()[:nr])
        eye.ray_spec, eye.ray_hit = self.ray_host
        whole = EyeData(**{**eye.__dict__, "npoints": int(self.counts.sum(dtype=np.int64)),
                           "npieces": int(self.pcounts.sum(dtype=np.int64)), "pix0": 0, "pix1": self.npix,
                           "layers": np.concatenate(layers).astype(np.int32),
                           "depth": np.concatenate(depth) if depth else np.zeros(0),
                           "zmin": 0.0 if zmin is None else zmin, "grazing": grazing,
                           "cone_deg": _view_cone_deg(dz), "piece_extent": _median_extent(exts)})
        if len(self.tiles) == 1:
            eye = whole
        else:
            eye.zmin, eye.grazing, eye.cone_deg, eye.piece_extent = (whole.zmin, whole.grazing, whole.cone_deg,
                                                                     whole.piece_extent)
        return whole, eye


def eye_params(scene: Scene, sch: Scheme, max_points: int) -> np.ndarray:
    """The kernel's ``EyeParams``: camera, sampling scheme, transmittance cut, voxels, light."""
    rc, cam, model = scene.settings, scene.camera, scene.config["model"]
    e = np.zeros(1, S.EYE_DTYPE)
    e["cam"], e["spp"] = cam.struct(), cam.spp
    e["scheme"] = 0 if sch.kind == "equal" else 1
    e["spacing"] = sch.spacing if sch.kind == "equal" else 1.0
    e["od_cut"] = -math.log(rc.threshold) if rc.threshold > 0 else 1e30
    e["merge"] = 1 if rc.merge == "voxel" else 0
    e["vox_dx"] = model["lateral_voxel_um"]
    e["vox_dz"] = model["voxel_um"]
    e["max_points"] = max_points
    e["max_len"] = 1e5
    e["alpha"] = rc.roughness
    e["seed_lo"], e["seed_hi"] = S.split_seed(rc.seed)
    e["jitter"] = 1 if cam.spp > 1 else 0
    light_fields(e, scene.light)
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
        self.nrays = cam.width * cam.height * cam.spp
        self.npts = cla.zeros(self.q, self.nrays + 1, np.uint32)
        self.npcs = cla.zeros(self.q, self.nrays + 1, np.uint32)
        self.ray_spec = cla.zeros(self.q, max(self.nrays, 1), np.float32)   # per ray, written by stores
        self.ray_hit = cla.zeros(self.q, max(self.nrays, 1), np.float32)
        self.dev = dev
        self.dummy4 = cl.Buffer(ctx, mf.READ_WRITE, 16)
        self.dummyf = cl.Buffer(ctx, mf.READ_WRITE, 16)

    def _launch(self, mode: EyeMode, outputs: dict) -> None:
        """One eye pass over every ray; the per-ray counts are both the counts it writes
        (EyeMode.COUNT) and the offsets it reads (the two store modes)."""
        self.knl(self.q, self.nrays, **self.common, write=int(mode), n_points=self.npts,
                 n_pieces=self.npcs, pt_start=self.npts, pc_start=self.npcs, **outputs,
                 smooth=self.smooth)

    def count(self) -> tuple[np.ndarray, np.ndarray]:
        """Sample points and pieces per ray (EyeMode.COUNT), on the host."""
        d4, df = self.dummy4, self.dummyf
        self._launch(EyeMode.COUNT, dict(pt_pos=d4, pt_dir=d4, pt_piece=d4, pieces=d4, ray_spec=df,
                                         ray_hit=df, pt_slab=df, geo=d4))
        return self.npts.get()[:self.nrays].copy(), self.npcs.get()[:self.nrays].copy()

    def offsets(self, r0: int, counts: np.ndarray, pcounts: np.ndarray) -> None:
        """Entries r0 .. r0 + len(counts) of the start arrays: the exclusive prefix sums of a
        tile's counts, the entry after its last ray the tile's total."""
        import pyopencl as cl
        for arr, c in ((self.npts, counts), (self.npcs, pcounts)):
            st = np.zeros(len(c) + 1, np.uint32)
            np.cumsum(c, dtype=np.uint32, out=st[1:])
            cl.enqueue_copy(self.q, arr.data, st, dst_offset=4 * r0)

    def store(self, npoints: int, npieces: int, geometry: bool, r0: int = 0, nrays: int | None = None,
              reuse=None) -> dict:
        """Sample points and path pieces of rays r0 .. r0 + nrays at their offsets
        (EyeMode.STORE; STORE_GEOMETRY with the pieces' geometry), into ``reuse``'s buffers
        where they are large enough."""
        import pyopencl as cl
        import pyopencl.array as cla
        import pyopencl.cltypes as cltypes
        q = self.q

        def buf(name, n, dtype):
            old = getattr(reuse, name, None) if reuse is not None else None
            return old if old is not None and old.size >= n else cla.empty(q, n, dtype)
        if reuse is not None and reuse.pt_piece.size < npoints + 1:
            reuse = None                 # the tile's arrays grow: let the old ones go first
        out = {"pt_pos": buf("pt_pos", max(npoints, 1), cltypes.float4),
               "pt_dir": buf("pt_dir", max(npoints, 1), cltypes.float4),
               "pt_piece": buf("pt_piece", npoints + 1, np.uint32),
               "pieces": buf("pieces", max(npieces, 1), cltypes.float2),
               "pt_slab": buf("pt_slab", max(npoints, 1), cltypes.float2),
               "geo": buf("geo", 2 * max(npieces, 1), cltypes.float4) if geometry else None}
        args = {k: self.dummy4 if a is None else a for k, a in out.items()}
        n = self.nrays if nrays is None else nrays
        if n:
            self.knl(self.q, n, start=r0, **self.common, write=int(EyeMode.STORE_GEOMETRY if geometry
                                                                    else EyeMode.STORE),
                     n_points=self.npts, n_pieces=self.npcs, pt_start=self.npts, pc_start=self.npcs,
                     ray_spec=self.ray_spec, ray_hit=self.ray_hit, **args, smooth=self.smooth)
        cl.enqueue_copy(q, out["pt_piece"].data, np.array([npieces], np.uint32), dst_offset=4 * npoints)
        return out


def _depth_reach(geo, npieces: int, pos) -> tuple[float | None, bool, np.ndarray]:
    """The lowest z the pieces reach (the sample points' where the pieces' geometry is not
    kept; None: no points), whether a piece runs closer to horizontal than 60 degrees from
    vertical, and the pieces' depth extents (empty without their geometry)."""
    if geo is not None and npieces:
        g = geo.get()[:2 * npieces]
        s, d = g[0::2], g[1::2]
        zend = np.minimum(s["z"], s["z"] + s["w"] * d["z"])
        return float(zend.min()), bool(np.any(np.abs(d["z"]) < 0.5)), np.abs(s["w"] * d["z"])
    if len(pos):
        return float(pos["z"].min()), False, np.zeros(0, np.float32)
    return None, False, np.zeros(0, np.float32)


def _median_extent(exts: list) -> float | None:
    """The beam's grid cell depth input: the median depth extent of every piece."""
    e = np.concatenate(exts) if exts else np.zeros(0, np.float32)
    return float(np.median(e)) if len(e) else None


def _view_cone_deg(dz: np.ndarray) -> float:
    """99th percentile of the sample points' eye directions' angle from +z (``dz``: their z)."""
    return float(np.degrees(np.arccos(np.clip(np.percentile(dz, 1.0), -1, 1)))) if len(dz) else 0.0
