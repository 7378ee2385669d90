/* grid.h -- the device photon lookup grid (uniform grid, cells x-fastest).
 *
 * Built every pass by clppm/integrators/hashgrid.py (kernels in hashgrid.cl): a uniform
 * grid over the box [lo, lo + (h*nx, h*ny, hz*nz)) with cells of edge h (µm) laterally and
 * depth hz (cubic, hz = h, unless the caller asks for flat cells: the beam estimator's discs
 * have no depth, and its eye-ray pieces are a few um deep against R of hundreds).
 * Cell (ix, iy, iz) has the linear index  c = ix + nx*(iy + ny*iz)  (x fastest):
 * a collision-free spatial hash, so a query visits every photon at most once
 * and needs no per-candidate cell check.  Points outside the box are clamped
 * to the boundary cells (lookups stay exact: the distance test decides).
 *
 * After a build the photons are stored cell-sorted, CSR style:
 *   cell_start[c] .. cell_start[c+1]-1   are the photons of cell c
 *   (cell_start has ncells+1 entries, cell_start[ncells] == number of photons)
 *   spos_w[j] = (x, y, z [µm], weight),  sdir_b[j] = (dx, dy, dz, band as float)
 * Inside a cell the order is arbitrary (counting sort with atomics): accumulate
 * order-independently (integer fixed point).
 *
 * Because cells are x-fastest, cells ix0..ix1 of one (iy, iz) row are one
 * contiguous photon range [cell_start[c(ix0,iy,iz)], cell_start[c(ix1,iy,iz)+1]).
 *
 * API
 * ---
 *   GridParams                     plain struct, 4-byte fields only, 48 bytes;
 *                                  mirrored by clppm.integrators.hashgrid.GRID_PARAMS_DTYPE.
 *                                  Pass it by value as a kernel argument (or read
 *                                  it from a __constant/__global buffer into a
 *                                  private copy: the functions take a VALUE).
 *   int  grid_axis(v, lo, inv_h, n)   cell coordinate of one axis, clamped to [0, n-1]
 *   int4 grid_coords(gp, p)           (ix, iy, iz, 0) of float3 p, clamped
 *   uint grid_cell_of(gp, p)          linear cell index of float3 p
 *   uint grid_cell_index(gp, ix, iy, iz)
 *   void grid_query_range(gp, x, R, &c0, &c1)
 *                                  inclusive cell-coordinate range (int4) of all
 *                                  cells that can hold a photon p with
 *                                  grid_within(p, x, R*R)
 *   int  grid_within(p, x, R2)     the distance test |p - x|^2 < R2 (float3),
 *                                  evaluated with FP_CONTRACT OFF so every kernel
 *                                  that uses it gets bit-identical results
 *
 *   uint2 grid_row_range(gp, cell_start, x0, x1, iy, iz)
 *                                  the contiguous range [begin, end) of sorted
 *                                  photon indices in cells x0..x1 of row (iy, iz).
 *       A query loops over the (iy, iz) rows of its cell range:
 *
 *         const float R2 = R * R;
 *         int4 c0, c1;
 *         grid_query_range(gp, x, R, &c0, &c1);
 *         for (int iz = c0.z; iz <= c1.z; ++iz)
 *             for (int iy = c0.y; iy <= c1.y; ++iy) {
 *                 const uint2 jr = grid_row_range(gp, cell_start, c0.x, c1.x, iy, iz);
 *                 for (uint j = jr.x; j < jr.y; ++j) {
 *                     const float4 p = spos_w[j];
 *                     if (grid_within(p.xyz, x, R2)) { ... }
 *                 }
 *             }
 *
 * Exactness: the query range is computed for R*(1 + GRID_R_PAD) (default 1e-4).
 * If grid_within(p, x, R*R) holds in float arithmetic, then |p.x - x.x| <
 * R*(1 + 1e-6) in exact arithmetic (each rounding is relative, u = 2^-24), so
 * fl(x.x - R') <= p.x by monotone rounding, and since grid_axis is monotone
 * (sub, mul, floor, clamp) the photon's cell lies inside the visited range.
 * A visit therefore finds exactly the photons a brute-force test finds.
 */
