"""The density estimate of a PPM pass, as a small strategy object per pipeline.

A :class:`clppm.integrators.ppm.Pipeline` holds one estimator, chosen by ``render.estimator``:

* :class:`SphereGather` (``sphere``, and its ``layer`` and ``clip`` variants): each sample
  point gathers the photons within its radius (kernels/gather.cl ``gather``), the paper's
  estimate (Kamatani & Kawai; Hachisuka et al. 2008).
* :class:`clppm.integrators.beam.BeamGather` (``beam``): each eye-ray piece gathers the photons
  within a disc around it, in one of two layouts (gather or scatter).

An estimator has two stages of a pass: :meth:`grid` (the photon grid it searches, and what it
files with it) and :meth:`estimate` (the gather, which adds the pass's radiance into the
accumulators and, with the per-point radius, updates the points' R and N).  ``dim`` is the
dimension of its kernel: the radius update's exponent.
"""
from __future__ import annotations

from dataclasses import dataclass

from ..compute.kernelcall import Kernel


@dataclass
class PassGrid:
    """A pass's photon grid (clppm.integrators.hashgrid.Grid) and what the estimator filed with it
    (the beam: each sorted photon's layer slab)."""

    grid: object
    slabs: object = None


class SphereGather:
    """The sample points' sphere gather: a work item per pixel walks its points."""

    dim = 3

    def __init__(self, pipe):
        self.pipe = pipe
        self.kernel = Kernel(pipe.prg, "gather")

    def grid(self, n: int, radii_median: float, rmax: float):
        return PassGrid(self.pipe.grid(n, radii_median, rmax))

    def estimate(self, pg, extra, st, acc, alpha: float, scale: float, pass_scale: float) -> None:
        sc, grid = self.pipe, pg.grid
        e = sc.eye
        p0, p1 = sc.pixels
        self.kernel(
            sc.dev.queue, p1 - p0, start=p0, gp=grid.params, cell_start=grid.cell_start, spos_w=grid.spos_w,
            sdir_b=grid.sdir_b, sextra=extra, hgtab=sc.hgtab, optics=sc.vbuf.optics,
            ray_start=e.ray_start, pt_pos=e.pt_pos, pt_dir=e.pt_dir, pt_piece=e.pt_piece,
            pieces=e.pieces, pt_slab=e.pt_slab, layer_z=sc.layer_z, pt_R=st.R, pt_N=st.N,
            pt_M=st.M, pix_acc=acc.pix, pix_pairs=acc.pairs, npix=p1, acc_base=acc.base, spp=e.camera.spp,
            alpha=alpha, global_radius=int(sc.global_radius), radius_scale=scale,
            pass_scale=pass_scale)
