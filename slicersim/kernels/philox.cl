/*
 * philox.cl: counter-based random numbers for slicersim kernels (header-like source).
 *
 * Use it with `#include "philox.cl"` (build option -I<kernels dir>) or prepend
 * its text to another kernel source.  It defines only types, macros and inline
 * functions (no kernels), guarded against double inclusion.
 *
 * Precision: double by default (bit for bit the NumPy twin, below); with -DSINGLE
 * (and -cl-single-precision-constant) rng_real is float, philox_u01 takes 24 bits
 * of its first word, and log/exp/sin/cos are the device's float functions: no
 * double anywhere, so a device without fp64 builds it; the results match the
 * float64 twin only statistically (checked in tests/test_ramp_precision.py).
 *
 * Vector width: build with -DRNG_VW=1|2|4|8|16 (default 1).  The types
 * rng_uint, rng_ulong, rng_long, rng_double are then uint, ..., double (VW = 1)
 * or their N-vectors, one lane per random element: explicit vectors make PoCL
 * use SIMD (its implicit work-item vectoriser gives up on this much code);
 * GPUs use VW = 1.
 *
 *   philox4x32_10(&a, &b, &c, &d, k0, k1)  Philox4x32-10 block in place (Salmon et al.
 *                                        2011, Random123); counter (a, b, c, d), key (k0, k1)
 *   philox_counter(index, stream, draw, &a, &b, &c, &d)
 *                                        counter (index lo, index hi, stream, draw)
 *   philox_u01(hi, lo)                   52-bit uniform (2x+1)*2^-53 in (0, 1), never 0 or 1
 *   philox_x52(hi, lo)                   its 52-bit integer x = hi*2^20 + (lo >> 12)
 *   rng_log(u)                           natural log of a positive normal double
 *   rng_sincos_2pi(u, &sin)              cos 2 pi u (returned) and sin 2 pi u
 *   box_muller_lanes(a, b, c, d, &z1)    two N(0,1) draws from one block (z0 returned)
 *   philox_block(key, index, stream, draw)   uint4 block (VW = 1 only)
 *   box_muller(w)                        (z0, z1) as a double2 from a uint4 block (VW = 1 only)
 *   rng_log_poisson(k, mu, ln mu)        -DSINGLE only: ln P(k; mu) without float cancellation
 *                                        (the PTRS acceptance test at large means)
 *
 * Bit-identity with the NumPy twin (slicersim/rng.py): only IEEE +, -, *, /,
 * sqrt and exact integer/bit operations are used (no libm log/cos, whose last
 * bit varies between implementations), constants are hex literals identical
 * to the Python ones, and FMA contraction is switched off.  Do not build with
 * -cl-fast-relaxed-math, -cl-mad-enable or -cl-unsafe-math-optimizations.
 */
#ifndef SLICERSIM_PHILOX_CL
#define SLICERSIM_PHILOX_CL

#if defined(RNG_VW) && !defined(VW)
#define VW RNG_VW                 /* the shared vector types follow the generator's width */
#endif
#include "vector_types.cl"
#pragma OPENCL FP_CONTRACT OFF

#ifndef RNG_INLINE            /* a kernel may force inlining: #define RNG_INLINE before #include */
#define RNG_INLINE inline
#endif

#ifndef RNG_VW
#define RNG_VW 1
#endif

#define RNG_PASTE_(a, b) a##b
#define RNG_PASTE(a, b) RNG_PASTE_(a, b)
#if RNG_VW == 1
#define RNG_SUFFIX
#define RNG_LANES 0ul
#define RNG_VLOAD(i, p) ((p)[i])
#define RNG_VSTORE(x, i, p) ((p)[i] = (x))
#elif RNG_VW == 2
#define RNG_SUFFIX 2
#define RNG_LANES ((ulong2)(0, 1))
#elif RNG_VW == 4
#define RNG_SUFFIX 4
#define RNG_LANES ((ulong4)(0, 1, 2, 3))
#elif RNG_VW == 8
#define RNG_SUFFIX 8
#define RNG_LANES ((ulong8)(0, 1, 2, 3, 4, 5, 6, 7))
#elif RNG_VW == 16
#define RNG_SUFFIX 16
#define RNG_LANES ((ulong16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15))
#else
#error "RNG_VW must be 1, 2, 4, 8 or 16"
#endif
#if RNG_VW > 1
#define RNG_VLOAD(i, p) RNG_PASTE(vload, RNG_SUFFIX)((i), (p))
#define RNG_VSTORE(x, i, p) RNG_PASTE(vstore, RNG_SUFFIX)((x), (i), (p))
#endif

