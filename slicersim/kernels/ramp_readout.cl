/*
 * ramp_readout.cl: the voltage-domain end of an H4RG read chain for ramps with
 * detector effects (ramp.cl built with -DRAMP_EFFECTS=1 gives the group means of
 * the read values).  One work item = RNG_VW consecutive pixels of one output row
 * (explicit vector lanes, lanes past the row end are computed on a clamped column
 * and not stored), group g of one ramp (one launch per group, in order):
 *   v    = sum_{dy,dx} K[dy][dx] * gmean[g, y+dy, x+dx]   inter-pixel capacitance
 *          (3x3 kernel, row-major order of the sum; rows from the block's halo,
 *          zero outside the detector)
 *   mean = v + read_sigma * z_g + extra[g, y, x]          white read noise (the same
 *          Philox counters as the plain ramp) + correlated read noise [e-]
 *   adu  = rint(bias[y, x] + gain * (reset + mean)),  clipped to [0, 65535]
 *          (rint as (x + 2^52) - 2^52: the same clipped values, see ro_round)
 * reset = kTC noise (plain ramp's counters).  GROUPDQ bit 2 (SATURATED) is sticky
 * from the first group flagged by the charge sampler or reaching `saturation`.
 * Build with -I<kernels dir> -DRNG_VW=N.  NumPy twin: slicersim/backends/ramp_effects.py
 * (readout_numpy); the two agree bit for bit.  With -DSINGLE (opencl.precision_options) every
 * real is float: the float twin of the charge sampler's single build.
 */
#define RNG_INLINE inline __attribute__((always_inline))
#include "philox.cl"

#define P_READ 1u
#define P_KTC 2u
#define RO_INLINE inline __attribute__((always_inline))

RO_INLINE rng_real ro_lanes(const real *v)
{
#if RNG_VW == 1
    return v[0];
#else
    return RNG_PASTE(vload, RNG_SUFFIX)(0, v);
#endif
}

/* lanes of a row segment p[0 .. VW-1]: one vector load when every lane is inside the row */
RO_INLINE rng_real ro_load_d(__global const real *p, const int nl)
{
#if RNG_VW > 1
    if (nl == RNG_VW)
        return RNG_PASTE(vload, RNG_SUFFIX)(0, p);
#endif
    real v[RNG_VW];
    for (int l = 0; l < RNG_VW; ++l)
        v[l] = p[l < nl ? l : nl - 1];
    return ro_lanes(v);
}

RO_INLINE rng_real ro_load_f(__global const float *p, const int nl)
{
#if RNG_VW > 1
    if (nl == RNG_VW)
        return rng_convert_real(RNG_PASTE(vload, RNG_SUFFIX)(0, p));
#endif
    real v[RNG_VW];
    for (int l = 0; l < RNG_VW; ++l)
        v[l] = (real)p[l < nl ? l : nl - 1];
    return ro_lanes(v);
}

/* charge-saturation flags of the lanes as doubles (one vector load inside the row) */
RO_INLINE rng_real ro_load_q(__global const uchar *p, const int nl)
{
#if RNG_VW > 1
    if (nl == RNG_VW)
        return rng_convert_real(RNG_PASTE(convert_float, RNG_SUFFIX)(RNG_PASTE(vload, RNG_SUFFIX)(0, p)));
#endif
    real v[RNG_VW];
    for (int l = 0; l < RNG_VW; ++l)
        v[l] = (real)p[l < nl ? l : nl - 1];
    return ro_lanes(v);
}

/* rint(x) where the result is then clipped to [0, 65535]: (x + 2^52) - 2^52 rounds half to even
 * like rint for 0 <= x < 2^52 (FP_CONTRACT is off; 2^23 in float), gives a value <= 0 for x < 0 and >= 2^52 for
 * x >= 2^52, so the clipped results are rint's (PoCL calls rint lane by lane: ~20 % of the kernel) */
#ifdef SINGLE
#define RO_ROUND_MAGIC 0x1.0p23f       /* float: one ulp = 1 from 2^23 on */
#else
#define RO_ROUND_MAGIC 0x1.0p52
#endif
RO_INLINE rng_real ro_round(const rng_real x)
{
    return (x + RO_ROUND_MAGIC) - RO_ROUND_MAGIC;
}

