/*
 * Point-source PSF kernels: fraction of a point source's flux in each cell.
 *
 * Cell coordinates are in cell units relative to the field centre (cell
 * edges X_k = k - nx/2, Y_j = j - ny/2).  Flux outside the field is lost.
 * Precision: real = real by default; -DSINGLE builds every kernel in float
 * (slicersim.backends.opencl.precision_options; tolerances in slicersim/backends/psf.py).
 * No fast-math build options.
 *
 * gaussian_cell_fractions, outer_product
 *                   Gaussian integrated exactly over each cell (erf product).
 * airy_rows         Airy intensity of an annular pupil at the sub-samples fused
 *                   with the banded contraction along y (jitter + binning);
 *                   equal |dx| (mirror blocks) and |dy| (shared rows) are
 *                   evaluated once; unobscured pupils use jinc_squared(v^2);
 *                   airy_subsamples + blur_bin_rows do the same in two passes
 *                   when the jitter margin is too wide for registers.
 * blur_bin_cols     banded contraction along x: jitter and blur + binning
 *                   (mirrored output blocks stored reversed).
 * bessel_j1_values  J1(x) with the approximation below (for tests).
 *
 * J1: OpenCL C has no Bessel functions.  2 J1(v)/v is evaluated as
 *   v < 12 : its power series in t = v^2/4, sum_k (-1)^k t^k / (k! (k+1)!),
 *            28 terms (truncation < 1e-17; rounding ~1e-13 at v = 12);
 *   v >= 12: Hankel's asymptotic expansion J1(v) = sqrt(2/(pi v))
 *            [P(v) cos(v - 3pi/4) - Q(v) sin(v - 3pi/4)] with 10 terms each
 *            of P and Q (truncation ~1.6e-12 at v = 12, less beyond);
 *            sin and cos by sin_cos() below.
 * Measured max |J1 - scipy.special.j1| 1.6e-12 (at v = 12) on [0, 1e6] (tests/test_psf.py).
 *
 * Vector width VW (1, 2, 4, 8, 16; -DVW=...): in the Airy and contraction
 * kernels each work item handles VW consecutive x sub-samples (or output
 * cells) with explicit vector types (PoCL then vectorises on CPUs; GPUs use
 * VW = 1).  NA (-DNA=2 m_y + 1) sizes airy_rows' register accumulators.
 */

#include "vector_types.cl"

#ifndef JR
#define JR 1
#endif

#ifdef SINGLE
#define JINC_SWITCH 7.0      /* float: the series' cancellation costs ~1e-6 of the peak near v = 12 */
#else
#define JINC_SWITCH 12.0
#endif

/* (-1)^k / (k! (k+1)!), k = 0..27 */
__constant real JINC_SERIES[28] = {
    1.0, -0.5, 0.08333333333333333, -0.006944444444444444, 0.00034722222222222224,
    -1.1574074074074073e-05, 2.755731922398589e-07, -4.920949861426052e-09,
    6.834652585313961e-11, -7.594058428126623e-13, 6.903689480115112e-15,
    -5.230067787965994e-17, 3.352607556388458e-19, -1.842092063949702e-21,
    8.771866971189057e-24, -3.654944571328774e-26, 1.3437296218120491e-28,
    -4.391273273895586e-31, 1.2839980333028028e-33, -3.3789421929021126e-36,
    8.045100459290744e-39, -1.7413637357772174e-41, 3.4414303078601135e-44,
    -6.234475195398757e-47, 1.0390791992331261e-49, -1.5985833834355786e-52,
    2.2771843068882885e-55, -3.0121485540850376e-58};

/* Hankel expansion of J1 (mu = 4): P = sum_m P_m v^-2m, Q = sum_m Q_m v^-(2m+1) */
__constant real HANKEL_P[10] = {
    1.0, 0.1171875, -0.144195556640625, 0.6765925884246826, -6.883914268109947,
    121.59789187653587, -3302.2722944808525, 127641.2726461746, -6656367.718817687,
    450278600.3050392};
__constant real HANKEL_Q[10] = {
    0.375, -0.1025390625, 0.2775764465332031, -1.993531733751297, 27.248827311268542,
    -603.8440767050702, 19718.37591223663, -890297.8767070678, 53104110.10968522,
    -4043620325.1077538};