typedef RNG_PASTE(uint, RNG_SUFFIX) rng_uint;
typedef RNG_PASTE(ulong, RNG_SUFFIX) rng_ulong;
typedef RNG_PASTE(long, RNG_SUFFIX) rng_long;
#ifndef SINGLE
typedef RNG_PASTE(double, RNG_SUFFIX) rng_double;
#endif
#define rng_convert_uint RNG_PASTE(convert_uint, RNG_SUFFIX)
#define rng_convert_long RNG_PASTE(convert_long, RNG_SUFFIX)
#define rng_convert_double RNG_PASTE(convert_double, RNG_SUFFIX)
#define rng_as_long RNG_PASTE(as_long, RNG_SUFFIX)
#define rng_as_ulong RNG_PASTE(as_ulong, RNG_SUFFIX)
#define rng_as_double RNG_PASTE(as_double, RNG_SUFFIX)
/* b where cond holds, else a (cond: a comparison, int for scalars, long-N for vectors).  Scalars use
 * the conditional operator: its meaning does not hang on how a driver reads a scalar select's
 * 64-bit condition (the spec: non-zero; vectors: the most significant bit). */
/* rng_real: the floating type of the draws' transforms (double; float with -DSINGLE, see below), rng_rmask
 * the integer of the same width that its comparisons give (long / int lanes) */
#ifdef SINGLE
typedef RNG_PASTE(float, RNG_SUFFIX) rng_real;
typedef RNG_PASTE(int, RNG_SUFFIX) rng_rmask;
#define RNG_RMASK_NAME int
#define rng_convert_real RNG_PASTE(convert_float, RNG_SUFFIX)
#define rng_convert_rmask RNG_PASTE(convert_int, RNG_SUFFIX)
#else
typedef rng_double rng_real;
typedef rng_long rng_rmask;
#define RNG_RMASK_NAME long
#define rng_convert_real rng_convert_double
#define rng_convert_rmask rng_convert_long
#endif
#if RNG_VW == 1
#define RNG_SELECT(a, b, cond) ((cond) ? (b) : (a))
#else
#define RNG_SELECT(a, b, cond) select((a), (b), rng_convert_rmask(cond))
#endif

#define PHILOX_M0 0xD2511F53ul
#define PHILOX_M1 0xCD9E8D57ul
#define PHILOX_W0 0x9E3779B9u
#define PHILOX_W1 0xBB67AE85u

#define RNG_LN2_HI 0x1.62e42fee00000p-1
#define RNG_LN2_LO 0x1.a39ef35793c76p-33
#define RNG_SQRT_HALF_BITS 0x3fe6a09e667f3bcdL   /* bits of sqrt(1/2) */
#define RNG_TWO_PI 0x1.921fb54442d18p+2

/* One round on words (a, b, c, d) with key (k0, k1); 32 x 32 -> 64-bit products. */
#define PHILOX_ROUND(a, b, c, d, k0, k1)                                   \
    {                                                                      \
        const rng_ulong p0_ = PHILOX_M0 * RNG_PASTE(convert_ulong, RNG_SUFFIX)(a); \
        const rng_ulong p1_ = PHILOX_M1 * RNG_PASTE(convert_ulong, RNG_SUFFIX)(c); \
        const rng_uint a_ = rng_convert_uint(p1_ >> 32) ^ (b) ^ (k0);      \
        const rng_uint c_ = rng_convert_uint(p0_ >> 32) ^ (d) ^ (k1);      \
        (b) = rng_convert_uint(p1_);                                       \
        (d) = rng_convert_uint(p0_);                                       \
        (a) = a_;                                                          \
        (c) = c_;                                                          \
    }
