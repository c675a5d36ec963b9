/*
 * noise.cl: random draws for cubes and ramps (needs philox.cl, see below).
 *
 * Element i of the current chunk has the global index first_index + i, which
 * keys its Philox counter, so the output does not depend on the chunking, the
 * work-group size or the vector width.  NumPy twins:
 * slicersim/rng.py and slicersim/compute_noise.py (bit-identical).
 *
 *   philox_words     raw Philox4x32-10 blocks for given counters and keys (tests)
 *   uniform_normal   two uniforms and two Box-Muller Gaussians per index
 *   gaussian_noise   out = expectation + sqrt(variance) N(0,1)   [NaN for
 *                    non-finite variance; exactly the expectation for variance 0]
 *   poisson_draw     Poisson(mean): inversion for mean < 10, PTRS (Hoermann
 *                    1993) above; NaN for non-finite mean
 *
 * The host builds this file with -I<kernels dir> and -DRNG_VW=N: uniform_normal and
 * gaussian_noise handle N consecutive elements per work item (explicit vectors;
 * buffers padded to a multiple of N); the other kernels exist only for N = 1.
 *
 * Precision: double by default (the bit-identical twins above); with -DSINGLE (and
 * -cl-single-precision-constant) the buffers and transforms are float (rng_real), from
 * the same Philox words (philox.cl's float philox_u01, log/exp, sincospi), no double
 * anywhere: equal to the float64 twin only statistically (measured in
 * tests/test_noise_precision.py and slicersim.backends.precision.SINGLE_PRECISION_ERRORS).
 * The float inversion stops where the float CDF stops growing (no run-away to p = 0 for
 * a u above the rounded total); the float PTRS acceptance uses rng_log_poisson.
 */
#include "philox.cl"

#if RNG_VW == 1

#define PTRS_MIN_MEAN 10.0
#define PTRS_MAX_ATTEMPTS 1000u

#ifndef SINGLE
#define RNG_INV_LN2 0x1.71547652b82fep+0
#define RNG_HALF_LOG_2PI 0x1.d67f1c864beb4p-1

/* exp(x), |x| < 700: x = n ln2 + r, Taylor series of e^r to r^13 */
/* rng_exp: see philox.cl */

__constant double LOG_FACTORIAL[10] = {
    0x0.0p+0, 0x0.0p+0, 0x1.62e42fefa39ecp-1, 0x1.cab0bfa2a2004p+0, 0x1.96ca77c922cf7p+1,
    0x1.326643c4479cap+2, 0x1.a51273acf01cbp+2, 0x1.10ce1f32dcc30p+3, 0x1.5358e82fcb70cp+3,
    0x1.99a8921a7f7cep+3};

/* ln k! for integer-valued k >= 0: table below 10, Stirling series above */
inline double log_factorial(const double k)
{
    if (k < 10.0)
        return LOG_FACTORIAL[(int)k];
    const double x = k + 1.0;
    const double r = 1.0 / x;
    const double z = r * r;
    double p = 0x1.a41a41a41a41ap-8;             /* 1/156 */
    p = p * z - 0x1.f6ab0d9993c7dp-10;           /* -691/360360 */
    p = p * z + 0x1.b951e2b18ff23p-11;           /* 1/1188 */
    p = p * z - 0x1.3813813813814p-11;           /* -1/1680 */
    p = p * z + 0x1.a01a01a01a01ap-11;           /* 1/1260 */
    p = p * z - 0x1.6c16c16c16c17p-9;            /* -1/360 */
    p = p * z + 0x1.5555555555555p-4;            /* 1/12 */
    return ((x - 0.5) * rng_log(x) - x) + (RNG_HALF_LOG_2PI + r * p);
}
#endif

/* Poisson(mu) by inversion: the CDF recurrence from p = e^-mu.  In float it also ends where the CDF
 * stops growing (the tail left is below its rounding, ~1e-7), not only where p underflows: a u above
 * the rounded total CDF would otherwise run on to k ~ 50 at mu = 5. */
inline rng_real poisson_inversion(const rng_real mu, const uint2 key, const ulong index, const uint stream)
{
    const uint4 w = philox_block(key, index, stream, 0u);
    const rng_real u = philox_u01(w.x, w.y);
    rng_real p = rng_exp(-mu);
    rng_real cdf = p;
    rng_real k = 0.0;
    while (u > cdf && p > 0.0) {
        k = k + 1.0;
        p = p * mu / k;
        const rng_real next = cdf + p;
#ifdef SINGLE
        if (!(next > cdf))
            break;
#endif
        cdf = next;
    }
    return k;
}