/* 2 J1(v)/v for v < JINC_SWITCH (power series) */
inline realv jinc_series(const realv v)
{
    const realv t = 0.25 * v * v;
    realv s = (realv)(JINC_SERIES[27]);
    for (int k = 26; k >= 0; --k)
        s = fma(s, t, (realv)(JINC_SERIES[k]));
    return s;
}

/*
 * sin and cos of x (|x| < 2^50), vectorised: x = n pi/2 + r, |r| <= pi/4,
 * with n and n mod 4 read from the bits of 2x/pi + 1.5 2^52 (PoCL lowers
 * rint/floor on real vectors to scalar calls: this alone made the Airy
 * kernel 1.75x faster, and its built-in sincos was no faster than the
 * polynomials), a two-constant Cody-Waite reduction through fma, Taylor
 * polynomials of sin r (9 terms) and cos r (10 terms; truncation < 1e-17).
 */
#ifdef SINGLE
#define PIO2_HI 1.5707963705062866            /* (float)(pi / 2) */
#define PIO2_LO -4.371139000186243e-08        /* pi / 2 - PIO2_HI */
#define ROUND_MAGIC 12582912.0                /* 1.5 2^23: rint through the float bits */
#else
#define PIO2_HI 1.5707963267948966
#define PIO2_LO 6.123233995736766e-17
#define ROUND_MAGIC 6755399441055744.0        /* 1.5 2^52 */
#endif
__constant real SIN_TAYLOR[9] = {
    1.0, -0.16666666666666666, 0.008333333333333333, -0.0001984126984126984,
    2.7557319223985893e-06, -2.505210838544172e-08, 1.6059043836821613e-10,
    -7.647163731819816e-13, 2.8114572543455206e-15};
__constant real COS_TAYLOR[10] = {
    1.0, -0.5, 0.041666666666666664, -0.001388888888888889, 2.48015873015873e-05,
    -2.755731922398589e-07, 2.08767569878681e-09, -1.1470745597729725e-11,
    4.779477332387385e-14, -1.5619206968586225e-16};

inline realv sin_cos(const realv x, realv *cosx)
{
    /* n = rint(2x/pi) and n mod 4 from the bits of 2x/pi + 1.5 2^52 (|x| < 2^50;
       float: 1.5 2^23, |x| < 2^21) */
    const realv t = fma(x, (realv)(0.6366197723675814), (realv)(ROUND_MAGIC));
    const longv q = AS_LONGV(t) & 3;
    const realv n = t - ROUND_MAGIC;
    const realv r = fma(-n, (realv)(PIO2_LO), fma(-n, (realv)(PIO2_HI), x));
    const realv r2 = r * r;
    realv sp = (realv)(SIN_TAYLOR[8]);
    for (int k = 7; k >= 0; --k)
        sp = fma(sp, r2, (realv)(SIN_TAYLOR[k]));
    sp *= r;
    realv cp = (realv)(COS_TAYLOR[9]);
    for (int k = 8; k >= 0; --k)
        cp = fma(cp, r2, (realv)(COS_TAYLOR[k]));
    /* q = 0: (s, c); 1: (c, -s); 2: (-s, -c); 3: (-c, s) */
    /* comparisons (not bare ints): vector ?: selects on the sign bit */
    const realv s1 = ((q & 1) != 0) ? cp : sp;
    const realv c1 = ((q & 1) != 0) ? sp : cp;
    *cosx = (q == 1 || q == 2) ? -c1 : c1;
    return (q >= 2) ? -s1 : s1;
}

/*
 * Hankel expansion for v >= JINC_SWITCH (v is clamped to the switch):
 * returns J1(v) and, in *jinc_out, 2 J1(v)/v.  No division: rsqrt only.
 */
inline realv j1_hankel(realv v, realv *jinc_out)
{
    v = fmax(v, (realv)(JINC_SWITCH));
    const realv rs = rsqrt(v);
    const realv rv = rs * rs;
    const realv z = rv * rv;
    realv p = (realv)(HANKEL_P[9]);
    realv q = (realv)(HANKEL_Q[9]);
    for (int m = 8; m >= 0; --m) {
        p = fma(p, z, (realv)(HANKEL_P[m]));
        q = fma(q, z, (realv)(HANKEL_Q[m]));
    }
    realv c;
    const realv s = sin_cos(v - 2.356194490192345, &c);          /* 3 pi / 4 */
    const realv j1v = 0.7978845608028654 * rs * (p * c - q * rv * s); /* sqrt(2/pi) */
    *jinc_out = 2.0 * rv * j1v;
    return j1v;
}

