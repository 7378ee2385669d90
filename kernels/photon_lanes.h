/* The photon pass in explicit SIMD lanes (LANES = 4, 8 or 16; photonpass.py photon_lanes picks it
 * per device: CPUs, whose OpenCL compilers run photon_pass one work item per lane of nothing).
 *
 * Neither CPU runtime vectorises photon_pass across work items: its loop body has a dozen kinds
 * of event, and a SIMD version of it executes all of them every iteration (Intel's, forced, ran
 * 1.8-5x slower).  But one kind dominates: a collision in a region bounded by planes, a layer's
 * core or, on the smooth walk, a tile's box clear of both surfaces (the forearm's photons: 236 of
 * 260 events are collisions).  Here one work item carries LANES photons in structure-of-arrays
 * state, and
 *
 *   - the fast phase runs that one kind in vector arithmetic over the lanes (float16 on
 *     AVX-512): the free path against the region's planes, absorption, the storage bound,
 *     Henyey-Greenstein scattering, the bands' phase-function ratios, roulette, the next optical
 *     depth, and Philox for every lane at once (blocks computed one iteration ahead).  A lane
 *     whose next event is anything else drops out of the fast phase; the phase ends when fewer
 *     than FAST_MIN lanes remain;
 *   - the slow phase gives each dropped lane photon_event (photon.cl, scalar, the same code as
 *     photon_pass) until it is back in such a region, and a lane whose photon ended the next
 *     photon of the launch (photon_start).
 *
 * A photon's path draws the same random numbers in the same order as in photon_pass (a lane's
 * Philox block is consumed one uniform at a time, as rng_u01 does), the arithmetic is the same
 * formulas, and a fast collision is one photon_event would make (a flight that stays in the
 * region crosses nothing), so both kernels give the same tallies and photon maps bit for bit
 * (tests/test_photon_lanes.py, Intel's runtime and PoCL). */
#ifndef CLPPM_PHOTON_LANES_H
#define CLPPM_PHOTON_LANES_H

#define VJOIN_(a, n) a##n
#define VJOIN(a, n) VJOIN_(a, n)
typedef VJOIN(float, LANES) vf;
typedef VJOIN(int, LANES) vi;
typedef VJOIN(uint, LANES) vu;
typedef VJOIN(long, LANES) vl;
#define V_F(x) VJOIN(convert_float, LANES)(x)
#define V_L(x) VJOIN(convert_long, LANES)(x)
#define V_I(x) VJOIN(convert_int, LANES)(x)
#define V_U(x) VJOIN(convert_uint, LANES)(x)
#define V_LRTE(x) VJOIN(VJOIN(convert_long, LANES), _rte)(x)
#define AS_F(x) VJOIN(as_float, LANES)(x)
#define AS_U(x) VJOIN(as_uint, LANES)(x)
#define AS_I(x) VJOIN(as_int, LANES)(x)

/* any, select, fmin, fmax, clamp, fabs and counting of lane masks (-1 true) in plain vector
 * operations: PoCL calls its library for each of these builtins on vectors (a call per use, the
 * vectors through memory); the results are the builtins' for the values met here (no NaN). */
#if LANES == 16
#define HALVES(v) ((v).lo | (v).hi)
#define ANY_(v) ({ const VJOIN(int, 8) a8 = HALVES(v); const int4 a4 = HALVES(a8); const int2 a2 = HALVES(a4); (a2.x | a2.y) < 0; })
#define SUM_(v) ({ const VJOIN(int, 8) a8 = (v).lo + (v).hi; const int4 a4 = a8.lo + a8.hi; const int2 a2 = a4.lo + a4.hi; a2.x + a2.y; })
#elif LANES == 8
#define ANY_(v) ({ const int4 a4 = (v).lo | (v).hi; const int2 a2 = a4.lo | a4.hi; (a2.x | a2.y) < 0; })
#define SUM_(v) ({ const int4 a4 = (v).lo + (v).hi; const int2 a2 = a4.lo + a4.hi; a2.x + a2.y; })
#elif LANES == 4
#define ANY_(v) ({ const int2 a2 = (v).lo | (v).hi; (a2.x | a2.y) < 0; })
#define SUM_(v) ({ const int2 a2 = (v).lo + (v).hi; a2.x + a2.y; })
#else
#error "LANES must be 4, 8 or 16"
#endif
HOT int any_v(vi m) { return ANY_(m); }
HOT int count_v(vi m) { return -SUM_(m); }
HOT vf sel_f(vf a, vf b, vi m) { return AS_F((AS_I(a) & ~m) | (AS_I(b) & m)); }
HOT vi sel_i(vi a, vi b, vi m) { return (a & ~m) | (b & m); }
HOT vu sel_u(vu a, vu b, vi m) { return (a & ~AS_U(m)) | (b & AS_U(m)); }
HOT vl sel_l(vl a, vl b, vl m) { return (a & ~m) | (b & m); }
HOT vf min_v(vf a, vf b) { return sel_f(a, b, b < a); }
HOT vf max_v(vf a, vf b) { return sel_f(a, b, b > a); }
HOT vf abs_v(vf a) { return AS_F(AS_I(a) & (vi)0x7fffffff); }
HOT vi clampi_v(vi a, int hi) { return sel_i(sel_i(a, (vi)hi, a > (vi)hi), (vi)0, a < (vi)0); }

