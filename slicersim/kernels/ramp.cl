/*
 * ramp.cl: up-the-ramp sampling of MACC(n, m, d) H4RG ramps.
 *
 * Random numbers come from Philox4x32-10 keyed by
 *   key = seed, counter = (pixel | (frame, group or pair) << 32, 4*ramp + purpose, draw)
 * (see slicersim/rng.py), so the output is the same for any work-group size,
 * vector width, pixel order, chunking or device count.  The NumPy twin is
 * slicersim/ramps.py (_simulate_block_numpy); both use the same operations in
 * the same order and agree bit for bit.
 *
 * Build with -I<kernels dir> -DRNG_VW=N.  One work item = N pixels in explicit
 * vector lanes (PoCL does not vectorise the data-dependent loops of a scalar
 * kernel; GPUs use N = 1), taken from a list of pixel indices (padded to a
 * multiple of N by repeating the last one); data-dependent loops run while any
 * lane needs them, with per-lane masks.  Two kernels, one per path:
 *   macc_ramp_sparse  mu*(m+d) < sparse_max_group: a Poisson process seen group
 *           by group.  The window of group g (its m reads then its d dropped
 *           frames; the last group has m frames) collects K_g ~ Poisson(mu w)
 *           events (CDF inversion, one uniform), each at a uniform frame of the
 *           window; an event at position j adds 1 e- to the m - j reads j..m-1.
 *           Exact, and its cost does not grow with m+d: a dark pixel costs
 *           about one Philox block per group (half for the count and event 0,
 *           half for the read noise).
 *   macc_ramp_dense   a Poisson increment in every frame: inversion below 30 e-
 *           (the CDF of the pixel is tabulated once, same values as the
 *           recurrence), PTRS above; optional Gaussian approximation above
 *           gauss_min_mean, rounded and clipped at 0.
 * Counters (index, stream, draw) of ramp r, pixel p, stream 4r + purpose:
 *   kTC            (p, P_KTC, 0), cos branch
 *   read noise     (p | (g/2) << 32, P_READ, 0): cos for even g, sin for odd g
 *   sparse count   (p | (g/2) << 32, P_SPARSE, 0): even g words x (top 32 bits of the uniform),
 *                  y (event 0's frame, (y w) >> 32); odd g words z, w.  Where a CDF value lies
 *                  between the smallest and largest 52-bit uniform with those top bits, the low
 *                  bits are word x of (p | g << 32, P_SPARSE, 0xFFFFFFFF) (rare: the counts are
 *                  those of full 52-bit uniforms);
 *                  event k >= 1: (p | g << 32, P_SPARSE, 1 + (k-1)/2), words x,y (odd k) or z,w
 *   dense frame f  inversion (p | (f/2) << 32, P_POISSON, 0) words x,y (even f) or z,w;
 *                  Gaussian the same with draw 1, cos / sin; PTRS (p | f << 32,
 *                  P_POISSON + 2^31, attempt)
 * Charge is clipped at the full well; the m reads of a group are averaged and
 * carry read noise of variance ron^2/m (one Gaussian per group: both Box-Muller
 * outputs of a block serve groups 2k and 2k+1); the reset level adds kTC noise
 * once per ramp; output = rint(bias + gain*(kTC + mean)) clipped to [0, 65535]
 * as uint16; GROUPDQ bit 2 (SATURATED) from the first group whose charge
 * reached the full well or whose ADU hit the saturation level.
 */
#define RNG_INLINE inline __attribute__((always_inline))   /* PoCL: no out-of-line vector calls */
#include "philox.cl"

#define P_POISSON 0u
#define P_READ 1u
#define P_KTC 2u
#define P_SPARSE 3u
#define RAMP_PTRS_MIN_MEAN 30.0   /* physics/ramp.py RAMP_PTRS_MIN_MEAN */
#define RAMP_PTRS_MAX_ATTEMPTS 1000u
#define RAMP_INV_TABLE 32           /* tabulated CDF terms of the dense inversion */
#define RAMP_SPARSE_TABLE 3         /* tabulated CDF terms of a full sparse window */
#define RAMP_REFINE_DRAW 0xFFFFFFFFu /* draw of a sparse count's low 32 bits */