/* 2 J1(v)/v, v >= 0 (1 at v = 0); each branch only evaluated when a lane needs it */
inline realv jinc(const realv v)
{
    if (!ANY(v >= JINC_SWITCH))
        return jinc_series(v);
    realv big;
    j1_hankel(v, &big);
    if (ANY(v < JINC_SWITCH))
        return (v < JINC_SWITCH) ? jinc_series(v) : big;
    return big;
}

/*
 * (2 J1(v)/v)^2 from v^2 (unobscured pupil): the series needs only v^2, and
 * for v >= JINC_SWITCH (2 J1(v)/v)^2 = 8 / (pi v^3) [P cos(v - 3pi/4) - Q sin(...) / v]^2
 * needs one sqrt and one division (no rsqrt): a sqrt costs as much as a
 * good part of the rest of a sub-sample on CPUs.
 */
inline realv jinc_series_t(const realv t)      /* 2 J1(v)/v, t = v^2 / 4 */
{
    realv s = (realv)(JINC_SERIES[27]);
    for (int k = 26; k >= 0; --k)
        s = fma(s, t, (realv)(JINC_SERIES[k]));
    return s;
}

inline realv jinc_squared_hankel(const realv v2)
{
    const realv v = sqrt(fmax(v2, (realv)(JINC_SWITCH * JINC_SWITCH)));
    const realv rv = 1.0 / v;
    const realv z = rv * rv;
    realv p = (realv)(HANKEL_P[9]);
    realv q = (realv)(HANKEL_Q[9]);
    for (int m = 8; m >= 0; --m) {
        p = fma(p, z, (realv)(HANKEL_P[m]));
        q = fma(q, z, (realv)(HANKEL_Q[m]));
    }
    realv c;
    const realv s = sin_cos(v - 2.356194490192345, &c);          /* 3 pi / 4 */
    const realv h = p * c - q * rv * s;
    return 2.5464790894703255 * (z * rv) * (h * h);                /* 8 / pi */
}

inline realv jinc_squared(const realv v2)
{
    const real sw2 = JINC_SWITCH * JINC_SWITCH;
    if (!ANY(v2 >= sw2)) {
        const realv g = jinc_series_t(0.25 * v2);
        return g * g;
    }
    const realv big = jinc_squared_hankel(v2);
    if (ANY(v2 < sw2)) {
        const realv g = jinc_series_t(0.25 * v2);
        return (v2 < sw2) ? g * g : big;
    }
    return big;
}

__kernel void bessel_j1_values(__global const real *restrict x, __global real *restrict out)
{
    const int i = get_global_id(0);
    const realv v = VLOAD(i, x);
    realv jv;
    const realv r = (v < JINC_SWITCH) ? 0.5 * v * jinc_series(v) : j1_hankel(v, &jv);
    VSTORE(r, i, out);
}

/*
 * Airy intensity per unit cell area at every sub-sample of a window:
 *   S[l, v, u] = pref[l] * g(kwave[l] * sqrt(dx[u]^2 + dy[v]^2))^2
 *   g(w) = (jinc(w) - eps^2 jinc(eps w)) / (1 - eps^2)
 * dx, dy: sub-sample offsets from the source [cells]; kwave = pi D s / lambda
 * [rad per cell]; pref = (1 - eps^2) kwave^2 / (4 pi) so that the intensity
 * integrates to 1 over the plane.  Global size (nxs / VW, nys, nl); the row
 * stride nxs is a multiple of VW (the host pads dx).
 */
