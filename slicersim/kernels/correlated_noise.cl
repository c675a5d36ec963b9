/*
 * correlated_noise.cl: random Fourier coefficients of Gaussian noise streams with a given PSD
 * (slicersim/backends/correlated_noise.py, NumPy twin spectral_coefficients_numpy).
 */
#include "philox.cl"

/*
 * spectral_coefficients: one Philox4x32-10 block
 * (counter (index = (hi[r] << 32) | b, stream[r], draw[r])) gives bins 2b and 2b + 1 of row r:
 * four 23-bit uniforms u = (2 (w >> 9) + 1) 2^-24 in (0, 1) (exact in float), and
 *     X[r, 2b + i] = amp[kind[r], 2b + i] * sqrt(-2 ln u_2i) * (cos 2 pi u_2i+1 + i sin 2 pi u_2i+1)
 * in float (the Box-Muller radius is capped at sqrt(-2 ln 2^-24) = 5.77 sigma).  Its NumPy twin
 * (spectral_coefficients_numpy) uses NumPy's float32 log/sin/cos: the two agree within a few
 * float ulps (libm differences), not bit for bit.  Work item (g, r): blocks g*FVW ... g*FVW+FVW-1.
 * Rows of amp and out have nbins (a multiple of 2*FVW) entries.
 */
#ifndef FVW
#define FVW 16
#endif
#if FVW == 1
#define FSUF
#define FLANES 0u
#elif FVW == 4
#define FSUF 4
#define FLANES ((uint4)(0, 1, 2, 3))
#define FLANES_REVERSED ((uint4)(3, 2, 1, 0))
#elif FVW == 8
#define FSUF 8
#define FLANES ((uint8)(0, 1, 2, 3, 4, 5, 6, 7))
#define FLANES_REVERSED ((uint8)(7, 6, 5, 4, 3, 2, 1, 0))
#elif FVW == 16
#define FSUF 16
#define FLANES ((uint16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15))
#define FLANES_REVERSED ((uint16)(15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0))
#else
#error "FVW must be 1, 4, 8 or 16"
#endif
typedef RNG_PASTE(uint, FSUF) fuint;
typedef RNG_PASTE(float, FSUF) ffloat;
#define FROUND(a, b, c, d, k0, k1)                                        \
    {                                                                     \
        const fuint hi0_ = mul_hi((fuint)PHILOX_M0, a), lo0_ = (fuint)PHILOX_M0 * (a); \
        const fuint hi1_ = mul_hi((fuint)PHILOX_M1, c), lo1_ = (fuint)PHILOX_M1 * (c); \
        (a) = hi1_ ^ (b) ^ (k0);                                          \
        (b) = lo1_;                                                       \
        (c) = hi0_ ^ (d) ^ (k1);                                          \
        (d) = lo0_;                                                       \
    }