#define PHILOX_ROUND_BUMP(a, b, c, d, k0, k1)                              \
    PHILOX_ROUND(a, b, c, d, k0, k1)                                       \
    (k0) += PHILOX_W0;                                                     \
    (k1) += PHILOX_W1;

/* Philox4x32-10 in place: ten rounds, the key bumped before rounds 2..10. */
RNG_INLINE void philox4x32_10(rng_uint *pa, rng_uint *pb, rng_uint *pc, rng_uint *pd, uint k0, uint k1)
{
    rng_uint a = *pa, b = *pb, c = *pc, d = *pd;
    PHILOX_ROUND_BUMP(a, b, c, d, k0, k1)
    PHILOX_ROUND_BUMP(a, b, c, d, k0, k1)
    PHILOX_ROUND_BUMP(a, b, c, d, k0, k1)
    PHILOX_ROUND_BUMP(a, b, c, d, k0, k1)
    PHILOX_ROUND_BUMP(a, b, c, d, k0, k1)
    PHILOX_ROUND_BUMP(a, b, c, d, k0, k1)
    PHILOX_ROUND_BUMP(a, b, c, d, k0, k1)
    PHILOX_ROUND_BUMP(a, b, c, d, k0, k1)
    PHILOX_ROUND_BUMP(a, b, c, d, k0, k1)
    PHILOX_ROUND(a, b, c, d, k0, k1)
    *pa = a; *pb = b; *pc = c; *pd = d;
}

/* counter = (index lo, index hi, stream, draw) */
RNG_INLINE void philox_counter(const rng_ulong index, const uint stream, const uint draw,
                           rng_uint *a, rng_uint *b, rng_uint *c, rng_uint *d)
{
    *a = rng_convert_uint(index);
    *b = rng_convert_uint(index >> 32);
    *c = (rng_uint)stream;
    *d = (rng_uint)draw;
}

#if RNG_VW == 1
/* Scalar convenience (both precisions: integers only): the block for counter (index lo, index hi,
 * stream, draw) and key. */
inline uint4 philox_block(const uint2 key, const ulong index, const uint stream, const uint draw)
{
    uint a, b, c, d;
    philox_counter(index, stream, draw, &a, &b, &c, &d);
    philox4x32_10(&a, &b, &c, &d, key.x, key.y);
    return (uint4)(a, b, c, d);
}
#endif

#ifndef SINGLE
/* u = (2x + 1) 2^-53 with the 52-bit x = hi * 2^20 + (lo >> 12): exact, in (0, 1).
 * No 32-bit word with its top bit set is ever widened to 64 bits: NVIDIA's OpenCL (H200, driver
 * 580.159) sign-extended hi in (ulong)hi << 20, so every u >= 0.5 came out as u - 1 (half the
 * uniforms, Poisson means 0.134 at mu = 1).  Here 2x + 1 = (hi >> 1) 2^22 + r with
 * r = (hi & 1) 2^21 + (lo >> 11 | 1) < 2^22, both parts below 2^31 (signed and unsigned readings
 * agree) and converted exactly; the two terms share no bit, so the sum is exact (FMA or not). */
RNG_INLINE rng_double philox_u01(const rng_uint hi, const rng_uint lo)
{
    const rng_uint r = ((hi & 1u) << 21) | (lo >> 11) | 1u;
    return rng_convert_double(hi >> 1) * 0x1.0p-31 + rng_convert_double(r) * 0x1.0p-53;
}

#endif

/* The 52-bit x = hi * 2^20 + (lo >> 12) of philox_u01 as an integer, built from two parts below
 * 2^31 (no widening of a word with its top bit set, see philox_u01). */