/* a lane array: as one vector (.v) or lane by lane (.s[i]) */
typedef union { vf v; float s[LANES]; } LF;
typedef union { vi v; int s[LANES]; } LI;
typedef union { vu v; uint s[LANES]; } LU;
typedef union { vl v; long s[LANES]; } LL;

/* the fast phase ends when fewer lanes than this still collide in a core */
#ifndef FAST_MIN
#define FAST_MIN (LANES / 2)
#endif

/* Every lane's state, structure of arrays.  A lane's scalar state (Track, Spectral, Rng) is
 * copied out for the slow phase and back after it; its Fates live here per lane (the fast phase
 * adds roulette and absorption into gain, loss and acur, folded in before the slow phase). */
typedef struct {
    LL W;
    LL gain, loss, acur;                   /* the fast phase's fates, acur in layer L */
    LF px, py, pz, ux, uy, uz;
    LI L, ix, iy;
    LI b, live, on, events, planes, still;
    LI fast;                     /* -1: in a layer's core, the fast phase's (0: not) */
    LF tau;
    LU rc[2][4], rk[2][2], rr[2][4];   /* [0] rng, [1] srng: Rng */
    LI ru[2];
    LU rn[4];                    /* rng's next block, computed ahead where rnv (its counter: rc - 1) */
    LI rnv;
#if HERO_C > 1
    LF lr[HERO_C], hq[HERO_C], la[HERO_C];
    LF scale, amax, pl;
    LI pL, pn;
    LF A[HERO_C], B[HERO_C];    /* the layer's TAB_HG of each band carried */
    LF malb;                           /* the layer's TAB_MAXALB of the hero class */
#endif

    /* the layer's constants: optics (mua/mut, g, 1/(2g), mut), the core's planes, store_imp's */
    LF opx, opg, opi, opm, zt, zb;
    /* on the smooth walk outside the core (tmode -1): the box of the photon's tile between the
     * lowest point of its layer's top and the highest of its bottom over the tile */
    LF bzt, bzb, bxl, bxh, byl, byh;
    LI tmode;
    LF smx, smy, szx, szy;
    Fates f[LANES];
} Lanes;

/* ---------------------------------------------------------------- one lane, scalar */
HOT void lane_rng_get(const Lanes* S, int w, int i, Rng* g) {
    for (int k = 0; k < 4; ++k) { g->c.v[k] = S->rc[w][k].s[i]; g->r.v[k] = S->rr[w][k].s[i]; }
    g->k.v[0] = S->rk[w][0].s[i]; g->k.v[1] = S->rk[w][1].s[i];
    g->used = S->ru[w].s[i];
    if (w == 0 && S->rnv.s[i]) g->c.v[1] -= 1u;      /* the block computed ahead is dropped */
}

HOT void lane_rng_put(Lanes* S, int w, int i, const Rng* g) {
    for (int k = 0; k < 4; ++k) { S->rc[w][k].s[i] = g->c.v[k]; S->rr[w][k].s[i] = g->r.v[k]; }
    S->rk[w][0].s[i] = g->k.v[0]; S->rk[w][1].s[i] = g->k.v[1];
    S->ru[w].s[i] = g->used;
    if (w == 0) S->rnv.s[i] = 0;
}

HOT void lane_track_get(const Lanes* S, int i, Track* t) {
    t->pos = (float3)(S->px.s[i], S->py.s[i], S->pz.s[i]);
    t->dir = (float3)(S->ux.s[i], S->uy.s[i], S->uz.s[i]);
    t->L = S->L.s[i]; t->ix = S->ix.s[i]; t->iy = S->iy.s[i];
}

HOT void lane_track_put(Lanes* S, int i, const Track* t) {
    S->px.s[i] = t->pos.x; S->py.s[i] = t->pos.y; S->pz.s[i] = t->pos.z;
    S->ux.s[i] = t->dir.x; S->uy.s[i] = t->dir.y; S->uz.s[i] = t->dir.z;
    S->L.s[i] = t->L; S->ix.s[i] = t->ix; S->iy.s[i] = t->iy;
}