__kernel void spectral_coefficients(__global const float *restrict amp, __global const uint *restrict kind,
                                        __global const uint *restrict hi, __global const uint *restrict stream,
                                        __global const uint *restrict draw, const uint nbins,
                                        const uint key0, const uint key1, __global float *restrict out)
{
    const size_t g = get_global_id(0);
    const size_t r = get_global_id(1);
    if (g * FVW * 2 >= nbins)
        return;
    const uint b0 = (uint)(g * FVW);
    fuint a = (fuint)b0 + FLANES;
    fuint b = (fuint)hi[r], c = (fuint)stream[r], d = (fuint)draw[r];
    uint k0 = key0, k1 = key1;
    for (int i = 0; i < 9; i++) {
        FROUND(a, b, c, d, k0, k1)
        k0 += PHILOX_W0;
        k1 += PHILOX_W1;
    }
    FROUND(a, b, c, d, k0, k1)
    const ffloat s24 = (ffloat)0x1.0p-24f;
    const ffloat ua = RNG_PASTE(convert_float, FSUF)((a >> 9) * 2u + 1u) * s24;
    const ffloat ub = RNG_PASTE(convert_float, FSUF)((b >> 9) * 2u + 1u) * s24;
    const ffloat uc = RNG_PASTE(convert_float, FSUF)((c >> 9) * 2u + 1u) * s24;
    const ffloat ud = RNG_PASTE(convert_float, FSUF)((d >> 9) * 2u + 1u) * s24;
    const ffloat r0 = sqrt(-2.0f * log(ua)), r1 = sqrt(-2.0f * log(uc));
    const ffloat c0 = cospi(2.0f * ub), s0 = sinpi(2.0f * ub);
    const ffloat c1 = cospi(2.0f * ud), s1 = sinpi(2.0f * ud);
    __global const float *w = amp + (size_t)kind[r] * nbins + 2 * (size_t)b0;
    __global float *o = out + 2 * ((size_t)r * nbins + 2 * (size_t)b0);
#if FVW == 16
    /* the same products as the loop below, interleaved by swizzles into four float16 stores
     * (PoCL turns the loop's 64 scalar stores into most of the kernel's time) */
    const float16 wa = vload16(0, w), wb = vload16(1, w);
    const float16 w0 = (float16)(wa.even, wb.even), w1 = (float16)(wa.odd, wb.odd);
    const float16 p = w0 * (r0 * c0), q = w0 * (r0 * s0), u = w1 * (r1 * c1), v = w1 * (r1 * s1);
#define CN_QUAD(i) p.s##i, q.s##i, u.s##i, v.s##i
    vstore16((float16)(CN_QUAD(0), CN_QUAD(1), CN_QUAD(2), CN_QUAD(3)), 0, o);
    vstore16((float16)(CN_QUAD(4), CN_QUAD(5), CN_QUAD(6), CN_QUAD(7)), 1, o);
    vstore16((float16)(CN_QUAD(8), CN_QUAD(9), CN_QUAD(a), CN_QUAD(b)), 2, o);
    vstore16((float16)(CN_QUAD(c), CN_QUAD(d), CN_QUAD(e), CN_QUAD(f)), 3, o);
#undef CN_QUAD
#else
    float x0[FVW], y0[FVW], x1[FVW], y1[FVW];
#if FVW == 1
    x0[0] = r0 * c0; y0[0] = r0 * s0; x1[0] = r1 * c1; y1[0] = r1 * s1;
#else
    RNG_PASTE(vstore, FSUF)(r0 * c0, 0, x0);
    RNG_PASTE(vstore, FSUF)(r0 * s0, 0, y0);
    RNG_PASTE(vstore, FSUF)(r1 * c1, 0, x1);
    RNG_PASTE(vstore, FSUF)(r1 * s1, 0, y1);
#endif
    for (int l = 0; l < FVW; l++) {
        const float w0 = w[2 * l], w1 = w[2 * l + 1];
        o[4 * l] = w0 * x0[l];
        o[4 * l + 1] = w0 * y0[l];
        o[4 * l + 2] = w1 * x1[l];
        o[4 * l + 3] = w1 * y1[l];
    }
#endif
}

/*
 * assemble_group: group grp's averaged correlated noise of a block of rows (twin: assemble_numpy).
 * Pixel (y, x) of the block (row y0 + y of the detector, output o = x / ncol, scan position j):
 *     sum over the (at most two) segments s whose span holds row y0 + y of
 *         win[s, p_s] * (seg[s, 0, p_s] + seg[s, 1 + o, p_s]),   p_s = (y0 + y - s*S + h)*row_len + j
 *   + lowA[y, o] + (j / row_len) * (lowA2[y, o] - lowA[y, o])          (low part, common + own)
 *   + (-1)^j * (altA[y, o] + (j / row_len) * (altA2[y, o] - altA[y, o]))  (alternating ACN, low part)
 *   + ped[o] + pf * (ey[y] + ex[x])
 * seg: (nsg, nout + 1, length) streams of segments s_first ... s_first + nsg - 1, win: (nsg, span);
 * the block's arrays hold every group: lowA ... altA2 (groups, rows, nout), ped (groups, nout),
 * pf (groups), out (groups, rows, nx); this launch fills group grp.
 */