#ifndef CLPPM_GRID_H
#define CLPPM_GRID_H

#include "scalar.h"

typedef struct {
    float lo_x, lo_y, lo_z;   /* box corner (µm) */
    float h;                  /* cell edge (µm) */
    float inv_h;              /* 1/h as float32, the factor every kernel uses (x and y) */
    int nx, ny, nz;           /* cells per axis */
    uint ncells;              /* nx*ny*nz */
    float hz, inv_hz;         /* cell depth (um; = h unless the caller asks for flat cells) */
    uint nclass;              /* > 1: that many grids, photon class in the key's .w; 48 bytes in all */
} GridParams;

#ifndef GRID_R_PAD
#define GRID_R_PAD 1.0e-4f
#endif

/* cell coordinate along one axis, clamped; NaN goes to cell 0 */
inline int grid_axis(const float v, const float lo, const float inv_h, const int n)
{
#pragma OPENCL FP_CONTRACT OFF
    float t = floor1((v - lo) * inv_h);
    t = fmin1(fmax1(t, 0.0f), (float)(n - 1));
    return (int)t;
}

inline int4 grid_coords(const GridParams gp, const float3 p)
{
    return (int4)(grid_axis(p.x, gp.lo_x, gp.inv_h, gp.nx),
                  grid_axis(p.y, gp.lo_y, gp.inv_h, gp.ny),
                  grid_axis(p.z, gp.lo_z, gp.inv_hz, gp.nz), 0);
}

inline uint grid_cell_index(const GridParams gp, const int ix, const int iy, const int iz)
{
    return (uint)ix + (uint)gp.nx * ((uint)iy + (uint)gp.ny * (uint)iz);
}

inline uint grid_cell_of(const GridParams gp, const float3 p)
{
    const int4 c = grid_coords(gp, p);
    return grid_cell_index(gp, c.x, c.y, c.z);
}

/* nx*ny*nz: the cells of one class */
inline uint grid_cells_xyz(const GridParams gp)
{
    return (uint)gp.nx * (uint)gp.ny * (uint)gp.nz;
}

/* The sort key of a photon whose key position is p: its cell, and with classes (nclass > 1)
 * its class p.w (a small integer as float) times the cells of a class, so that each class
 * is a grid of its own in one cell_start. */
inline uint grid_key_of(const GridParams gp, const float4 p)
{
    const uint c = grid_cell_of(gp, p.xyz);
    return gp.nclass > 1u ? c + grid_cells_xyz(gp) * min1((uint)p.w, gp.nclass - 1u) : c;
}

inline void grid_query_range(const GridParams gp, const float3 x, const float R,
                             int4 *c0, int4 *c1)
{
#pragma OPENCL FP_CONTRACT OFF
    const float Rp = R * (1.0f + GRID_R_PAD);
    *c0 = grid_coords(gp, x - Rp);
    *c1 = grid_coords(gp, x + Rp);
}

inline int grid_within(const float3 p, const float3 x, const float R2)
{
#pragma OPENCL FP_CONTRACT OFF
    const float dx = p.x - x.x, dy = p.y - x.y, dz = p.z - x.z;
    const float d2 = dx * dx + dy * dy + dz * dz;
    return d2 < R2;
}

inline uint2 grid_row_range(const GridParams gp, __global const uint* cell_start, const int x0,
                            const int x1, const int iy, const int iz)
{
    const uint row = grid_cell_index(gp, x0, iy, iz);
    return (uint2)(cell_start[row], cell_start[row + (uint)(x1 - x0) + 1u]);
}

#endif /* CLPPM_GRID_H */