RNG_INLINE rng_ulong philox_x52(const rng_uint hi, const rng_uint lo)
{
    return (RNG_PASTE(convert_ulong, RNG_SUFFIX)(hi >> 1) << 21)
         | RNG_PASTE(convert_ulong, RNG_SUFFIX)(((hi & 1u) << 20) | (lo >> 12));
}

#ifndef SINGLE
/* ln u for positive normal u: u = m 2^e, m in [sqrt(1/2), sqrt(2)), ln m = 2 atanh s. */
RNG_INLINE rng_double rng_log(const rng_double u)
{
    const rng_long bits = rng_as_long(u);
    rng_long e = ((bits >> 52) & 0x7ffL) - 1022L;
    rng_long mbits = (bits & 0x000fffffffffffffL) | 0x3fe0000000000000L;   /* m in [0.5, 1) */
    const rng_long low = (mbits - RNG_SQRT_HALF_BITS) >> 63;              /* -1 if m < sqrt(1/2) */
    mbits += low & 0x0010000000000000L;                                   /* m -> 2m exactly */
    e += low;
    const rng_double m = rng_as_double(mbits);
    const rng_double ed = rng_convert_double(e);
    const rng_double s = (m - 1.0) / (m + 1.0);
    const rng_double s2 = s * s;
    rng_double p = 0x1.642c8590b2164p-5;         /* 1/23 */
    p = p * s2 + 0x1.8618618618618p-5;           /* 1/21 */
    p = p * s2 + 0x1.af286bca1af28p-5;           /* 1/19 */
    p = p * s2 + 0x1.e1e1e1e1e1e1ep-5;           /* 1/17 */
    p = p * s2 + 0x1.1111111111111p-4;           /* 1/15 */
    p = p * s2 + 0x1.3b13b13b13b14p-4;           /* 1/13 */
    p = p * s2 + 0x1.745d1745d1746p-4;           /* 1/11 */
    p = p * s2 + 0x1.c71c71c71c71cp-4;           /* 1/9  */
    p = p * s2 + 0x1.2492492492492p-3;           /* 1/7  */
    p = p * s2 + 0x1.999999999999ap-3;           /* 1/5  */
    p = p * s2 + 0x1.5555555555555p-2;           /* 1/3  */
    const rng_double logm = 2.0 * s + (2.0 * s) * (s2 * p);
    return ed * RNG_LN2_HI + (ed * RNG_LN2_LO + logm);
}

/* cos 2 pi u (returned) and sin 2 pi u (*sin_out) for u in (0, 1): u = q/4 + r exactly,
 * |2 pi r| <= pi/4, Taylor series to t^19, quadrant applied by exact bit selection. */
RNG_INLINE rng_double rng_sincos_2pi(const rng_double u, rng_double *sin_out)
{
    const rng_long q = rng_convert_long(4.0 * u + 0.5);              /* floor (> 0): 0..4 */
    const rng_double t = (u - 0.25 * rng_convert_double(q)) * RNG_TWO_PI;
    const rng_double t2 = t * t;
    rng_double pc = -0x1.6827863b97d97p-53;
    pc = pc * t2 + 0x1.ae7f3e733b81fp-45;
    pc = pc * t2 - 0x1.93974a8c07c9dp-37;
    pc = pc * t2 + 0x1.1eed8eff8d898p-29;
    pc = pc * t2 - 0x1.27e4fb7789f5cp-22;
    pc = pc * t2 + 0x1.a01a01a01a01ap-16;
    pc = pc * t2 - 0x1.6c16c16c16c17p-10;
    pc = pc * t2 + 0x1.5555555555555p-5;
    pc = pc * t2 - 0x1.0000000000000p-1;
    rng_double ps = -0x1.2f49b46814157p-57;
    ps = ps * t2 + 0x1.952c77030ad4ap-49;
    ps = ps * t2 - 0x1.ae7f3e733b81fp-41;
    ps = ps * t2 + 0x1.6124613a86d09p-33;
    ps = ps * t2 - 0x1.ae64567f544e4p-26;
    ps = ps * t2 + 0x1.71de3a556c734p-19;
    ps = ps * t2 - 0x1.a01a01a01a01ap-13;
    ps = ps * t2 + 0x1.1111111111111p-7;
    ps = ps * t2 - 0x1.5555555555555p-3;
    const rng_long cbits = rng_as_long(1.0 + t2 * pc);
    const rng_long sbits = rng_as_long(t + t * (t2 * ps));
    /* q mod 4 = 0: (c, s); 1: (-s, c); 2: (-c, -s); 3: (s, -c) */
    const rng_long swap = -(q & 1L);                                 /* all ones for odd q */
    /* sign bits shifted as unsigned: (2L << 62) overflows a signed long (undefined behaviour) */
    const rng_long sflip = rng_as_long(rng_as_ulong(q & 2L) << 62);
    const rng_long cflip = rng_as_long(rng_as_ulong((q + 1L) & 2L) << 62);
    *sin_out = rng_as_double(((sbits & ~swap) | (cbits & swap)) ^ sflip);
    return rng_as_double(((cbits & ~swap) | (sbits & swap)) ^ cflip);
}