#define RAMP_INLINE inline __attribute__((always_inline))
#define RAMP_CONVERT_INT RNG_PASTE(convert_int, RNG_SUFFIX)
/* masks: comparisons and ! && || give 1/0 for scalars, -1/0 per lane for vectors */
#if RNG_VW == 1
typedef int ramp_mask;
#define RAMP_ANY(c) (c)
#define RAMP_FLAG(sat) ((uchar)((sat) ? 2 : 0))
#define RAMP_U16(x) ((ushort)(x))
#define RAMP_VSTORE(x, p) (*(p) = (x))
#else
typedef rng_rmask ramp_mask;
#define RAMP_ANY(c) ramp_any(c)
#define RAMP_FLAG(sat) RNG_PASTE(convert_uchar, RNG_SUFFIX)((sat) & 2)
#define RAMP_U16(x) RNG_PASTE(convert_ushort, RNG_SUFFIX)(x)
#define RAMP_VSTORE(x, p) RNG_PASTE(vstore, RNG_SUFFIX)((x), 0, (p))
#endif

#if RNG_VW > 1
/* any lane set: an OR tree (PoCL's any() extracts and branches lane by lane) */
RAMP_INLINE int ramp_any(const rng_rmask c)
{
#if RNG_VW == 16
    const RNG_PASTE(RNG_RMASK_NAME, 8) c8 = c.lo | c.hi;
#elif RNG_VW == 8
    const RNG_PASTE(RNG_RMASK_NAME, 8) c8 = c;
#endif
#if RNG_VW >= 8
    const RNG_PASTE(RNG_RMASK_NAME, 4) c4 = c8.lo | c8.hi;
#elif RNG_VW == 4
    const RNG_PASTE(RNG_RMASK_NAME, 4) c4 = c;
#endif
#if RNG_VW >= 4
    const RNG_PASTE(RNG_RMASK_NAME, 2) c2 = c4.lo | c4.hi;
#else
    const RNG_PASTE(RNG_RMASK_NAME, 2) c2 = c;
#endif
    return (c2.x | c2.y) < 0;
}
#endif

__constant real RAMP_LOG_FACTORIAL[10] = {
    0x0.0p+0, 0x0.0p+0, 0x1.62e42fefa39ecp-1, 0x1.cab0bfa2a2004p+0, 0x1.96ca77c922cf7p+1,
    0x1.326643c4479cap+2, 0x1.a51273acf01cbp+2, 0x1.10ce1f32dcc30p+3, 0x1.5358e82fcb70cp+3,
    0x1.99a8921a7f7cep+3};

/* Philox4x32-10 block of counter (index, stream, draw), any width (philox.cl, forced inline) */
RAMP_INLINE void ramp_block(const rng_ulong index, const uint stream, const uint draw, uint k0, uint k1,
                            rng_uint *pa, rng_uint *pb, rng_uint *pc, rng_uint *pd)
{
    philox_counter(index, stream, draw, pa, pb, pc, pd);
    philox4x32_10(pa, pb, pc, pd, k0, k1);
}

/* The CDF recurrences end where the CDF stops growing in float: a u above the rounded total (its tail
 * below the rounding, ~1e-7) would otherwise run on until p underflows (k ~ 50 at mu = 5).  Double:
 * unchanged (bit for bit the twin's loop, which ends at p = 0). */
#ifdef SINGLE
#define RAMP_CDF_GROWS(cdf, before) && ((cdf) > (before))
#else
#define RAMP_CDF_GROWS(cdf, before)
#endif

#define ramp_box_muller box_muller_lanes
#define ramp_exp rng_exp

#ifndef SINGLE
RAMP_INLINE rng_real ramp_log_factorial(const rng_real k)
{
    const rng_real x = k + 1.0;
    const rng_real r = 1.0 / x;
    const rng_real z = r * r;
    rng_real p = 0x1.a41a41a41a41ap-8;
    p = p * z - 0x1.f6ab0d9993c7dp-10;
    p = p * z + 0x1.b951e2b18ff23p-11;
    p = p * z - 0x1.3813813813814p-11;
    p = p * z + 0x1.a01a01a01a01ap-11;
    p = p * z - 0x1.6c16c16c16c17p-9;
    p = p * z + 0x1.5555555555555p-4;
    rng_real out = ((x - 0.5) * rng_log(x) - x) + (0x1.d67f1c864beb4p-1 + r * p);
    for (int t = 0; t < 10; ++t)
        out = RNG_SELECT(out, (rng_real)RAMP_LOG_FACTORIAL[t], k == (real)t);
    return out;
}
#endif