HOT void lane_sw_get(const Lanes* S, int i, Spectral* w) {
    w->h = S->b.s[i];
#if HERO_C > 1
    for (int j = 0; j < HERO_C; ++j) { w->lr[j] = S->lr[j].s[i]; w->hq[j] = S->hq[j].s[i]; w->la[j] = S->la[j].s[i]; }
    w->scale = S->scale.s[i]; w->amax = S->amax.s[i]; w->pl = S->pl.s[i]; w->pL = S->pL.s[i]; w->pn = S->pn.s[i];
#endif
}

HOT void lane_sw_put(Lanes* S, int i, const Spectral* w) {
#if HERO_C > 1
    for (int j = 0; j < HERO_C; ++j) { S->lr[j].s[i] = w->lr[j]; S->hq[j].s[i] = w->hq[j]; S->la[j].s[i] = w->la[j]; }
    S->scale.s[i] = w->scale; S->amax.s[i] = w->amax; S->pl.s[i] = w->pl; S->pL.s[i] = w->pL; S->pn.s[i] = w->pn;
#endif
}

/* the fast phase's fates of lane i into its Fates */
HOT void lane_fold(Lanes* S, int i) {
    Fates* f = &S->f[i];
    f->gain += S->gain.s[i]; f->loss += S->loss.s[i];
    if (S->acur.s[i]) f->absorbed[S->L.s[i]] += S->acur.s[i];
    S->gain.s[i] = 0; S->loss.s[i] = 0; S->acur.s[i] = 0;
}

/* Whether lane i's photon is in its layer's core with optics the fast phase handles (it decides
 * each event itself whether the next one is a collision there), and if so the layer's constants.
 * Brings the bands' pending part to the layer (sw_flight would on its next flight). */
HOT int lane_enter_fast(Lanes* S, int i, const Track* t, Spectral* sw, VOLUME_ARGS,
                        __global const float* logmu, __global const float2* store_imp) {
#if NINC > 0
    return 0;                           /* inclusions: photon_pass (photonpass.py photon_lanes) */
#endif
    const int L = t->L;
    if (L < 0 || L >= NL) return 0;
#ifdef MAPS
    if (map_first(optics, L) >= 0) return 0;          /* a mapped layer: collide_mapped's */
#endif
    const float4 op = optics[L * NB + S->b.s[i]];
    if (!(op.x < 1.0f) || !(op.w > 0.0f)) return 0;
    int tmode = 0;
#ifdef FLAT
    const float zt = IF_Z(L);
    const float zb = (L + 1 <= NL && IF_Z(L + 1) > -BIG) ? IF_Z(L + 1) : -BIG;
#else
    const float zt = IF_ZMIN(L), zb = IF_ZMAX(L + 1);
    const float z = t->pos.z, dz = t->dir.z;
    if (!((dz > 0.0f ? z < zt : z <= zt) && (dz < 0.0f ? z > zb : z >= zb))) {
#ifdef SMOOTH_SURFACE
        /* tile mode: within its tile, between the lowest point of its layer's top and the
         * highest of its bottom over the tile, a flight that stays in that box crosses no surface
         * (photon_smooth_boundary would find none before leaving it), so a collision in it is the
         * scalar walk's collision.  (A box of 3 x 3 tiles with their joint bounds left the share
         * of events in the fast phase at 0.82 on the forearm: the flights it keeps the thin wavy
         * layers lose.) */
        const int tx = t->ix / SMOOTH_CELL, ty = t->iy / SMOOTH_CELL;
        const float top = IF_VAR(L) >= 0 ? smooth_tile(P, iface, heights, L, tx, ty).x : IF_Z(L);
        const float bot = L + 1 >= NL ? IF_Z(L + 1)
                        : (IF_VAR(L + 1) >= 0 ? smooth_tile(P, iface, heights, L + 1, tx, ty).y : IF_Z(L + 1));
        if (!((dz > 0.0f ? z < top : z <= top) && (dz < 0.0f ? z > bot : z >= bot))) return 0;
        const float xl = P->x0 + P->dx * (float)(tx * SMOOTH_CELL);
        const float xh = fmin(P->x0 + P->dx * (float)((tx + 1) * SMOOTH_CELL), P->x0 + P->xw);
        const float yl = P->y0 + P->dy * (float)(ty * SMOOTH_CELL);
        const float yh = fmin(P->y0 + P->dy * (float)((ty + 1) * SMOOTH_CELL), P->y0 + P->yw);
        const float x = t->pos.x, y = t->pos.y;
        if (!(x >= xl && x <= xh && y >= yl && y <= yh)) return 0;
        S->bzt.s[i] = top; S->bzb.s[i] = bot; S->bxl.s[i] = xl; S->bxh.s[i] = xh; S->byl.s[i] = yl; S->byh.s[i] = yh;
        S->ix.s[i] = tx * SMOOTH_CELL; S->iy.s[i] = ty * SMOOTH_CELL;   /* as photon_event sets them */
        tmode = -1;
#else
        return 0;
#endif
    }
#endif
    S->tmode.s[i] = tmode;
    S->opx.s[i] = op.x; S->opg.s[i] = op.y; S->opi.s[i] = op.z; S->opm.s[i] = op.w;
    S->zt.s[i] = zt; S->zb.s[i] = zb;
    const float2 m = store_imp[NL * NB + 2 * L], zg = store_imp[NL * NB + 2 * L + 1];
    S->smx.s[i] = m.x; S->smy.s[i] = m.y; S->szx.s[i] = zg.x; S->szy.s[i] = zg.y;
#if HERO_C > 1
    __global const float* tab = logmu;
    if (L != sw->pL) { sw_sync(sw, optics, tab); sw->pL = L; }
    for (int j = 0; j < HERO_C; ++j) {
        const float2 ab = TAB_HG(L, sw_band(sw->h, j));
        S->A[j].s[i] = ab.x; S->B[j].s[i] = ab.y;
    }
    S->malb.s[i] = TAB_MAXALB(L, sw->h);
#endif
    return 1;
}