/* store the lanes inside the row (one vector store when all are) */
RO_INLINE void ro_store_d(__global real *p, const rng_real v, const int nl)
{
#if RNG_VW > 1
    if (nl == RNG_VW) {
        RNG_PASTE(vstore, RNG_SUFFIX)(v, 0, p);
        return;
    }
    real w[RNG_VW];
    RNG_PASTE(vstore, RNG_SUFFIX)(v, 0, w);
    for (int l = 0; l < nl; ++l)
        p[l] = w[l];
#else
    p[0] = v;
#endif
}

RO_INLINE void ro_block(const rng_ulong index, const uint stream, uint k0, uint k1, rng_uint *a, rng_uint *b,
                        rng_uint *c, rng_uint *d)
{
    philox_counter(index, stream, 0u, a, b, c, d);
    philox4x32_10(a, b, c, d, k0, k1);
}

__kernel void ramp_readout(
    __global const real *restrict gmean,   /* (n, rows_in, nx) group means [e-], row halo_top = y0 */
    __global const uchar *restrict qsat,     /* (n, rows_in, nx) charge-saturation flags */
    __global const float *restrict extra,    /* (n, rows, nx) read-domain noise [e-] or unused */
    __global const float *restrict bias_map, /* (rows, nx) [ADU] or unused */
    __constant real *ipc,                  /* 3x3, row-major */
    __global ushort *restrict sci, __global uchar *restrict gdq,   /* (n, rows, nx) */
    __global real *restrict reset_state,   /* (rows, nx) kTC reset [e-]: written at g = 0 */
    __global real *restrict z_state,       /* (rows, nx) the odd group's read-noise draw */
    __global uchar *restrict sat_state,      /* (rows, nx) sticky saturation of groups < g */
    const uint rows, const uint nx, const uint rows_in, const uint halo_top, const uint y0,
    const uint ny, const uint ramp, const uint k0, const uint k1, const int g, const real read_sigma,
    const real gain, const real bias, const real ktc, const real saturation,
    const int use_ipc, const int use_extra, const int use_bias_map)
{
    /* One launch per group g (in order 0 .. n-1): every launch streams through one plane of each
     * array (a loop over the groups inside a work item strides by whole planes and costs about
     * twice as much on CPUs); the per-pixel state between launches is kept in three small buffers. */
    const uint per_row = (nx + RNG_VW - 1) / RNG_VW;
    const size_t t = get_global_id(0);
    if (t >= (size_t)rows * per_row)
        return;
    const uint r = (uint)(t / per_row), x0 = (uint)(t % per_row) * RNG_VW;
    const uint y = y0 + r, ri = r + halo_top;
    int nl = (int)nx - (int)x0;                 /* lanes inside the row */
    nl = nl < RNG_VW ? nl : RNG_VW;
    const size_t o_row = (size_t)r * nx + x0;                   /* output offset of lane 0 */
    const size_t i_row = (size_t)ri * nx + x0;                  /* input offset of lane 0 */
    const uint sbase = 4u * ramp;
    rng_real reset = 0.0, z = 0.0, sat = 0.0;
    if (g == 0 || (g & 1) == 0) {
        uint xs[RNG_VW];
        ulong pixs[RNG_VW];
        for (int l = 0; l < RNG_VW; ++l) {
            xs[l] = l < nl ? x0 + (uint)l : nx - 1u;
            pixs[l] = (ulong)y * nx + xs[l];
        }
#if RNG_VW == 1
        const rng_ulong pixv = pixs[0];
#else
        const rng_ulong pixv = RNG_PASTE(vload, RNG_SUFFIX)(0, pixs);
#endif
        if (g == 0 && ktc > 0.0) {
            rng_uint a, b, c, d;
            rng_real unused;
            ro_block(pixv, sbase + P_KTC, k0, k1, &a, &b, &c, &d);
            reset = ktc * box_muller_lanes(a, b, c, d, &unused);
        }
        rng_uint a, b, c, d;
        rng_real z_odd;
        ro_block(((ulong)(g >> 1) << 32) | pixv, sbase + P_READ, k0, k1, &a, &b, &c, &d);
        z = box_muller_lanes(a, b, c, d, &z_odd);
        ro_store_d(z_state + o_row, z_odd, nl);
        if (g == 0)
            ro_store_d(reset_state + o_row, reset, nl);
    } else {
        z = ro_load_d(z_state + o_row, nl);
    }
    if (g > 0) {
        reset = ro_load_d(reset_state + o_row, nl);
        sat = ro_load_q(sat_state + o_row, nl);
    }
    const rng_real b0 = use_bias_map ? ro_load_f(bias_map + o_row, nl) : (rng_real)bias;
    const size_t plane_in = (size_t)rows_in * nx, plane = (size_t)rows * nx;
    const int interior = nl == RNG_VW && x0 >= 1u && x0 + RNG_VW < nx;
    __global const real *gm = gmean + (size_t)g * plane_in;
    rng_real v;
    if (use_ipc) {
        v = 0.0;
        for (int dy = -1; dy <= 1; ++dy) {
            const int yy = (int)y + dy, rr = (int)ri + dy;
            const int row_ok = yy >= 0 && yy < (int)ny && rr >= 0 && rr < (int)rows_in;
            if (row_ok && interior) {
                __global const real *q = gm + (size_t)rr * nx + x0;
                for (int dx = -1; dx <= 1; ++dx)
                    v = v + ipc[(dy + 1) * 3 + (dx + 1)] * ro_load_d(q + dx, RNG_VW);
            } else {
                real s[RNG_VW + 2];       /* columns x0-1 .. x0+VW, zero outside the detector */
                for (int l = 0; l < RNG_VW + 2; ++l) {
                    const int xx = (int)x0 + l - 1;  /* lanes past the row end are not stored */
                    s[l] = (row_ok && xx >= 0 && xx < (int)nx) ? gm[(size_t)rr * nx + xx] : 0.0;
                }
                for (int dx = -1; dx <= 1; ++dx)
                    v = v + ipc[(dy + 1) * 3 + (dx + 1)] * ro_lanes(s + dx + 1);
            }
        }
    } else {
        v = ro_load_d(gm + i_row, nl);
    }
    rng_real mean = v + read_sigma * z;
    if (use_extra)
        mean = mean + ro_load_f(extra + (size_t)g * plane + o_row, nl);
    rng_real adu = ro_round(b0 + gain * (reset + mean));
    adu = RNG_SELECT(adu, (rng_real)0.0, adu < 0.0);
    adu = RNG_SELECT(adu, (rng_real)65535.0, adu > 65535.0);
    sat = RNG_SELECT(sat, (rng_real)1.0, (ro_load_q(qsat + (size_t)g * plane_in + i_row, nl) > 0.0)
                                            || (adu >= saturation));
    __global ushort *so = sci + (size_t)g * plane + o_row;
    __global uchar *go = gdq + (size_t)g * plane + o_row;
    __global uchar *ss = sat_state + o_row;
#if RNG_VW > 1
    if (nl == RNG_VW) {
        /* via int: PoCL converts real vectors to 8/16-bit lanes one by one */
        const RNG_PASTE(int, RNG_SUFFIX) si = RNG_PASTE(convert_int, RNG_SUFFIX)(sat);
        RNG_PASTE(vstore, RNG_SUFFIX)(RNG_PASTE(convert_ushort, RNG_SUFFIX)(RNG_PASTE(convert_int, RNG_SUFFIX)(adu)),
                                      0, so);
        RNG_PASTE(vstore, RNG_SUFFIX)(RNG_PASTE(convert_uchar, RNG_SUFFIX)(si * 2), 0, go);
        RNG_PASTE(vstore, RNG_SUFFIX)(RNG_PASTE(convert_uchar, RNG_SUFFIX)(si), 0, ss);
        return;
    }
#endif
    real av[RNG_VW], sv[RNG_VW];
#if RNG_VW == 1
    av[0] = adu;
    sv[0] = sat;
#else
    RNG_PASTE(vstore, RNG_SUFFIX)(adu, 0, av);
    RNG_PASTE(vstore, RNG_SUFFIX)(sat, 0, sv);
#endif
    for (int l = 0; l < nl; ++l) {
        so[l] = (ushort)av[l];
        go[l] = sv[l] > 0.0 ? (uchar)2 : (uchar)0;
        ss[l] = sv[l] > 0.0 ? (uchar)1 : (uchar)0;
    }
}