__kernel void airy_subsamples(
    __global const real *restrict dx,     /* (nxs,) */
    __global const real *restrict dy,     /* (nys,) */
    __global const real *restrict kwave,  /* (nl,)  */
    __global const real *restrict pref,   /* (nl,)  */
    const real eps,
    const int nxs,
    __global real *restrict S)            /* (nl, nys, nxs) */
{
    const int uv = get_global_id(0);
    const int v = get_global_id(1);
    const int l = get_global_id(2);
    const int nys = get_global_size(1);
    const real k = kwave[l];
    const real y = dy[v];
    const realv x = VLOAD(uv, dx);
    const realv w = k * sqrt(fma(x, x, (realv)(y * y)));
    realv g = jinc(w);
    if (eps > 0.0) {
        const real e2 = eps * eps;
        g = (g - e2 * jinc(eps * w)) / (1.0 - e2);
    }
    const size_t row = ((size_t)l * (size_t)nys + (size_t)v) * (size_t)nxs;
    VSTORE(pref[l] * g * g, 0, S + row + (size_t)uv * VW);
}

#if VW == 1
#define REVERSE(v) (v)
#elif VW == 2
#define REVERSE(v) ((v).s10)
#elif VW == 4
#define REVERSE(v) ((v).s3210)
#elif VW == 8
#define REVERSE(v) ((v).s76543210)
#else
#define REVERSE(v) ((v).sfedcba9876543210)
#endif

#ifdef NA
/*
 * airy_subsamples fused with blur_bin_rows (S never goes to memory):
 *   U[l, j, u] = sum_{a < NA} sum_{b < o} ky[o a + b] S(l, row o (j + a) + b, u)
 * Each work item walks down one block of VW columns; acc[a] accumulates output
 * row c - a while window cell row c is processed (NA = 2 m_y + 1 is a build
 * option, so the accumulators stay in registers).  Global (nw, nl).
 *
 * The Airy intensity depends on |dx| and |dy| only, so equal offsets are
 * evaluated once (a source centred in a symmetric window: 4x fewer J1):
 *   x: xblocks[2 w] is the block (VW columns) of work item w, xblocks[2 w + 1]
 *      the block holding the same |dx| in reverse lane order (or -1): U of
 *      the mirror block is U of the block reversed (the row contraction is
 *      the same linear map of the same samples).
 *   y: yslot[i] = -1: evaluate row i; 2 s: evaluate and keep it in slot s of
 *      the scratch T; 2 s + 1: row i has the |dy| of slot s, read it back
 *      (rows are walked in order, so a slot is written before it is read).
 */
__kernel void airy_rows(
    __global const real *restrict dx,     /* (nxs,) */
    __global const real *restrict dy,     /* (o * (nyo + NA - 1),) */
    __global const real *restrict kwave,  /* (nl,) */
    __global const real *restrict pref,   /* (nl,) */
    __global const real *restrict ky,     /* (o * NA,) */
    __global const int *restrict xblocks,   /* (nw, 2) */
    __global const int *restrict yslot,     /* (o * (nyo + NA - 1),) */
    const real eps,
    const int o,
    const int nyo,
    const int nxs,
    const int nslot,
    __global real *restrict T,            /* scratch (nl, nslot, nw VW) */
    __global real *restrict U)            /* (nl, nyo, nxs) */
{
    const int w = get_global_id(0);
    const int l = get_global_id(1);
    const int nw = get_global_size(0);
    const int blk = xblocks[2 * w];
    const int mir = xblocks[2 * w + 1];
    const real k = kwave[l];
    const real pf = pref[l];
    const real e2 = eps * eps;
    const real k2 = k * k;
    const realv x = VLOAD(blk, dx);
    const realv x2 = x * x;
    realv acc[NA];
    for (int a = 0; a < NA; ++a)
        acc[a] = (realv)(0.0);
    __global real *dst = U + (size_t)l * (size_t)nyo * (size_t)nxs;
    __global real *scr = T + ((size_t)l * (size_t)nslot * (size_t)nw + (size_t)w) * VW;
    const size_t slot_stride = (size_t)nw * VW;
    const int ncy = nyo + NA - 1;
    for (int c = 0; c < ncy; ++c) {
        for (int b = 0; b < o; ++b) {
            const int code = yslot[c * o + b];
            realv sv;
            if (code >= 0 && (code & 1)) {
                sv = VLOAD(0, scr + (size_t)(code >> 1) * slot_stride);
            } else {
                const real y = dy[c * o + b];
                if (eps > 0.0) {
                    const realv wv = k * sqrt(x2 + y * y);
                    const realv g = (jinc(wv) - e2 * jinc(eps * wv)) / (1.0 - e2);
                    sv = pf * g * g;
                } else {
                    sv = pf * jinc_squared(k2 * (x2 + y * y));
                }
                if (code >= 0)
                    VSTORE(sv, 0, scr + (size_t)(code >> 1) * slot_stride);
            }
#pragma unroll
            for (int a = 0; a < NA; ++a)
                acc[a] = fma((realv)(ky[o * a + b]), sv, acc[a]);
        }
        const int j = c - (NA - 1);           /* output row now complete */
        if (j >= 0) {
            VSTORE(acc[NA - 1], 0, dst + (size_t)j * (size_t)nxs + (size_t)blk * VW);
            if (mir >= 0)
                VSTORE(REVERSE(acc[NA - 1]), 0, dst + (size_t)j * (size_t)nxs + (size_t)mir * VW);
        }
#pragma unroll
        for (int a = NA - 1; a > 0; --a)
            acc[a] = acc[a - 1];
        acc[0] = (realv)(0.0);
    }
}
#endif