/* ---------------------------------------------------------------- lanes, vector */
/* Philox4x32-10 (Random123's philox4x32, pyopencl-random123/philox.cl) on LANES counters.  The
 * 32 x 32 -> 64-bit products in 64-bit lanes: PoCL calls its library for a vector mul_hi. */
HOT void philox_v(vu* c0, vu* c1, vu* c2, vu* c3, vu k0, vu k1) {
    const vl m0 = (vl)0xD2511F53L, m1 = (vl)0xCD9E8D57L;
    for (int r = 0; r < 10; ++r) {
        if (r > 0) { k0 += (vu)0x9E3779B9u; k1 += (vu)0xBB67AE85u; }
        const vl p0 = m0 * V_L(*c0), p1 = m1 * V_L(*c2);
        const vu hi0 = V_U(p0 >> 32), lo0 = V_U(p0), hi1 = V_U(p1 >> 32), lo1 = V_U(p1);
        *c0 = hi1 ^ *c1 ^ k0; *c1 = lo1; *c2 = hi0 ^ *c3 ^ k1; *c3 = lo0;
    }
}

/* The next block of rng (stream 0) for the lanes of m that have none: one Philox for all of them,
 * so that the lanes' blocks, used up at different draws, cost one vector Philox per fast
 * iteration rather than one per draw. */
HOT void rng_ahead(Lanes* S, vi m) {
    const vi need = m & ~S->rnv.v;
    if (!any_v(need)) return;
    const vu c1 = S->rc[0][1].v;
    vu n0 = S->rc[0][0].v, n1 = c1, n2 = S->rc[0][2].v, n3 = S->rc[0][3].v;
    philox_v(&n0, &n1, &n2, &n3, S->rk[0][0].v, S->rk[0][1].v);
    S->rn[0].v = sel_u(S->rn[0].v, n0, need); S->rn[1].v = sel_u(S->rn[1].v, n1, need);
    S->rn[2].v = sel_u(S->rn[2].v, n2, need); S->rn[3].v = sel_u(S->rn[3].v, n3, need);
    S->rc[0][1].v = sel_u(c1, c1 + (vu)1u, need);
    S->rnv.v |= need;
}

/* rng_u01 of stream w (0: the path's, 1: storage's) in the lanes of mask m (the others draw
 * nothing): the same uniforms, in the same order, as a scalar Rng */
HOT vf vdraw(Lanes* S, int w, vi m) {
    vi used = S->ru[w].v;
    vu r0 = S->rr[w][0].v, r1 = S->rr[w][1].v, r2 = S->rr[w][2].v, r3 = S->rr[w][3].v;
    const vi need = m & (used == (vi)4);
    if (any_v(need)) {
        if (w == 0) {
            rng_ahead(S, need);
            r0 = sel_u(r0, S->rn[0].v, need); r1 = sel_u(r1, S->rn[1].v, need);
            r2 = sel_u(r2, S->rn[2].v, need); r3 = sel_u(r3, S->rn[3].v, need);
            S->rnv.v &= ~need;
        } else {
            const vu c1 = S->rc[w][1].v;
            vu n0 = S->rc[w][0].v, n1 = c1, n2 = S->rc[w][2].v, n3 = S->rc[w][3].v;
            philox_v(&n0, &n1, &n2, &n3, S->rk[w][0].v, S->rk[w][1].v);
            r0 = sel_u(r0, n0, need); r1 = sel_u(r1, n1, need);
            r2 = sel_u(r2, n2, need); r3 = sel_u(r3, n3, need);
            S->rc[w][1].v = sel_u(c1, c1 + (vu)1u, need);
        }
        S->rr[w][3].v = r3;
        used = sel_i(used, (vi)0, need);
    }
    const vu x = r0;
    S->rr[w][0].v = sel_u(r0, r1, m);
    S->rr[w][1].v = sel_u(r1, r2, m);
    S->rr[w][2].v = sel_u(r2, r3, m);
    S->ru[w].v = used - m;                      /* m is -1 where drawn */
    return (V_F(x >> (vu)8u) + 1.0f) * (1.0f / 16777216.0f);
}