/* 52-bit integer of a uniform (as philox_u01) mapped to a frame position in [0, w):
 * (x * w) >> 52, exact integer arithmetic (w <= 4096), uniform to a relative 2^-40. */
RAMP_INLINE rng_real frame_position(const rng_uint hi, const rng_uint lo, const int w)
{
    const rng_ulong x = philox_x52(hi, lo);
    return rng_convert_real(rng_as_long((x * (ulong)w) >> 52));   /* < 2^12: signed conversion is exact */
}

/* Frame position in [0, w) from a 32-bit word: (x * w) >> 32 (exact integers; uniform for w a power
 * of two, else to a relative w 2^-32). */
RAMP_INLINE rng_real frame_position32(const rng_uint x, const int w)
{
    const rng_ulong x64 = (RNG_PASTE(convert_ulong, RNG_SUFFIX)(x >> 1) << 1)     /* no widening of a word */
                        | RNG_PASTE(convert_ulong, RNG_SUFFIX)(x & 1u);         /* with its top bit set */
    return rng_convert_real(rng_as_long((x64 * (ulong)w) >> 32));
}

/* K ~ Poisson by inversion of u (sparse windows): full windows start from the tabulated first terms
 * of Poisson(lam_full), the last window (m frames) from p_last = exp(-lam_last); then the recurrence
 * p_k = p_(k-1) lam / k (the twin's rng.inversion_search, bit for bit). */
RAMP_INLINE rng_real sparse_count(const rng_real u, const int last, const rng_real *tab_p, const rng_real *tab_cdf,
                                  const rng_real p_last, const rng_real lam_full, const rng_real lam_last)
{
    rng_real K = 0.0, p, cdf;
    ramp_mask act;
    if (!last) {
        act = (u > tab_cdf[0]) && (tab_p[0] > 0.0);
        K = RNG_SELECT(K, K + 1.0, act);
        for (int k = 1; k < RAMP_SPARSE_TABLE; ++k) {
            act = act && (u > tab_cdf[k]) && (tab_p[k] > 0.0);
            K = RNG_SELECT(K, K + 1.0, act);
        }
        p = tab_p[RAMP_SPARSE_TABLE - 1];
        cdf = tab_cdf[RAMP_SPARSE_TABLE - 1];
    } else {
        p = p_last;
        cdf = p_last;
        act = (u > cdf) && (p > 0.0);
        K = RNG_SELECT(K, K + 1.0, act);
    }
    const rng_real lam = last ? lam_last : lam_full;
    while (RAMP_ANY(act)) {
        p = RNG_SELECT(p, p * lam / K, act);
        const rng_real cdf_before = cdf;
        cdf = RNG_SELECT(cdf, cdf + p, act);
        act = act && (u > cdf) && (p > 0.0) RAMP_CDF_GROWS(cdf, cdf_before);
        K = RNG_SELECT(K, K + 1.0, act);
    }
    return K;
}

/* Position of event k >= 1 of group g: block (g << 32 | pixel, P_SPARSE, 1 + (k-1)/2),
 * words x,y for odd k, z,w for even k (event 0 uses words z,w of draw 0). */
RAMP_INLINE rng_real event_position(const int g, const int k, const int w, const rng_ulong pixv, const uint stream,
                                 const uint k0, const uint k1)
{
    rng_uint a, b, c, d;
    ramp_block(((ulong)g << 32) | pixv, stream, 1u + (uint)((k - 1) >> 1), k0, k1, &a, &b, &c, &d);
    return (k & 1) ? frame_position(a, b, w) : frame_position(c, d, w);
}

/* Sum over reads j of min(full_well, before + #{events at positions <= j}) for the lanes whose
 * window crosses the full well (rare; O(m K) Philox blocks). */
