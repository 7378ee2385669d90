/* The photon pass in explicit SIMD lanes (LANES = 4, 8 or 16; photonpass.py photon_lanes picks it
 * per device: CPUs, whose OpenCL compilers run photon_pass one work item per lane of nothing).
 *
 * Neither CPU runtime vectorises photon_pass across work items: its loop body has a dozen kinds
 * of event, and a SIMD version of it executes all of them every iteration (Intel's, forced, ran
 * 1.8-5x slower).  But one kind dominates: a collision in the core of a layer, where the region's
 * boundaries are two planes and the domain's sides (the forearm's photons: 236 of 260 events are
 * collisions).  Here one work item carries LANES photons in structure-of-arrays state, and
 *
 *   - the fast phase runs that one kind in vector arithmetic over the lanes (float16 on
 *     AVX-512): the free path against the core's planes and sides, absorption, the storage
 *     bound, Henyey-Greenstein scattering, the bands' phase-function ratios, roulette, the next
 *     optical depth, and Philox for every lane at once.  A lane whose next event is anything
 *     else drops out of the fast phase; the phase ends when fewer than FAST_MIN lanes remain;
 *   - the slow phase gives each dropped lane photon_event (photon.cl, scalar, the same code as
 *     photon_pass) until it is back in a layer's core, and a lane whose photon ended the next
 *     photon of the launch (photon_start).
 *
 * A photon's path draws the same random numbers in the same order as in photon_pass (a lane's
 * Philox block is consumed one uniform at a time, as rng_u01 does), and the arithmetic is the
 * same formulas, so paths agree until float rounding of a vector operation first differs;
 * storage decisions (store_bound, then store_record) are photon_pass's. */
#ifndef CLPPM_PHOTON_LANES_H
#define CLPPM_PHOTON_LANES_H

#define VJOIN_(a, n) a##n
#define VJOIN(a, n) VJOIN_(a, n)
typedef VJOIN(float, LANES) vf;
typedef VJOIN(int, LANES) vi;
typedef VJOIN(uint, LANES) vu;
typedef VJOIN(long, LANES) vl;
#define VLD(p) VJOIN(vload, LANES)(0, p)
#define VST(v, p) VJOIN(vstore, LANES)(v, 0, p)
#define V_F(x) VJOIN(convert_float, LANES)(x)
#define V_L(x) VJOIN(convert_long, LANES)(x)
#define V_I(x) VJOIN(convert_int, LANES)(x)
#define V_LRTE(x) VJOIN(VJOIN(convert_long, LANES), _rte)(x)
#define AS_F(x) VJOIN(as_float, LANES)(x)
#define AS_U(x) VJOIN(as_uint, LANES)(x)
#define AS_I(x) VJOIN(as_int, LANES)(x)

/* the fast phase ends when fewer lanes than this still collide in a core */
#ifndef FAST_MIN
#define FAST_MIN (LANES / 2)
#endif

/* Every lane's state, structure of arrays.  A lane's scalar state (Track, Spectral, Rng) is
 * copied out for the slow phase and back after it; its Fates live here per lane (the fast phase
 * adds roulette and absorption into gain, loss and acur, folded in before the slow phase). */
typedef struct {
    float px[LANES], py[LANES], pz[LANES], ux[LANES], uy[LANES], uz[LANES];
    int L[LANES], ix[LANES], iy[LANES];
    long W[LANES];
    int b[LANES], live[LANES], on[LANES], events[LANES], planes[LANES], still[LANES];
    int fast[LANES];                     /* -1: in a layer's core, the fast phase's (0: not) */
    float tau[LANES];
    uint rc[2][4][LANES], rk[2][2][LANES], rr[2][4][LANES];   /* [0] rng, [1] srng: Rng */
    int ru[2][LANES];
#if HERO_C > 1
    float lr[HERO_C][LANES], hq[HERO_C][LANES], la[HERO_C][LANES];
    float scale[LANES], amax[LANES], pl[LANES];
    int pL[LANES], pn[LANES];
    float A[HERO_C][LANES], B[HERO_C][LANES];    /* the layer's TAB_HG of each band carried */
    float malb[LANES];                           /* the layer's TAB_MAXALB of the hero class */
#endif
    long gain[LANES], loss[LANES], acur[LANES];  /* the fast phase's fates, acur in layer L */
    Fates f[LANES];
    /* the layer's constants: optics (mua/mut, g, 1/(2g), mut), the core's planes, store_imp's */
    float opx[LANES], opg[LANES], opi[LANES], opm[LANES], zt[LANES], zb[LANES];
    float smx[LANES], smy[LANES], szx[LANES], szy[LANES];
} Lanes;