/* neg_log_u01, exp_neg, azimuth_cs, hg_sample_cos_t, rotate_dir_cst of volume.h, lane-wise */
HOT vf neg_log_v(vf u) {
    const vu bits = AS_U(u);
    vi e = AS_I(bits >> (vu)23u) - (vi)127;
    vf m = AS_F((bits & (vu)0x007fffffu) | (vu)0x3f800000u);
    const vi big = m > (vf)1.41421356f;
    m = sel_f(m, m * 0.5f, big);
    e = e - big;
    const vf s = (m - 1.0f) / (m + 1.0f);
    const vf s2 = s * s;
    const vf lnm = 2.0f * s * (1.0f + s2 * (1.0f / 3.0f + s2 * (0.2f + s2 * (1.0f / 7.0f
                   + s2 * (1.0f / 9.0f)))));
    return -(lnm + V_F(e) * 0.693147180559945f);
}

HOT vf exp_neg_v(vf x) {
    const vf y = max_v(x, (vf)0.0f) * 1.44269504088896f;
    const vi ok = y < (vf)126.0f;
    const vf n = V_F(V_I(sel_f((vf)0.0f, y, ok)));        /* floor: y >= 0 */
    const vf t = (y - n - 0.5f) * 0.693147180559945f;
    const vf p = 1.0f - t * (1.0f - t * (0.5f - t * (1.0f / 6.0f - t * (1.0f / 24.0f
                 - t * (1.0f / 120.0f - t * (1.0f / 720.0f))))));
    return sel_f((vf)0.0f, AS_F(((vi)127 - V_I(n)) << (vi)23) * (p * 0.707106781186548f), ok);
}

HOT void azimuth_v(vf u, vf* cp, vf* sp) {
    const vf x = 4.0f * u;
    const vi iq = V_I(x);
    const vf fq = V_F(iq);
    const vi q = iq & (vi)3;
    const vf a = (x - fq - 0.5f) * 1.57079632679490f;
    const vf a2 = a * a;
    const vf sa = a * (1.0f + a2 * (-1.0f / 6.0f + a2 * (1.0f / 120.0f + a2 * (-1.0f / 5040.0f
                  + a2 * (1.0f / 362880.0f)))));
    const vf ca = 1.0f + a2 * (-0.5f + a2 * (1.0f / 24.0f + a2 * (-1.0f / 720.0f
                  + a2 * (1.0f / 40320.0f))));
    const vf c = (ca - sa) * 0.707106781186548f;
    const vf s = (ca + sa) * 0.707106781186548f;
    const vi q0 = q == (vi)0, q1 = q == (vi)1, q2 = q == (vi)2;
    *cp = select(select(select(s, -c, q2), -s, q1), c, q0);
    *sp = select(select(select(-c, -s, q2), c, q1), s, q0);
}

HOT vf hg_cos_v(vf g, vf inv2g, vf u) {
    const vf t = (1.0f - g * g) / (1.0f - g + 2.0f * g * u);
    const vf c0 = (1.0f + g * g - t * t) * inv2g;
    const vf c = sel_f(sel_f(c0, (vf)1.0f, c0 > (vf)1.0f), (vf)-1.0f, c0 < (vf)-1.0f);
    return sel_f(c, 2.0f * u - 1.0f, inv2g == (vf)0.0f);
}

HOT void rotate_v(vf* dx, vf* dy, vf* dz, vf ct, vf cp, vf sp) {
    const vf st2 = 1.0f - ct * ct;
    const vf st = sel_f((vf)0.0f, sqrt(st2), st2 > (vf)0.0f);
    const vf sg = sel_f((vf)-1.0f, (vf)1.0f, *dz >= (vf)0.0f);
    const vf a = -1.0f / (sg + *dz);
    const vf bb = *dx * *dy * a;
    const vf b1x = 1.0f + sg * *dx * *dx * a, b1y = sg * bb, b1z = -sg * *dx;
    const vf b2x = bb, b2y = sg + *dy * *dy * a, b2z = -*dy;
    const vf c1 = st * cp, c2 = st * sp;
    const vf ox = c1 * b1x + c2 * b2x + ct * *dx;
    const vf oy = c1 * b1y + c2 * b2y + ct * *dy;
    const vf oz = c1 * b1z + c2 * b2z + ct * *dz;
    const vf k = 1.5f - 0.5f * (ox * ox + oy * oy + oz * oz);
    *dx = ox * k; *dy = oy * k; *dz = oz * k;
}