RAMP_INLINE rng_real clipped_read_sum(const rng_real before, const rng_real K, const rng_real pos0,
                                   const int g, const int w, const int m, const real full_well,
                                   const rng_ulong pixv, const uint stream, const uint k0, const uint k1)
{
    rng_real total = 0.0;
    for (int j = 0; j < m; ++j) {
        rng_real cj = RNG_SELECT((rng_real)0.0, (rng_real)1.0, (K > 0.0) && (pos0 <= (real)j));
        for (int k = 1; RAMP_ANY((real)k < K); ++k) {
            const rng_real pos = event_position(g, k, w, pixv, stream, k0, k1);
            cj = RNG_SELECT(cj, cj + 1.0, ((real)k < K) && (pos <= (real)j));
        }
        const rng_real charge = before + cj;
        total = total + RNG_SELECT(charge, (rng_real)full_well, charge >= full_well);
    }
    return total;
}

/* Read noise, rounding, clipping to uint16, flags; stores group g of the lanes. */
RAMP_INLINE void store_group(const int g, const rng_real sum, const rng_real z, const rng_real reset,
                        ramp_mask *sat, const int m, const real read_sigma, const real gain,
                        const real bias, const real saturation, __global ushort *restrict sci,
                        __global uchar *restrict gdq, const int write_dq, const uint *idx, const int contiguous,
                        const size_t npix)
{
    const rng_real mean = sum / (real)m + read_sigma * z;
    rng_real adu = rint(bias + gain * (reset + mean));
    adu = RNG_SELECT(adu, (rng_real)0.0, adu < 0.0);
    adu = RNG_SELECT(adu, (rng_real)65535.0, adu > 65535.0);
    *sat = *sat | (adu >= saturation);
    __global ushort *s = sci + (size_t)g * npix;
    __global uchar *q = gdq + (size_t)g * npix;
    if (contiguous) {
        RAMP_VSTORE(RAMP_U16(adu), s + idx[0]);
        if (write_dq)
            RAMP_VSTORE(RAMP_FLAG(*sat), q + idx[0]);
    } else {
        ushort su[RNG_VW];
        uchar sq[RNG_VW];
        RAMP_VSTORE(RAMP_U16(adu), su);
        RAMP_VSTORE(RAMP_FLAG(*sat), sq);
        for (int l = 0; l < RNG_VW; ++l)
            s[idx[l]] = su[l];
        if (write_dq)
            for (int l = 0; l < RNG_VW; ++l)
                q[idx[l]] = sq[l];
    }
}

/* lanes of work item t: mu (0 for dead pixels), pixel numbers, whether they are consecutive */
RAMP_INLINE int gather_lanes(__global const real *restrict mu_frame, __global const uint *restrict list,
                        const size_t t, const uint pixel0, uint *idx, rng_real *mu, rng_ulong *pixv)
{
    real m[RNG_VW];
    int contiguous = 1;
    for (int l = 0; l < RNG_VW; ++l) {
        idx[l] = list[t * RNG_VW + l];
        contiguous = contiguous && (idx[l] == idx[0] + (uint)l);
    }
    if (contiguous) {
#if RNG_VW == 1
        *mu = mu_frame[idx[0]];
#else
        *mu = RNG_PASTE(vload, RNG_SUFFIX)(0, mu_frame + idx[0]);
#endif
    } else {
        for (int l = 0; l < RNG_VW; ++l)
            m[l] = mu_frame[idx[l]];
#if RNG_VW == 1
        *mu = m[0];
#else
        *mu = RNG_PASTE(vload, RNG_SUFFIX)(0, m);
#endif
    }
    *pixv = (rng_ulong)((ulong)pixel0 + idx[0]) + RNG_LANES;
    if (!contiguous) {
        ulong p[RNG_VW];
        for (int l = 0; l < RNG_VW; ++l)
            p[l] = (ulong)pixel0 + idx[l];
#if RNG_VW == 1
        *pixv = p[0];
#else
        *pixv = RNG_PASTE(vload, RNG_SUFFIX)(0, p);
#endif
    }
    return contiguous;
}

RAMP_INLINE rng_real ktc_reset(const real ktc, const rng_ulong pixv, const uint sbase, const uint k0, const uint k1)
{
    if (!(ktc > 0.0))
        return 0.0;
    rng_uint a, b, c, d;
    rng_real unused;
    ramp_block(pixv, sbase + P_KTC, 0u, k0, k1, &a, &b, &c, &d);
    return ktc * ramp_box_muller(a, b, c, d, &unused);
}