/* exp(x) for |x| < 700, any width: Cody–Waite reduction and a degree-13 Taylor series
 * (the operations of slicersim.rng.rng_exp, bit for bit). */
RNG_INLINE rng_double rng_exp(const rng_double x)
{
    const rng_double n = floor(x * 0x1.71547652b82fep+0 + 0.5);
    const rng_double r = (x - n * RNG_LN2_HI) - n * RNG_LN2_LO;
    rng_double p = 0x1.6124613a86d09p-33;        /* 1/13! */
    p = p * r + 0x1.1eed8eff8d898p-29;
    p = p * r + 0x1.ae64567f544e4p-26;
    p = p * r + 0x1.27e4fb7789f5cp-22;
    p = p * r + 0x1.71de3a556c734p-19;
    p = p * r + 0x1.a01a01a01a01ap-16;
    p = p * r + 0x1.a01a01a01a01ap-13;
    p = p * r + 0x1.6c16c16c16c17p-10;
    p = p * r + 0x1.1111111111111p-7;
    p = p * r + 0x1.5555555555555p-5;
    p = p * r + 0x1.5555555555555p-3;
    p = p * r + 0x1.0000000000000p-1;            /* 1/2! */
    return ldexp(1.0 + r * (1.0 + r * p), RNG_PASTE(convert_int, RNG_SUFFIX)(n));
}

#else /* SINGLE: float transforms of the same words (no bit twin: compared with the float64 twin, whose
        * outputs they reproduce up to the last float bit; see kernels/ramp.cl) */

/* u in (0, 1) from the 32-bit word hi (lo unused): (hi | 1) 2^-32 rounded toward zero to 24 bits, so
 * never 0 or 1; within 2^-24 (relative) of the double philox_u01(hi, lo); down to 2^-32 near 0
 * (Box-Muller tails to 6.66 sigma). */
RNG_INLINE rng_real philox_u01(const rng_uint hi, const rng_uint lo)
{
    (void)lo;
    return RNG_PASTE(RNG_PASTE(convert_float, RNG_SUFFIX), _rtz)(hi | 1u) * 0x1.0p-32f;
}

#define rng_log log
#define rng_exp exp

/* cos 2 pi u (returned) and sin 2 pi u (*sin_out): cospi/sinpi reduce the argument exactly */
RNG_INLINE rng_real rng_sincos_2pi(const rng_real u, rng_real *sin_out)
{
    *sin_out = sinpi(2.0f * u);
    return cospi(2.0f * u);
}

/* ln k! for k = 0..9 */
__constant float RNG_LOG_FACTORIAL_F[10] = {
    0.0f, 0.0f, 0x1.62e430p-1f, 0x1.cab0c0p+0f, 0x1.96ca78p+1f, 0x1.326644p+2f, 0x1.a51274p+2f, 0x1.10ce20p+3f,
    0x1.5358e8p+3f, 0x1.99a892p+3f};