/*
 * U[l, j, u] = sum_{e < wy} ky[e] S[l, o j + e, u]   (rows of S: nys)
 * ky holds the fraction of a sub-sample's light that the Gaussian jitter puts
 * into the output row, times the quadrature weight.  Global (nxs / VW, nyo, nl).
 */
__kernel void blur_bin_rows(
    __global const real *restrict S,      /* (nl, nys, nxs) */
    __global const real *restrict ky,     /* (wy,) */
    const int wy,
    const int o,
    const int nys,
    const int nxs,
    __global real *restrict U)            /* (nl, nyo, nxs) */
{
    const int uv = get_global_id(0);
    const int j = get_global_id(1);
    const int l = get_global_id(2);
    const int nyo = get_global_size(1);
    __global const real *src = S + ((size_t)l * (size_t)nys + (size_t)(o * j)) * (size_t)nxs
                                 + (size_t)uv * VW;
    realv acc = (realv)(0.0);
    for (int e = 0; e < wy; ++e)
        acc = fma((realv)(ky[e]), VLOAD(0, src + (size_t)e * (size_t)nxs), acc);
    VSTORE(acc, 0, U + ((size_t)l * (size_t)nyo + (size_t)j) * (size_t)nxs + (size_t)uv * VW);
}

/*
 * Along x the sub-samples of a row are stored de-interleaved: the sub-sample
 * at node b of window cell c sits at b * ncx + c.  Then
 *   P[l, j, k] = sum_{b < o} sum_{a < na} kx[o a + b] U[l, j, b ncx + xoff + k + a]
 * reads contiguous vectors for VW consecutive output cells k.
 * oblocks[2 w] is the block (VW output cells) of work item w, oblocks[2 w + 1]
 * the block whose cells mirror it in reverse order about the source (equal
 * inputs, symmetric taps; the host checks both) or -1: it gets the values
 * reversed.  Blocks count padded cells (nxo rounded up to VW, pad of them
 * before the first output cell); padding is not stored.  Global (nwo, ceil(nyo / JR), nl);
 * plane l of the launch is stored at plane lout + l of P (a whole cube in one buffer).
 * Each work item does JR rows (-DJR=..., default 1): a lone 63-term FMA chain is
 * latency-bound on CPUs; JR independent chains (same summation order per row, so
 * bit-identical results): JR = 4 is 2-2.5x faster on PoCL with U in cache, ~1.3x
 * inside get_cube.
 */
/* VW values for cells [k, k + VW) of a row of n cells; lanes outside [0, n) are dropped */
inline void store_cells(const realv v, const int k, const int n, __global real *row)
{
    if (k >= 0 && k + VW <= n) {
        VSTORE(v, 0, row + k);
    } else {
        real lanes[VW];
        VSTORE(v, 0, lanes);
        for (int i = 0; i < VW; ++i)
            if (k + i >= 0 && k + i < n)
                row[k + i] = lanes[i];
    }
}