#define RAMP_KERNEL_ARGS                                                                            \
    __global const real *restrict mu_frame, /* e-/frame, 0 for dead pixels */                     \
    __global const uint *restrict list, const uint nitems, /* RNG_VW pixel indices per item */      \
    __global ushort *restrict sci, __global uchar *restrict gdq, /* (n, npix) */                    \
    const uint npix, const uint pixel0, const uint ramp, const uint k0, const uint k1, const int n,  \
    const int m, const int d, const real read_sigma, const real gain, const real bias,        \
    const real ktc, const real full_well, const real saturation,                            \
    const int write_dq /* 0: GROUPDQ not wanted */ RAMP_EFFECT_ARGS

#ifdef RAMP_EFFECTS
#include "ramp_effects.cl"
#define RAMP_EFFECT_ARGS ,                                                                           \
    __global const uint *restrict dep_start, /* (npix + 1) CSR of each pixel's deposits */          \
    __global const int *restrict dep_frame, __global const real *restrict dep_e, /* frame, e- */      \
    __global const real *restrict nl_a2, __global const real *restrict nl_a3, const int use_nl,      \
    __global real *restrict gmean /* (n, npix) group mean of the read values [e-] */
#else
#define RAMP_EFFECT_ARGS
#endif

__kernel void macc_ramp_sparse(RAMP_KERNEL_ARGS)
{
    const size_t t = get_global_id(0);
    if (t >= nitems)
        return;
    uint idx[RNG_VW];
    rng_real mu;
    rng_ulong pixv;
    const int contiguous = gather_lanes(mu_frame, list, t, pixel0, idx, &mu, &pixv);
    const uint sbase = 4u * ramp, stream = sbase + P_SPARSE;
    const int W = m + d;
    const rng_real reset = ktc_reset(ktc, pixv, sbase, k0, k1);
    /* CDF of Poisson(mu W) for full windows: first terms tabulated (the recurrence's values) */
    const rng_real lam_full = mu * (real)W, lam_last = mu * (real)m;
    rng_real tab_p[RAMP_SPARSE_TABLE], tab_cdf[RAMP_SPARSE_TABLE];
    tab_p[0] = ramp_exp(-lam_full);
    tab_cdf[0] = tab_p[0];
    for (int k = 1; k < RAMP_SPARSE_TABLE; ++k) {
        tab_p[k] = tab_p[k - 1] * lam_full / (real)k;
        tab_cdf[k] = tab_cdf[k - 1] + tab_p[k];
    }
    const rng_real p_last = ramp_exp(-lam_last);
    const int any_charge = RAMP_ANY(mu > 0.0);
    rng_real before = 0.0;                                     /* clipped charge before the window */
    ramp_mask sat = (ramp_mask)0;
    rng_real z_even = 0.0, z_odd = 0.0;
    rng_uint pa = 0u, pb = 0u, pc = 0u, pd = 0u;               /* block of the window pair (g/2) */
#ifdef RAMP_EFFECTS
    uint dp[RNG_VW], de[RNG_VW], ws[RNG_VW];
    rng_real next_dep = deposit_cursor(dep_start, dep_frame, idx, dp, de);
    const rng_real a2 = use_nl ? load_lanes(nl_a2, idx) : 0.0, a3 = use_nl ? load_lanes(nl_a3, idx) : 0.0;
    int f0 = 0;                                                  /* first frame of the window */
#endif
    for (int g = 0; g < n; ++g) {
        const int last = g == n - 1;
        const int w = last ? m : W;
        rng_uint a, b, c, e;
#ifndef RAMP_EFFECTS
        if ((g & 1) == 0) {
            ramp_block(((ulong)(g >> 1) << 32) | pixv, sbase + P_READ, 0u, k0, k1, &a, &b, &c, &e);
            z_even = ramp_box_muller(a, b, c, e, &z_odd);
        }
#endif
        /* K ~ Poisson(mu w) by inversion of a uniform whose top 32 bits are word x (even g) or z (odd g)
         * of the pair's block; words y / w place event 0.  The count is that of every 52-bit uniform
         * with those top bits unless a CDF value falls between them (then the low bits are drawn). */
        if (any_charge && (g & 1) == 0)
            ramp_block(((ulong)(g >> 1) << 32) | pixv, stream, 0u, k0, k1, &pa, &pb, &pc, &pd);
        const rng_uint uh = (g & 1) ? pc : pa, ph = (g & 1) ? pd : pb;
        rng_real K = 0.0;
        if (any_charge) {
            K = sparse_count(philox_u01(uh, (rng_uint)0u), last, tab_p, tab_cdf, p_last, lam_full, lam_last);
#ifdef RAMP_REFINE_ALWAYS                /* tests: every lane draws its low bits (same counts) */
            const ramp_mask amb = mu == mu;
#else
            const ramp_mask amb = sparse_count(philox_u01(uh, (rng_uint)0xFFFFFFFFu), last, tab_p, tab_cdf, p_last,
                                               lam_full, lam_last) > K;
#endif
            if (RAMP_ANY(amb)) {
                ramp_block(((ulong)g << 32) | pixv, stream, RAMP_REFINE_DRAW, k0, k1, &a, &b, &c, &e);
                K = RNG_SELECT(K, sparse_count(philox_u01(uh, a), last, tab_p, tab_cdf, p_last, lam_full, lam_last),
                               amb);
            }
        }
        /* reads that see each event: m - position */
        const rng_real pos0 = frame_position32(ph, w);
        rng_real seen = RNG_SELECT((rng_real)0.0, (real)m - pos0, (K > 0.0) && (pos0 < (real)m));
#ifdef RAMP_EFFECTS
        rng_real posk[RAMP_POS_MAX];
#endif
        for (int k = 1; RAMP_ANY((real)k < K); ++k) {
            if (k & 1)                           /* events 2i+1 and 2i+2 share draw 1 + i */
                ramp_block(((ulong)g << 32) | pixv, stream, 1u + (uint)((k - 1) >> 1), k0, k1, &a, &b, &c, &e);
            const rng_real pos = (k & 1) ? frame_position(a, b, w) : frame_position(c, e, w);
            seen = RNG_SELECT(seen, seen + ((real)m - pos), ((real)k < K) && (pos < (real)m));
#ifdef RAMP_EFFECTS
            if (k < RAMP_POS_MAX)
                posk[k] = pos;
#endif
        }
#ifdef RAMP_EFFECTS
        rng_real dsum = 0.0;                   /* deposits of the window */
        ramp_mask has_dep = (ramp_mask)0;
        const int any_dep = RAMP_ANY(next_dep < (real)(f0 + w));
        if (any_dep) {
            dsum = take_deposits(dep_frame, dep_e, f0 + w, dp, de, ws, &next_dep);
            real hd[RNG_VW];
            for (int l = 0; l < RNG_VW; ++l)
                hd[l] = dp[l] > ws[l] ? 1.0 : 0.0;
            has_dep = lanes_from(hd) > 0.0;
        }
        const rng_real total = (before + K) + dsum;
#else
        const rng_real total = before + K;
#endif
        rng_real sum = (real)m * before + seen;
        const ramp_mask over = total > full_well;
        if (RAMP_ANY(over))
            sum = RNG_SELECT(sum, clipped_read_sum(before, K, pos0, g, w, m, full_well, pixv, stream, k0, k1),
                             over);
#ifdef RAMP_EFFECTS
        if (use_nl || any_dep) {                 /* read by read where a deposit or R(Q) needs it */
            const rng_real by_read = window_read_sum(before, K, pos0, posk, g, w, m, f0, full_well, pixv, stream,
                                                       k0, k1, any_dep, ws, dp, dep_frame, dep_e, a2, a3, use_nl);
            sum = use_nl ? by_read : RNG_SELECT(sum, by_read, has_dep);
        }
        f0 += w;
#endif
        const ramp_mask full = total >= full_well;
        sat = sat || full;
        before = RNG_SELECT(total, (rng_real)full_well, full);
#ifdef RAMP_EFFECTS
        store_mean(g, sum, sat, m, gmean, gdq, idx, contiguous, npix);
#else
        store_group(g, sum, (g & 1) ? z_odd : z_even, reset, &sat, m, read_sigma, gain, bias, saturation,
                    sci, gdq, write_dq, idx, contiguous, npix);
#endif
    }
}