HOT vf hg_rel_v(vf g, vf ce) {
    const vf a = 1.0f + g * g - 2.0f * g * ce;
    const vf omg = 1.0f - abs_v(g);
    return omg * omg * omg / (a * sqrt(a));
}

/* The distance to the first plane ahead of a box (z in zb .. zt, x in xl .. xh, y in yl .. yh),
 * at least 0: in a layer's core its planes and the domain's sides (next_boundary's core mode, or
 * FLAT's mode), in tile mode the tile's box.  A flight shorter than it meets no boundary. */
HOT vf box_exit_v(vf x, vf y, vf z, vf dx, vf dy, vf dz, vf zt, vf zb, vf xl, vf xh, vf yl, vf yh) {
    const vf bz = sel_f(sel_f((vf)BIG, (zb - z) / dz, (dz < (vf)0.0f) & (zb > (vf)(-BIG))),
                        (zt - z) / dz, dz > (vf)0.0f);
    const vf bx = sel_f(sel_f((vf)BIG, (xl - x) / dx, dx < (vf)0.0f), (xh - x) / dx, dx > (vf)0.0f);
    const vf by = sel_f(sel_f((vf)BIG, (yl - y) / dy, dy < (vf)0.0f), (yh - y) / dy, dy > (vf)0.0f);
    const vf b = min_v(bz, min_v(bx, by));
    return sel_f((vf)0.0f, b, b > (vf)0.0f);
}

/* whether z lies within zb .. zt, moving by dz (a photon on a plane moving out of it is not) */
HOT vi within_v(vf z, vf dz, vf zt, vf zb) {
    return sel_i(z <= zt, z < zt, dz > (vf)0.0f) & sel_i(z >= zb, z > zb, dz < (vf)0.0f);
}

/* Up to FAST_ITERS iterations of the fast phase: every lane of S->fast whose next event is a
 * collision in its layer's core does it (collide in photon.cl, in vector arithmetic); the others
 * leave S->fast for the slow phase.  Returns the collisions done. */