inline rng_real poisson_ptrs(const rng_real mu, const uint2 key, const ulong index, const uint stream)
{
    const rng_real smu = sqrt(mu);
    const rng_real log_mu = rng_log(mu);
    const rng_real b = 0.931 + 2.53 * smu;
    const rng_real a = -0.059 + 0.02483 * b;
    const rng_real log_inv_alpha = rng_log(1.1239 + 1.1328 / (b - 3.4));
    const rng_real vr = 0.9277 - 3.6224 / (b - 2.0);
    RNG_PTRS_SPLIT(mu)
    for (uint attempt = 0u; attempt < PTRS_MAX_ATTEMPTS; ++attempt) {
        const uint4 w = philox_block(key, index, stream, attempt);
        const rng_real U = philox_u01(w.x, w.y) - 0.5;
        const rng_real V = philox_u01(w.z, w.w);
        const rng_real us = 0.5 - fabs(U);
        const rng_real k = RNG_PTRS_K(a, b, us, U, mu);
        if (us >= 0.07 && V <= vr)
            return k;
        if (k < 0.0 || (us < 0.013 && V > us))
            continue;
        const rng_real lhs = (rng_log(V) + log_inv_alpha) - rng_log(a / (us * us) + b);
#ifdef SINGLE
        const rng_real rhs = rng_log_poisson(k, mu, log_mu);     /* no float cancellation (philox.cl) */
#else
        const rng_real rhs = (k * log_mu - mu) - log_factorial(k);
#endif
        if (lhs <= rhs)
            return k;
    }
    return NAN;
}

__kernel void philox_words(__global const uint4 *restrict counter, __global const uint2 *restrict key,
                           __global uint4 *restrict out, const uint n)
{
    const size_t i = get_global_id(0);
    if (i >= n)
        return;
    uint a = counter[i].x, b = counter[i].y, c = counter[i].z, d = counter[i].w;
    philox4x32_10(&a, &b, &c, &d, key[i].x, key[i].y);
    out[i] = (uint4)(a, b, c, d);
}

__kernel void poisson_draw(__global const real *restrict mean, __global real *restrict out,
                           const ulong first_index, const uint n, const uint key_lo, const uint key_hi,
                           const uint stream)
{
    const size_t i = get_global_id(0);
    if (i >= n)
        return;
    const real mu = mean[i];
    const uint2 key = (uint2)(key_lo, key_hi);
    const ulong index = first_index + i;
    real k;
    if (!isfinite(mu))
        k = NAN;
    else if (mu < PTRS_MIN_MEAN)
        k = poisson_inversion(mu, key, index, stream);
    else
        k = poisson_ptrs(mu, key, index, stream);
    out[i] = k;
}
#endif /* RNG_VW == 1 */

/* Grid of rows x ncols elements (ncols a multiple of RNG_VW; the host pads): work item (g, row)
 * draws elements g*RNG_VW ... g*RNG_VW + RNG_VW - 1 of its row, element (row, col) keyed by
 * index = first_index + row*row_stride + col, stored at row*ncols + col of each plane. */
__kernel void uniform_normal(__global real *restrict u1, __global real *restrict u2,
                             __global real *restrict z1, __global real *restrict z2,
                             const ulong first_index, const ulong row_stride, const uint ncols,
                             const uint key_lo, const uint key_hi, const uint stream, const uint draw)
{
    const size_t g = get_global_id(0);
    const size_t row = get_global_id(1);
    if (g * RNG_VW >= ncols)
        return;
    const size_t o = row * (ncols / RNG_VW) + g;
    rng_uint a, b, c, d;
    philox_counter((rng_ulong)(first_index + row * row_stride + g * RNG_VW) + RNG_LANES, stream, draw,
                   &a, &b, &c, &d);
    philox4x32_10(&a, &b, &c, &d, key_lo, key_hi);
    RNG_VSTORE(philox_u01(a, b), o, u1);
    RNG_VSTORE(philox_u01(c, d), o, u2);
    rng_real zs;
    const rng_real zc = box_muller_lanes(a, b, c, d, &zs);
    RNG_VSTORE(zc, o, z1);
    RNG_VSTORE(zs, o, z2);
}

/* out = expectation + sqrt(variance) N(0,1); NaN for non-finite variance, the expectation for 0 */
__kernel void gaussian_noise(__global const real *restrict expectation,
                             __global const real *restrict variance, __global real *restrict out,
                             const ulong first_index, const uint n, const uint key_lo, const uint key_hi,
                             const uint stream)
{
    const size_t g = get_global_id(0);
    if (g * RNG_VW >= n)
        return;
    rng_uint a, b, c, d;
    philox_counter((rng_ulong)(first_index + g * RNG_VW) + RNG_LANES, stream, 0u, &a, &b, &c, &d);
    philox4x32_10(&a, &b, &c, &d, key_lo, key_hi);
    rng_real unused;
    const rng_real z = box_muller_lanes(a, b, c, d, &unused);
    const rng_real e = RNG_VLOAD(g, expectation), v = RNG_VLOAD(g, variance);
    rng_real r = RNG_SELECT(e + sqrt(v) * z, e, v == 0.0);
    r = RNG_SELECT(r, (rng_real)NAN, !isfinite(v));
    RNG_VSTORE(r, g, out);
}