/* PTRS (Hoermann 1993) for the lanes in `lanes`, attempt a keyed by draw a (as noise.cl). */
RAMP_INLINE rng_real ptrs_lanes(const rng_real mu, const ramp_mask lanes, const rng_real log_mu,
                             const rng_real a, const rng_real b, const rng_real log_inv_alpha,
                             const rng_real vr, const rng_ulong index, const uint stream, const uint k0,
                             const uint k1)
{
    rng_real res = 0.0;
    ramp_mask todo = lanes;
    RNG_PTRS_SPLIT(mu)
    for (uint attempt = 0u; attempt < RAMP_PTRS_MAX_ATTEMPTS && RAMP_ANY(todo); ++attempt) {
        rng_uint wa, wb, wc, wd;
        ramp_block(index, stream, attempt, k0, k1, &wa, &wb, &wc, &wd);
        const rng_real U = philox_u01(wa, wb) - 0.5;
        const rng_real V = philox_u01(wc, wd);
        const rng_real us = 0.5 - fabs(U);
        const rng_real k = RNG_PTRS_K(a, b, us, U, mu);
        ramp_mask accept = (us >= 0.07) && (V <= vr);
        const ramp_mask test = todo && !accept && !((k < 0.0) || ((us < 0.013) && (V > us)));
        if (RAMP_ANY(test)) {
            const rng_real lhs = (rng_log(V) + log_inv_alpha) - rng_log(a / (us * us) + b);
#ifdef SINGLE
            const rng_real rhs = rng_log_poisson(fmax(k, 0.0f), mu, log_mu);
#else
            const rng_real rhs = (k * log_mu - mu) - ramp_log_factorial(fmax(k, 0.0));
#endif
            accept = accept || (test && (lhs <= rhs));
        }
        accept = accept && todo;
        res = RNG_SELECT(res, k, accept);
        todo = todo && !accept;
    }
    return RNG_SELECT(res, (rng_real)NAN, todo);
}