/* ln P(k; mu) = k ln mu - mu - ln k! in float without the cancellation of its large terms: for k >= 10,
 * Stirling's series, -mu h((k - mu)/mu) - ln(2 pi k)/2 - 1/(12k) + 1/(360k^3), h(x) = (1+x) ln(1+x) - x
 * (error a few float ulps of the result); below 10 the direct sum with the tabulated ln k!. */
RNG_INLINE rng_real rng_log_poisson(const rng_real k, const rng_real mu, const rng_real log_mu)
{
    const rng_real kk = fmax(k, 10.0f);
    const rng_real x = (kk - mu) / mu;
    /* |x| < 1/4: the series sum_(n>=2) (-x)^n / (n(n-1)) (no cancellation; 11 terms: 4e-8 relative) */
    rng_real hs = 1.0f / 132.0f;
    hs = 1.0f / 110.0f - x * hs;
    hs = 1.0f / 90.0f - x * hs;
    hs = 1.0f / 72.0f - x * hs;
    hs = 1.0f / 56.0f - x * hs;
    hs = 1.0f / 42.0f - x * hs;
    hs = 1.0f / 30.0f - x * hs;
    hs = 1.0f / 20.0f - x * hs;
    hs = 1.0f / 12.0f - x * hs;
    hs = 1.0f / 6.0f - x * hs;
    hs = 0.5f - x * hs;
    const rng_real h = RNG_SELECT((1.0f + x) * log1p(x) - x, (x * x) * hs, fabs(x) < 0.25f);
    const rng_real r = 1.0f / kk;
    const rng_real big = (-mu * h - 0.5f * log(0x1.921fb6p+2f * kk)) - r * (0x1.555556p-4f - (r * r) * 0x1.6c16c2p-9f);
    rng_real lf = 0.0f;
    for (int t = 0; t < 10; ++t)
        lf = RNG_SELECT(lf, (rng_real)RNG_LOG_FACTORIAL_F[t], k == (real)t);
    return RNG_SELECT(big, (k * log_mu - mu) - lf, k < 10.0f);
}
#endif /* SINGLE */

/* Two independent N(0, 1) draws from one block (either precision): cos branch returned, sin in *z1. */
RNG_INLINE rng_real box_muller_lanes(const rng_uint a, const rng_uint b, const rng_uint c, const rng_uint d,
                                     rng_real *z1)
{
    const rng_real radius = sqrt(-2.0 * rng_log(philox_u01(a, b)));
    rng_real s;
    const rng_real cs = rng_sincos_2pi(philox_u01(c, d), &s);
    *z1 = radius * s;
    return radius * cs;
}

/* PTRS (Hoermann 1993) proposal k = floor((2a/us + b) U + mu + 0.43), shared by noise.cl and ramp.cl:
 * RNG_PTRS_SPLIT(mu) once before the attempts, then RNG_PTRS_K(...) per attempt.  In float mu is split
 * exactly into floor(mu) + frac, so the sum rounds at ulp(X), not ulp(mu) (mu + 0.43 alone rounds to
 * 2^-25 mu: 2 % of the draws moved at mu = 3e5). */
#ifdef SINGLE
#define RNG_PTRS_SPLIT(mu) const rng_real ptrs_whole_ = floor(mu), ptrs_frac_ = ((mu) - ptrs_whole_) + 0.43;
#define RNG_PTRS_K(a, b, us, U, mu) (floor((2.0 * (a) / (us) + (b)) * (U) + ptrs_frac_) + ptrs_whole_)
#else
#define RNG_PTRS_SPLIT(mu)
#define RNG_PTRS_K(a, b, us, U, mu) floor((2.0 * (a) / (us) + (b)) * (U) + (mu) + 0.43)
#endif

#if RNG_VW == 1 && !defined(SINGLE)
/* Scalar convenience: (cos, sin) Box-Muller pair of a block. */
inline double2 box_muller(const uint4 w)
{
    double z1;
    const double z0 = box_muller_lanes(w.x, w.y, w.z, w.w, &z1);
    return (double2)(z0, z1);
}
#endif

#endif /* SLICERSIM_PHILOX_CL */