/* ---------------------------------------------------------------- one lane, scalar */
HOT void lane_rng_get(const Lanes* S, int w, int i, Rng* g) {
    for (int k = 0; k < 4; ++k) { g->c.v[k] = S->rc[w][k][i]; g->r.v[k] = S->rr[w][k][i]; }
    g->k.v[0] = S->rk[w][0][i]; g->k.v[1] = S->rk[w][1][i];
    g->used = S->ru[w][i];
}

HOT void lane_rng_put(Lanes* S, int w, int i, const Rng* g) {
    for (int k = 0; k < 4; ++k) { S->rc[w][k][i] = g->c.v[k]; S->rr[w][k][i] = g->r.v[k]; }
    S->rk[w][0][i] = g->k.v[0]; S->rk[w][1][i] = g->k.v[1];
    S->ru[w][i] = g->used;
}

HOT void lane_track_get(const Lanes* S, int i, Track* t) {
    t->pos = (float3)(S->px[i], S->py[i], S->pz[i]);
    t->dir = (float3)(S->ux[i], S->uy[i], S->uz[i]);
    t->L = S->L[i]; t->ix = S->ix[i]; t->iy = S->iy[i];
}

HOT void lane_track_put(Lanes* S, int i, const Track* t) {
    S->px[i] = t->pos.x; S->py[i] = t->pos.y; S->pz[i] = t->pos.z;
    S->ux[i] = t->dir.x; S->uy[i] = t->dir.y; S->uz[i] = t->dir.z;
    S->L[i] = t->L; S->ix[i] = t->ix; S->iy[i] = t->iy;
}

HOT void lane_sw_get(const Lanes* S, int i, Spectral* w) {
    w->h = S->b[i];
#if HERO_C > 1
    for (int j = 0; j < HERO_C; ++j) { w->lr[j] = S->lr[j][i]; w->hq[j] = S->hq[j][i]; w->la[j] = S->la[j][i]; }
    w->scale = S->scale[i]; w->amax = S->amax[i]; w->pl = S->pl[i]; w->pL = S->pL[i]; w->pn = S->pn[i];
#endif
}

HOT void lane_sw_put(Lanes* S, int i, const Spectral* w) {
#if HERO_C > 1
    for (int j = 0; j < HERO_C; ++j) { S->lr[j][i] = w->lr[j]; S->hq[j][i] = w->hq[j]; S->la[j][i] = w->la[j]; }
    S->scale[i] = w->scale; S->amax[i] = w->amax; S->pl[i] = w->pl; S->pL[i] = w->pL; S->pn[i] = w->pn;
#endif
}

/* the fast phase's fates of lane i into its Fates */
HOT void lane_fold(Lanes* S, int i) {
    Fates* f = &S->f[i];
    f->gain += S->gain[i]; f->loss += S->loss[i];
    if (S->acur[i]) f->absorbed[S->L[i]] += S->acur[i];
    S->gain[i] = 0; S->loss[i] = 0; S->acur[i] = 0;
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
    const float4 op = optics[L * NB + S->b[i]];
    if (!(op.x < 1.0f) || !(op.w > 0.0f)) return 0;
#ifdef FLAT
    const float zt = IF_Z(L);
    const float zb = (L + 1 <= NL && IF_Z(L + 1) > -BIG) ? IF_Z(L + 1) : -BIG;
#else
    const float zt = IF_ZMIN(L), zb = IF_ZMAX(L + 1);
    const float z = t->pos.z, dz = t->dir.z;
    if (!((dz > 0.0f ? z < zt : z <= zt) && (dz < 0.0f ? z > zb : z >= zb))) return 0;
#endif
    S->opx[i] = op.x; S->opg[i] = op.y; S->opi[i] = op.z; S->opm[i] = op.w;
    S->zt[i] = zt; S->zb[i] = zb;
    const float2 m = store_imp[NL * NB + 2 * L], zg = store_imp[NL * NB + 2 * L + 1];
    S->smx[i] = m.x; S->smy[i] = m.y; S->szx[i] = zg.x; S->szy[i] = zg.y;
#if HERO_C > 1
    __global const float* tab = logmu;
    if (L != sw->pL) { sw_sync(sw, optics, tab); sw->pL = L; }
    for (int j = 0; j < HERO_C; ++j) {
        const float2 ab = TAB_HG(L, sw_band(sw->h, j));
        S->A[j][i] = ab.x; S->B[j][i] = ab.y;
    }
    S->malb[i] = TAB_MAXALB(L, sw->h);
#endif
    return 1;
}