HOT int lanes_fast(Lanes* S, __constant const Params* P, __global const float4* optics,
                   __global const float* logmu, __global const float2* store_imp,
                   __global const float2* band_spi, PhotonMap map, Counters* cnt) {
    int done = 0;
    vi act = S->fast.v;
    const vf opx = S->opx.v, opg = S->opg.v, opi = S->opi.v, opm = S->opm.v;
    const vf zt = S->zt.v, zb = S->zb.v;
#ifdef SMOOTH_SURFACE
    const vi tmode = S->tmode.v;
    const vf bzt = S->bzt.v, bzb = S->bzb.v, bxl = S->bxl.v, bxh = S->bxh.v;
    const vf byl = S->byl.v, byh = S->byh.v;
#endif
    const vl thr = (vl)(long)(P->rr_threshold * W0F);
    for (;;) {
        vf x = S->px.v, y = S->py.v, z = S->pz.v;
        vf dx = S->ux.v, dy = S->uy.v, dz = S->uz.v;
        vf tau = S->tau.v;
        vi events = S->events.v;
        const vf s = tau / opm;
#ifdef FLAT
        const int sides = P->lateral != 0;
#else
        const int sides = 1;
#endif
        const vf xl = sides ? (vf)P->x0 : (vf)(-BIG), xh = sides ? (vf)(P->x0 + P->xw) : (vf)BIG;
        const vf yl = sides ? (vf)P->y0 : (vf)(-BIG), yh = sides ? (vf)(P->y0 + P->yw) : (vf)BIG;
#ifdef FLAT
        const vf db = box_exit_v(x, y, z, dx, dy, dz, zt, zb, xl, xh, yl, yh);
#else
        const vi core = within_v(z, dz, zt, zb);
        vf db = box_exit_v(x, y, z, dx, dy, dz, zt, zb, xl, xh, yl, yh);
#ifdef SMOOTH_SURFACE
        const vi tile = ~core & tmode & within_v(z, dz, bzt, bzb);
        db = sel_f(db, box_exit_v(x, y, z, dx, dy, dz, bzt, bzb, bxl, bxh, byl, byh), tile);
        act &= core | tile;
#else
        act &= core;
#endif
#endif
        const vi coll = act & (s < db) & (events < (vi)P->max_events);
        if (!any_v(coll)) { act = coll; break; }
        COUNT(cnt, K_LANE_ITERS);

        rng_ahead(S, coll);
        /* ---- collide: move, absorb by weight */
        events -= coll;
        S->events.v = events;
        x = sel_f(x, x + s * dx, coll); y = sel_f(y, y + s * dy, coll); z = sel_f(z, z + s * dz, coll);
        S->px.v = x; S->py.v = y; S->pz.v = z;

        const vl cl = V_L(coll);
#if HERO_C > 1
        S->pl.v = sel_f(S->pl.v, S->pl.v + s, coll);
        S->pn.v = S->pn.v - coll;
        vf amax = sel_f(S->amax.v, S->amax.v * S->malb.v, coll);
#endif
        vl W = S->W.v;
        vl dw = V_LRTE(V_F(W) * opx);
#ifdef CLPPM_FAULT_WRONG                /* the self-test's tests only: a miscompiled absorption */
        dw = V_LRTE(V_F(dw) * 1.5f);
#endif
        dw = sel_l(sel_l(dw, W, dw > W), (vl)0, dw < (vl)0);
        dw = sel_l((vl)0, dw, cl);
        S->acur.v = S->acur.v + dw;
        W -= dw;
        const vi scat = coll & V_I(W > (vl)0);
        /* ---- storage: store_event's bound in the lanes, store_record lane by lane */
        if (map.capacity > 0u) {
            const vi cand = scat & (z > (vf)P->store_zmin);
            if (any_v(cand)) {
                vf u = (vf)0.0f;
                vi keep = cand;
                if (P->store_rule == 1) {
                    u = vdraw(S, 1, cand);
                    const vf c = dz;
                    const vf ce = sel_f(c * P->store_cos + sqrt(max_v((vf)0.0f, 1.0f - c * c)) * P->store_sin,
                                         (vf)1.0f, c >= (vf)P->store_cos);
                    const vf szy = S->szy.v;
                    const vf hrel = sel_f((vf)1.0f, hg_rel_v(szy, ce), szy >= (vf)0.0f);
#if HERO_C > 1
                    const vf am = amax;
#else
                    const vf am = V_F(W) * (1.0f / W0F);
#endif
                    const vf bound = 1.001f * hrel * exp_neg_v(S->smx.v + S->smy.v * max_v((vf)0.0f, S->szx.v - z))
                                     * am;
                    keep = cand & (u <= min_v(max_v(P->store_scale * bound, (vf)P->store_qmin), (vf)1.0f));
                }
                if (any_v(keep)) {
                    LF us;
                    LI ks;
                    LL ws;
                    us.v = u; ks.v = keep; ws.v = W;
#if HERO_C > 1
                    S->amax.v = amax;
#endif
                    for (int i = 0; i < LANES; ++i) {
                        if (!ks.s[i]) continue;
                        Track t;
                        Spectral sw;
                        lane_track_get(S, i, &t);
                        lane_sw_get(S, i, &sw);
                        store_record(P, &t, &sw, ws.s[i], S->b.s[i], us.s[i], store_imp, band_spi, optics, logmu, map, cnt);
                    }
                }
            }
        }
        /* ---- scatter_photon: Henyey-Greenstein, the bands' ratios, roulette */
        const vf ct = hg_cos_v(opg, opi, vdraw(S, 0, scat));
        vf cp, sp;
        azimuth_v(vdraw(S, 0, scat), &cp, &sp);
        vf nx = dx, ny = dy, nz = dz;
        rotate_v(&nx, &ny, &nz, ct, cp, sp);
        S->ux.v = sel_f(dx, nx, scat); S->uy.v = sel_f(dy, ny, scat); S->uz.v = sel_f(dz, nz, scat);
#if HERO_C > 1
        {
            const vf inv = 1.0f / (S->A[0].v - S->B[0].v * ct);
            vf lo = (vf)1.0f, hi = (vf)1.0f;
            for (int j = 1; j < HERO_C; ++j) {
                const vf h = S->hq[j].v;
                const vf hn = sel_f(h, h * ((S->A[j].v - S->B[j].v * ct) * inv), scat);
                S->hq[j].v = hn;
                lo = min_v(lo, hn); hi = max_v(hi, hn);
            }
            const vi fold = scat & ((lo < (vf)0x1p-40f) | (hi > (vf)0x1p40f));
            if (any_v(fold)) {
                LI fs;
                fs.v = fold;
                for (int i = 0; i < LANES; ++i) {
                    if (!fs.s[i]) continue;
                    for (int j = 1; j < HERO_C; ++j) {
                        S->lr[j].s[i] -= 1.5f * log(S->hq[j].s[i]);
                        S->hq[j].s[i] = 1.0f;
                    }
                }
            }
        }
#endif
        const vi rr = scat & V_I(W < thr);
        if (any_v(rr)) {
            const vi surv = rr & (vdraw(S, 0, rr) * P->rr_m <= (vf)1.0f);
            const vi die = rr & ~surv;
            const vl sl = V_L(surv), dl = V_L(die);
            const vl g2 = W * (long)P->rr_m - W;
            S->gain.v = S->gain.v + sel_l((vl)0, g2, sl);
            S->loss.v = S->loss.v + sel_l((vl)0, W, dl);
            W = sel_l(W, W + g2, sl);
            W = sel_l(W, (vl)0, dl);
#if HERO_C > 1
            S->scale.v = sel_f(S->scale.v, S->scale.v * P->rr_m, surv);
            amax = sel_f(amax, amax * P->rr_m, surv);
#endif
        }
#if HERO_C > 1
        S->amax.v = amax;
#endif
        S->W.v = W;
#ifdef DEPTH_ROULETTE
        {
            const vi deep = scat & V_I(W > (vl)0) & (S->pz.v < (vf)P->deep_z0) & (S->planes.v < (vi)DEEP_PLANES);
            if (any_v(deep)) {
                LI ds;
                ds.v = deep;
                for (int i = 0; i < LANES; ++i) {
                    if (!ds.s[i]) continue;
                    Track t;
                    Spectral sw;
                    Rng g;
                    lane_track_get(S, i, &t);
                    lane_sw_get(S, i, &sw);
                    lane_rng_get(S, 0, i, &g);
                    lane_fold(S, i);
                    deep_roulette(P, &t, &sw, &S->W.s[i], &S->f[i], &S->planes.s[i], &g);
                    lane_sw_put(S, i, &sw);
                    lane_rng_put(S, 0, i, &g);
                }
            }
        }
#endif
        /* ---- the next optical depth */
        S->tau.v = sel_f(tau, neg_log_v(vdraw(S, 0, coll)), coll);
        const int n = count_v(coll);
        act = coll & V_I(W > (vl)0);                /* an ended photon: the slow phase's next */
        done += n;
        if (n < FAST_MIN) break;
    }
    S->fast.v = act;
    return done;
}