__kernel void assemble_group(__global const float *restrict seg, __global const float *restrict win,
                             const int s_first, const int nsg, const int nseg, const int S, const int h,
                             const int span, const int length, const int y0, const int row_len,
                             const int ncol, const int nout, const int nx,
                             __global const float *restrict lowA, __global const float *restrict lowA2,
                             __global const float *restrict altA, __global const float *restrict altA2,
                             __global const float *restrict ped_all, __global const float *restrict pf_all,
                             __global const float *restrict ey, __global const float *restrict ex,
                             __global float *restrict out_all, const int grp, const int rows)
{
    /* work item (v, y): pixels x = v*FVW ... v*FVW + FVW - 1 of block row y, all in one output
     * (ncol % FVW == 0).  Lanes are evaluated in ascending scan position j (one vector load
     * from each stream; an odd output reads its columns right to left, so its lanes are
     * reversed before the per-column terms). */
    const int x0 = (int)get_global_id(0) * FVW;
    const int y = get_global_id(1);
    if (x0 >= nx)
        return;
    __global const float *restrict ped = ped_all + (size_t)grp * nout;
    const float pf = pf_all[grp];
    __global float *restrict out = out_all + (size_t)grp * rows * nx;
    const int o = x0 / ncol, xl0 = x0 - o * ncol;
    const int odd = o & 1;
    const int jlo = odd ? ncol - FVW - xl0 : xl0;          /* smallest scan position of the lanes */
    const int row = y0 + y;
    const int s1 = row / S, r1 = row - s1 * S;
    int s2 = (r1 < h) ? s1 - 1 : ((r1 >= S - h) ? s1 + 1 : -1);
    const int ok2 = (s2 >= 0) && (s2 < nseg);
    s2 = ok2 ? s2 : s1;
    const int i1 = s1 - s_first, i2 = s2 - s_first;
    const int p1 = (row - s1 * S + h) * row_len + jlo, p2 = (row - s2 * S + h) * row_len + jlo;
    const size_t b1 = (size_t)i1 * (nout + 1) * length, b2 = (size_t)i2 * (nout + 1) * length;
    const size_t own = (size_t)(1 + o) * length;
#if FVW == 1
#define FLOAD(p) (*(p))
#else
#define FLOAD(p) RNG_PASTE(vload, FSUF)(0, (p))
#endif
    const ffloat v1 = FLOAD(win + (size_t)i1 * span + p1) * (FLOAD(seg + b1 + p1) + FLOAD(seg + b1 + own + p1));
    ffloat v = v1;
    if (ok2) {
        const ffloat v2 = FLOAD(win + (size_t)i2 * span + p2) * (FLOAD(seg + b2 + p2) + FLOAD(seg + b2 + own + p2));
        v = v1 + v2;
    } else {
        v = v1 + (ffloat)0.0f;
    }
    const fuint j = (fuint)(uint)jlo + FLANES;
    const ffloat t = RNG_PASTE(convert_float, FSUF)(j) / (ffloat)(float)row_len;
    const int lo = (grp * rows + y) * nout + o;
    const float a = lowA[lo], a2 = lowA2[lo], c = altA[lo], c2 = altA2[lo];
    const ffloat low = (ffloat)a + t * (ffloat)(a2 - a);
    const ffloat alt = (ffloat)c + t * (ffloat)(c2 - c);
#if FVW == 1
    v = v + low + ((j & 1u) ? -alt : alt);
#else
    v = v + low + select(alt, -alt, RNG_PASTE(convert_int, FSUF)(j & 1u) != 0);
    if (odd)
        v = shuffle(v, FLANES_REVERSED);
#endif
    v = v + (ffloat)ped[o] + (ffloat)pf * ((ffloat)ey[y] + FLOAD(ex + x0));
#if FVW == 1
    out[(size_t)y * nx + x0] = v;
#else
    RNG_PASTE(vstore, FSUF)(v, 0, out + (size_t)y * nx + x0);
#endif
#undef FLOAD
}