/* ---------------------------------------------------------------- lanes, vector */
/* Philox4x32-10 (Random123's philox4x32, pyopencl-random123/philox.cl) on LANES counters */
HOT void philox_v(vu* c0, vu* c1, vu* c2, vu* c3, vu k0, vu k1) {
    for (int r = 0; r < 10; ++r) {
        if (r > 0) { k0 += (vu)0x9E3779B9u; k1 += (vu)0xBB67AE85u; }
        const vu hi0 = mul_hi((vu)0xD2511F53u, *c0), lo0 = (vu)0xD2511F53u * *c0;
        const vu hi1 = mul_hi((vu)0xCD9E8D57u, *c2), lo1 = (vu)0xCD9E8D57u * *c2;
        *c0 = hi1 ^ *c1 ^ k0; *c1 = lo1; *c2 = hi0 ^ *c3 ^ k1; *c3 = lo0;
    }
}

/* rng_u01 of stream w (0: the path's, 1: storage's) in the lanes of mask m (the others draw
 * nothing): the same uniforms, in the same order, as a scalar Rng */
HOT vf vdraw(Lanes* S, int w, vi m) {
    vi used = VLD(S->ru[w]);
    vu r0 = VLD(S->rr[w][0]), r1 = VLD(S->rr[w][1]), r2 = VLD(S->rr[w][2]), r3 = VLD(S->rr[w][3]);
    const vi need = m & (used == (vi)4);
    if (any(need)) {
        const vu c1 = VLD(S->rc[w][1]);
        vu n0 = VLD(S->rc[w][0]), n1 = c1, n2 = VLD(S->rc[w][2]), n3 = VLD(S->rc[w][3]);
        philox_v(&n0, &n1, &n2, &n3, VLD(S->rk[w][0]), VLD(S->rk[w][1]));
        r0 = select(r0, n0, need); r1 = select(r1, n1, need);
        r2 = select(r2, n2, need); r3 = select(r3, n3, need);
        VST(select(c1, c1 + (vu)1u, need), S->rc[w][1]);
        VST(r3, S->rr[w][3]);
        used = select(used, (vi)0, need);
    }
    const vu x = r0;
    VST(select(r0, r1, m), S->rr[w][0]);
    VST(select(r1, r2, m), S->rr[w][1]);
    VST(select(r2, r3, m), S->rr[w][2]);
    VST(used - m, S->ru[w]);                    /* m is -1 where drawn */
    return (V_F(x >> (vu)8u) + 1.0f) * (1.0f / 16777216.0f);
}

/* neg_log_u01, exp_neg, azimuth_cs, hg_sample_cos_t, rotate_dir_cst of volume.h, lane-wise */
HOT vf neg_log_v(vf u) {
    const vu bits = AS_U(u);
    vi e = AS_I(bits >> (vu)23u) - (vi)127;
    vf m = AS_F((bits & (vu)0x007fffffu) | (vu)0x3f800000u);
    const vi big = m > (vf)1.41421356f;
    m = select(m, m * 0.5f, big);
    e = e - big;
    const vf s = (m - 1.0f) / (m + 1.0f);
    const vf s2 = s * s;
    const vf lnm = 2.0f * s * (1.0f + s2 * (1.0f / 3.0f + s2 * (0.2f + s2 * (1.0f / 7.0f
                   + s2 * (1.0f / 9.0f)))));
    return -(lnm + V_F(e) * 0.693147180559945f);
}