/* The slow phase of lane i (not in S->fast): photon_event until its photon is in a layer's core
 * again (at least one event if it was live: the one the fast phase left), and when a photon
 * ends its fates and the next photon of the launch.  Clears S->on.s[i] when none is left. */
HOT void lane_slow(Lanes* S, int i, const PhotonLaunch* launch, VOLUME_ARGS, __global const float2* store_imp,
                   __global const float* band_cdf, __global const float2* band_spi, __global const float* logmu,
                   __global volatile uint* store_count, __global long* tallies, __global const float* smooth,
                   __global const float2* tile_z, PhotonMap map, Counters* cnt) {
    Track t;
    Spectral sw;
    Rng rng, srng;
    lane_fold(S, i);
    lane_track_get(S, i, &t);
    lane_sw_get(S, i, &sw);
    lane_rng_get(S, 0, i, &rng);
    lane_rng_get(S, 1, i, &srng);
    long W = S->W.s[i];
    int b = S->b.s[i], live = S->live.s[i], events = S->events.s[i], planes = S->planes.s[i], still = S->still.s[i];
    float tau = S->tau.s[i];
    Fates* f = &S->f[i];
    int first = W > 0;
    int fast = 0;
    for (;;) {
        if (W <= 0) {
            if (live) { fates_flush(f, tallies + (size_t)b * NC); fates_clear(f); live = 0; }
            const uint k = atomic_inc(store_count + 1);
            if (k >= launch->count) { S->on.s[i] = 0; break; }
            live = photon_start(launch->photon_offset + k, launch, VOLUME_PASS, band_cdf, smooth, tallies, &rng,
                                &srng, &t, &sw, &b, f, &W, &events, &planes, &still, &tau, cnt);
            S->b.s[i] = b;
            continue;
        }
        if (!first && (fast = lane_enter_fast(S, i, &t, &sw, VOLUME_PASS, logmu, store_imp))) break;
        first = 0;
        photon_event(&t, &sw, &W, b, f, &events, &planes, &still, &tau, &rng, &srng, VOLUME_PASS, store_imp,
                     band_spi, logmu, smooth, tile_z, map, cnt);
    }
    lane_track_put(S, i, &t);
    lane_sw_put(S, i, &sw);
    lane_rng_put(S, 0, i, &rng);
    lane_rng_put(S, 1, i, &srng);
    S->W.s[i] = W; S->b.s[i] = b; S->live.s[i] = live; S->events.s[i] = events; S->planes.s[i] = planes;
    S->still.s[i] = still; S->tau.s[i] = tau;
    S->fast.s[i] = fast ? -1 : 0;
}

#endif