__kernel void macc_ramp_dense(RAMP_KERNEL_ARGS, const real gauss_min_mean)
{
    const size_t t = get_global_id(0);
    if (t >= nitems)
        return;
    uint idx[RNG_VW];
    rng_real mu;
    rng_ulong pixv;
    const int contiguous = gather_lanes(mu_frame, list, t, pixel0, idx, &mu, &pixv);
    const uint sbase = 4u * ramp, stream = sbase + P_POISSON;
    const rng_real reset = ktc_reset(ktc, pixv, sbase, k0, k1);
    const ramp_mask gauss = mu >= gauss_min_mean;
    const ramp_mask ptrs = !gauss && (mu >= RAMP_PTRS_MIN_MEAN);
    const ramp_mask inv = !gauss && !ptrs;
    const int any_gauss = RAMP_ANY(gauss), any_ptrs = RAMP_ANY(ptrs), any_inv = RAMP_ANY(inv);
    const rng_real sqrt_mu = sqrt(mu);
    /* inversion: CDF terms 0..RAMP_INV_TABLE-1 (a term with p = 0 ends the search: +inf) */
    rng_real tab[RAMP_INV_TABLE];
    rng_real p_end = ramp_exp(-mu), cdf_end = p_end;
    if (any_inv) {
        tab[0] = RNG_SELECT(cdf_end, (rng_real)INFINITY, !(p_end > 0.0));
        for (int k = 1; k < RAMP_INV_TABLE; ++k) {
            p_end = p_end * mu / (real)k;
            cdf_end = cdf_end + p_end;
            tab[k] = RNG_SELECT(cdf_end, (rng_real)INFINITY, !(p_end > 0.0));
        }
    }
    /* PTRS constants */
    const rng_real log_mu = rng_log(mu);
    const rng_real pb = 0.931 + 2.53 * sqrt_mu;
    const rng_real pa = -0.059 + 0.02483 * pb;
    const rng_real log_inv_alpha = rng_log(1.1239 + 1.1328 / (pb - 3.4));
    const rng_real vr = 0.9277 - 3.6224 / (pb - 2.0);

    rng_real charge = 0.0;
    ramp_mask sat = (ramp_mask)0;
    int frame = 0;
    rng_uint wa = 0, wb = 0, wc = 0, wd = 0;
    rng_real zf_even = 0.0, zf_odd = 0.0, z_even = 0.0, z_odd = 0.0;
#ifdef RAMP_EFFECTS
    uint dp[RNG_VW], de[RNG_VW], ws[RNG_VW];
    rng_real next_dep = deposit_cursor(dep_start, dep_frame, idx, dp, de);
    const rng_real a2 = use_nl ? load_lanes(nl_a2, idx) : 0.0, a3 = use_nl ? load_lanes(nl_a3, idx) : 0.0;
#endif
    for (int g = 0; g < n; ++g) {
        rng_real sum = 0.0;
        const int w = (g == n - 1) ? m : m + d;
        for (int j = 0; j < w; ++j, ++frame) {
            rng_real inc = 0.0;
            const rng_ulong pair = ((ulong)(frame >> 1) << 32) | pixv;
            if (any_inv) {
                if ((frame & 1) == 0)
                    ramp_block(pair, stream, 0u, k0, k1, &wa, &wb, &wc, &wd);
                const rng_real u = (frame & 1) ? philox_u01(wc, wd) : philox_u01(wa, wb);
                rng_real K = 0.0;
                ramp_mask act = inv;
                for (int k = 0; k < RAMP_INV_TABLE && RAMP_ANY(act); ++k) {
                    act = act && (u > tab[k]);
                    K = RNG_SELECT(K, K + 1.0, act);
                }
                if (RAMP_ANY(act)) {              /* beyond the table: the recurrence goes on */
                    rng_real p = p_end, cdf = cdf_end;
                    while (RAMP_ANY(act)) {
                        p = RNG_SELECT(p, p * mu / K, act);
                        const rng_real cdf_before = cdf;
                        cdf = RNG_SELECT(cdf, cdf + p, act);
                        act = act && (u > cdf) && (p > 0.0) RAMP_CDF_GROWS(cdf, cdf_before);
                        K = RNG_SELECT(K, K + 1.0, act);
                    }
                }
                inc = K;
            }
            if (any_gauss) {
                if ((frame & 1) == 0) {
                    rng_uint a, b, c, e;
                    ramp_block(pair, stream, 1u, k0, k1, &a, &b, &c, &e);
                    zf_even = ramp_box_muller(a, b, c, e, &zf_odd);
                }
                const rng_real k = rint(mu + sqrt_mu * ((frame & 1) ? zf_odd : zf_even));
                inc = RNG_SELECT(inc, RNG_SELECT(k, (rng_real)0.0, !(k > 0.0)), gauss);
            }
            if (any_ptrs)
                inc = RNG_SELECT(inc, ptrs_lanes(mu, ptrs, log_mu, pa, pb, log_inv_alpha, vr,
                                                 ((ulong)frame << 32) | pixv, stream + 0x80000000u, k0, k1),
                                 ptrs);
            charge = charge + inc;
#ifdef RAMP_EFFECTS
            if (RAMP_ANY(next_dep == (real)frame))
                charge = charge + take_deposits(dep_frame, dep_e, frame + 1, dp, de, ws, &next_dep);
#endif
            const ramp_mask full = charge >= full_well;
            charge = RNG_SELECT(charge, (rng_real)full_well, full);
            sat = sat || full;
#ifdef RAMP_EFFECTS
            if (j < m)
                sum = sum + (use_nl ? nl_read(charge, a2, a3) : charge);
#else
            if (j < m)
                sum = sum + charge;
#endif
        }
#ifdef RAMP_EFFECTS
        store_mean(g, sum, sat, m, gmean, gdq, idx, contiguous, npix);
#else
        if ((g & 1) == 0) {
            rng_uint a, b, c, e;
            ramp_block(((ulong)(g >> 1) << 32) | pixv, sbase + P_READ, 0u, k0, k1, &a, &b, &c, &e);
            z_even = ramp_box_muller(a, b, c, e, &z_odd);
        }
        store_group(g, sum, (g & 1) ? z_odd : z_even, reset, &sat, m, read_sigma, gain, bias, saturation,
                    sci, gdq, write_dq, idx, contiguous, npix);
#endif
    }
}