HOT vf exp_neg_v(vf x) {
    const vf y = fmax(x, (vf)0.0f) * 1.44269504088896f;
    const vi ok = y < (vf)126.0f;
    const vf n = floor(select((vf)0.0f, y, ok));
    const vf t = (y - n - 0.5f) * 0.693147180559945f;
    const vf p = 1.0f - t * (1.0f - t * (0.5f - t * (1.0f / 6.0f - t * (1.0f / 24.0f
                 - t * (1.0f / 120.0f - t * (1.0f / 720.0f))))));
    return select((vf)0.0f, AS_F(((vi)127 - V_I(n)) << (vi)23) * (p * 0.707106781186548f), ok);
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
    const vf c = clamp((1.0f + g * g - t * t) * inv2g, -1.0f, 1.0f);
    return select(c, 2.0f * u - 1.0f, inv2g == (vf)0.0f);
}

HOT void rotate_v(vf* dx, vf* dy, vf* dz, vf ct, vf cp, vf sp) {
    const vf st2 = 1.0f - ct * ct;
    const vf st = select((vf)0.0f, sqrt(st2), st2 > (vf)0.0f);
    const vf sg = select((vf)-1.0f, (vf)1.0f, *dz >= (vf)0.0f);
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
    const vf omg = 1.0f - fabs(g);
    return omg * omg * omg / (a * sqrt(a));
}

/* the distance to the core's planes and, if it reaches them, the domain's sides (next_boundary's
 * core mode; FLAT: its flat mode), at least 0 */
HOT vf core_boundary_v(__constant const Params* P, vf x, vf y, vf z, vf dx, vf dy, vf dz, vf zt, vf zb) {
    vf best = select(select((vf)BIG, (zb - z) / dz, (dz < (vf)0.0f) & (zb > (vf)(-BIG))),
                     (zt - z) / dz, dz > (vf)0.0f);
#ifdef FLAT
    if (P->lateral != 0)
#endif
    {
        const vf ex = x + best * dx, ey = y + best * dy;
        const vi inside = (best < (vf)BIG) & (ex >= (vf)P->x0) & (ex <= (vf)(P->x0 + P->xw)) &
                          (ey >= (vf)P->y0) & (ey <= (vf)(P->y0 + P->yw));
        if (!all(inside)) {
            const vf sx = (select((vf)P->x0, (vf)(P->x0 + P->xw), dx > (vf)0.0f) - x) / dx;
            const vf sy = (select((vf)P->y0, (vf)(P->y0 + P->yw), dy > (vf)0.0f) - y) / dy;
            best = select(best, fmin(best, sx), ~inside & (dx != (vf)0.0f) & (sx < best));
            best = select(best, fmin(best, sy), ~inside & (dy != (vf)0.0f) & (sy < best));
        }
    }
    return fmax(best, (vf)0.0f);
}

/* Up to FAST_ITERS iterations of the fast phase: every lane of S->fast whose next event is a
 * collision in its layer's core does it (collide in photon.cl, in vector arithmetic); the others
 * leave S->fast for the slow phase.  Returns the collisions done. */