__kernel void blur_bin_cols(
    __global const real *restrict U,      /* (nl, nyo, nxs), nxs = o * ncx */
    __global const real *restrict kx,     /* (o * na,) */
    __global const int *restrict oblocks,   /* (nwo, 2) */
    const int na,                           /* 2 m + 1 cells of taps */
    const int o,
    const int ncx,
    const int xoff,
    const int pad,                          /* padded output cell pad is output cell 0 */
    const int nxo,
    const int lout,                         /* first output plane of the launch */
    const int nyo,
    __global real *restrict P)            /* (lout + nl, nyo, nxo) */
{
    const int w = get_global_id(0);
    const int j0 = get_global_id(1) * JR;
    const int l = get_global_id(2);
    const int kv = oblocks[2 * w];
    const int mir = oblocks[2 * w + 1];
    const size_t nxs = (size_t)(o * ncx);
    __global const real *src[JR];
    realv acc[JR];
#pragma unroll
    for (int r = 0; r < JR; ++r) {            /* rows past the last are clamped, not stored */
        const int j = min(j0 + r, nyo - 1);
        src[r] = U + ((size_t)l * (size_t)nyo + (size_t)j) * nxs + (size_t)(kv * VW + xoff);
        acc[r] = (realv)(0.0);
    }
    for (int b = 0; b < o; ++b)
        for (int a = 0; a < na; ++a) {
            const realv t = (realv)(kx[o * a + b]);
            const size_t off = (size_t)(b * ncx + a);
#pragma unroll
            for (int r = 0; r < JR; ++r)
                acc[r] = fma(t, VLOAD(0, src[r] + off), acc[r]);
        }
#pragma unroll
    for (int r = 0; r < JR; ++r) {
        const int j = j0 + r;
        if (j < nyo) {
            __global real *dst = P + ((size_t)(lout + l) * (size_t)nyo + (size_t)j) * (size_t)nxo;
            store_cells(acc[r], kv * VW - pad, nxo, dst);
            if (mir >= 0)
                store_cells(REVERSE(acc[r]), mir * VW - pad, nxo, dst);
        }
    }
}

/*
 * Fraction of a 1-D Gaussian (centre c, sigma[l] cells) in each cell of an
 * axis of n cells with edges e_k = k - n/2, z = (e - c)/(sqrt2 sigma), a = z_k,
 * b = z_{k+1}, without cancellation in the tails:
 *   a >= 1/2:    f = 1/2 [erfc(a) - erfc(b)]
 *   b <= -1/2:   f = 1/2 [erfc(-b) - erfc(-a)]
 *   otherwise:   f = 1/2 [E(b) - E(a)],  E(z) = erf(z) for |z| < 1/2, else +-(1 - erfc(|z|))
 * (erf(b) - erf(a) with both near +-1 lost everything below 1 ulp of 1: 5.5e-12
 * of the peak between an H200 and NumPy for a source off the field).
 * Global (n, nl).  NumPy twin: slicersim.physics.psf.erf_cell_fractions.
 */
#define ERF_SPLIT 0.5

inline real erf_split(const real z)
{
    return fabs(z) < ERF_SPLIT ? erf(z) : copysign(1.0 - erfc(fabs(z)), z);
}

__kernel void gaussian_cell_fractions(
    __global const real *restrict sigma,  /* (nl,) [cells] */
    const real c,
    __global real *restrict f)            /* (nl, n) */
{
    const int k = get_global_id(0);
    const int l = get_global_id(1);
    const int n = get_global_size(0);
    const real z = M_SQRT2 * sigma[l];
    const real e = (real)k - 0.5 * (real)n;
    const real a = (e - c) / z, b = (e + 1.0 - c) / z;
    real v;
    if (a >= ERF_SPLIT)
        v = erfc(a) - erfc(b);
    else if (b <= -ERF_SPLIT)
        v = erfc(-b) - erfc(-a);
    else
        v = erf_split(b) - erf_split(a);
    f[(size_t)l * (size_t)n + (size_t)k] = 0.5 * v;
}

/* P[l, j, k] = fy[l, j] fx[l, k] (Gaussian PSF: erf product).  Global (nx, ny, nl). */
__kernel void outer_product(
    __global const real *restrict fy,     /* (nl, ny) */
    __global const real *restrict fx,     /* (nl, nx) */
    __global real *restrict P)            /* (nl, ny, nx) */
{
    const int k = get_global_id(0);
    const int j = get_global_id(1);
    const int l = get_global_id(2);
    const int nx = get_global_size(0);
    const int ny = get_global_size(1);
    const size_t row = (size_t)l * (size_t)ny + (size_t)j;
    P[row * (size_t)nx + (size_t)k] = fy[row] * fx[(size_t)l * (size_t)nx + (size_t)k];
}