HOT int lanes_fast(Lanes* S, __constant const Params* P, __global const float4* optics,
                   __global const float* logmu, __global const float2* store_imp,
                   __global const float2* band_spi, PhotonMap map, Counters* cnt) {
    int done = 0;
    vi act = VLD(S->fast);
    const vf opx = VLD(S->opx), opg = VLD(S->opg), opi = VLD(S->opi), opm = VLD(S->opm);
    const vf zt = VLD(S->zt), zb = VLD(S->zb);
    const vl thr = (vl)(long)(P->rr_threshold * W0F);
    for (;;) {
        vf x = VLD(S->px), y = VLD(S->py), z = VLD(S->pz);
        vf dx = VLD(S->ux), dy = VLD(S->uy), dz = VLD(S->uz);
        vf tau = VLD(S->tau);
        vi events = VLD(S->events);
        const vf s = tau / opm;
#ifndef FLAT
        act &= select((vi)0, (vi)-1, ((dz > (vf)0.0f) ? (z < zt) : (z <= zt)) &
                                     ((dz < (vf)0.0f) ? (z > zb) : (z >= zb)));
#endif
        const vf db = core_boundary_v(P, x, y, z, dx, dy, dz, zt, zb);
        const vi coll = act & (s < db) & (events < (vi)P->max_events);
        act = coll;
        if (!any(coll)) break;
        /* ---- collide: move, absorb by weight */
        events -= coll;
        VST(events, S->events);
        x = select(x, x + s * dx, coll); y = select(y, y + s * dy, coll); z = select(z, z + s * dz, coll);
        VST(x, S->px); VST(y, S->py); VST(z, S->pz);
        const vl cl = V_L(coll);
#if HERO_C > 1
        VST(select(VLD(S->pl), VLD(S->pl) + s, coll), S->pl);
        VST(VLD(S->pn) - coll, S->pn);
        vf amax = select(VLD(S->amax), VLD(S->amax) * VLD(S->malb), coll);
#endif
        vl W = VLD(S->W);
        vl dw = V_LRTE(V_F(W) * opx);
#ifdef CLPPM_FAULT_WRONG                /* the self-test's tests only: a miscompiled absorption */
        dw = V_LRTE(V_F(dw) * 1.5f);
#endif
        dw = select(select(dw, W, dw > W), (vl)0, dw < (vl)0);
        dw = select((vl)0, dw, cl);
        VST(VLD(S->acur) + dw, S->acur);
        W -= dw;
        const vi scat = coll & V_I(W > (vl)0);
        /* ---- storage: store_event's bound in the lanes, store_record lane by lane */
        if (map.capacity > 0u) {
            const vi cand = scat & (z > (vf)P->store_zmin);
            if (any(cand)) {
                vf u = (vf)0.0f;
                vi keep = cand;
                if (P->store_rule == 1) {
                    u = vdraw(S, 1, cand);
                    const vf c = dz;
                    const vf ce = select(c * P->store_cos + sqrt(fmax((vf)0.0f, 1.0f - c * c)) * P->store_sin,
                                         (vf)1.0f, c >= (vf)P->store_cos);
                    const vf szy = VLD(S->szy);
                    const vf hrel = select((vf)1.0f, hg_rel_v(szy, ce), szy >= (vf)0.0f);
#if HERO_C > 1
                    const vf am = amax;
#else
                    const vf am = V_F(W) * (1.0f / W0F);
#endif
                    const vf bound = 1.001f * hrel * exp_neg_v(VLD(S->smx) + VLD(S->smy) * fmax((vf)0.0f, VLD(S->szx) - z))
                                     * am;
                    keep = cand & (u <= clamp(P->store_scale * bound, (vf)P->store_qmin, (vf)1.0f));
                }
                if (any(keep)) {
                    float us[LANES];
                    int ks[LANES];
                    long ws[LANES];
                    VST(u, us); VST(keep, ks); VST(W, ws);
#if HERO_C > 1
                    VST(amax, S->amax);
#endif
                    for (int i = 0; i < LANES; ++i) {
                        if (!ks[i]) continue;
                        Track t;
                        Spectral sw;
                        lane_track_get(S, i, &t);
                        lane_sw_get(S, i, &sw);
                        store_record(P, &t, &sw, ws[i], S->b[i], us[i], store_imp, band_spi, optics, logmu, map, cnt);
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
        VST(select(dx, nx, scat), S->ux); VST(select(dy, ny, scat), S->uy); VST(select(dz, nz, scat), S->uz);
#if HERO_C > 1
        {
            const vf inv = 1.0f / (VLD(S->A[0]) - VLD(S->B[0]) * ct);
            vf lo = (vf)1.0f, hi = (vf)1.0f;
            for (int j = 1; j < HERO_C; ++j) {
                const vf h = VLD(S->hq[j]);
                const vf hn = select(h, h * ((VLD(S->A[j]) - VLD(S->B[j]) * ct) * inv), scat);
                VST(hn, S->hq[j]);
                lo = fmin(lo, hn); hi = fmax(hi, hn);
            }
            const vi fold = scat & ((lo < (vf)0x1p-40f) | (hi > (vf)0x1p40f));
            if (any(fold)) {
                int fs[LANES];
                VST(fold, fs);
                for (int i = 0; i < LANES; ++i) {
                    if (!fs[i]) continue;
                    for (int j = 1; j < HERO_C; ++j) {
                        S->lr[j][i] -= 1.5f * log(S->hq[j][i]);
                        S->hq[j][i] = 1.0f;
                    }
                }
            }
        }
#endif
        const vi rr = scat & V_I(W < thr);
        if (any(rr)) {
            const vi surv = rr & (vdraw(S, 0, rr) * P->rr_m <= (vf)1.0f);
            const vi die = rr & ~surv;
            const vl sl = V_L(surv), dl = V_L(die);
            const vl g2 = W * (long)P->rr_m - W;
            VST(VLD(S->gain) + select((vl)0, g2, sl), S->gain);
            VST(VLD(S->loss) + select((vl)0, W, dl), S->loss);
            W = select(W, W + g2, sl);
            W = select(W, (vl)0, dl);
#if HERO_C > 1
            VST(select(VLD(S->scale), VLD(S->scale) * P->rr_m, surv), S->scale);
            amax = select(amax, amax * P->rr_m, surv);
#endif
        }
#if HERO_C > 1
        VST(amax, S->amax);
#endif
        VST(W, S->W);
#ifdef DEPTH_ROULETTE
        {
            const vi deep = scat & V_I(W > (vl)0) & (VLD(S->pz) < (vf)P->deep_z0) & (VLD(S->planes) < (vi)DEEP_PLANES);
            if (any(deep)) {
                int ds[LANES];
                VST(deep, ds);
                for (int i = 0; i < LANES; ++i) {
                    if (!ds[i]) continue;
                    Track t;
                    Spectral sw;
                    Rng g;
                    lane_track_get(S, i, &t);
                    lane_sw_get(S, i, &sw);
                    lane_rng_get(S, 0, i, &g);
                    lane_fold(S, i);
                    deep_roulette(P, &t, &sw, &S->W[i], &S->f[i], &S->planes[i], &g);
                    lane_sw_put(S, i, &sw);
                    lane_rng_put(S, 0, i, &g);
                }
            }
        }
#endif
        /* ---- the next optical depth */
        VST(select(tau, neg_log_v(vdraw(S, 0, coll)), coll), S->tau);
        int cs[LANES], n = 0;
        VST(coll, cs);
        for (int i = 0; i < LANES; ++i) n += cs[i] & 1;
        done += n;
        if (n < FAST_MIN) break;
    }
    VST(act, S->fast);
    return done;
}

/* The slow phase of lane i (not in S->fast): photon_event until its photon is in a layer's core
 * again (at least one event if it was live: the one the fast phase left), and when a photon
 * ends its fates and the next photon of the launch.  Clears S->on[i] when none is left. */
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
    long W = S->W[i];
    int b = S->b[i], live = S->live[i], events = S->events[i], planes = S->planes[i], still = S->still[i];
    float tau = S->tau[i];
    Fates* f = &S->f[i];
    int first = W > 0;
    int fast = 0;
    for (;;) {
        if (W <= 0) {
            if (live) { fates_flush(f, tallies + (size_t)b * NC); fates_clear(f); live = 0; }
            const uint k = atomic_inc(store_count + 1);
            if (k >= launch->count) { S->on[i] = 0; break; }
            live = photon_start(launch->photon_offset + k, launch, VOLUME_PASS, band_cdf, smooth, tallies, &rng,
                                &srng, &t, &sw, &b, f, &W, &events, &planes, &still, &tau, cnt);
            S->b[i] = b;
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
    S->W[i] = W; S->b[i] = b; S->live[i] = live; S->events[i] = events; S->planes[i] = planes;
    S->still[i] = still; S->tau[i] = tau;
    S->fast[i] = fast ? -1 : 0;
}

#endif
