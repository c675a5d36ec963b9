/*
 * Fused point-source cube: LSF, QE, signal and Rauscher07 variance of a
 * wavelength chunk in one pass, from small inputs (no product cube G P).
 *
 * For output bin i (global index, i0 <= i < i1), cell (y, x):
 *
 *   photons   C = sum_t w_t [G_j P_j(y, x) + H_j(y, x)] + U_i     [ph/s/cell]
 *                 j = reflect(i + t - NTAPS/2): mirror about the outer edges
 *                 of the whole grid of nl bins (scipy's "reflect", period 2 nl)
 *   electrons e = QE_i C                                          [e-/s/cell]
 *   signal    S = e t_int g r                                     [ADU]
 *   variance  V = r A + r B e   (Rauscher07, linear in e)         [ADU^2]
 *   saturated e > e_sat  ->  S = NaN, V = +inf
 *
 * P is the separable erf product fy[j, y] fx[j, x] (SEPARABLE=1) or a full
 * block P[j, y, x] (SEPARABLE=0, e.g. Airy); H (HAS_HOST=1) is an extended
 * source already blurred by the PSF [ph/s/cell]; HAS_POINT=0 drops G P.
 * The input blocks hold bins lo .. lo + nb - 1 (the chunk plus the LSF halo).
 * Each voxel's arithmetic depends only on its own inputs, never on the chunk.
 *
 * NDRange (ceil(nvec_row / nvec), ny, planes of the launch), nvec_row = ceil(nx / VW):
 * a work item does nvec consecutive vectors of VW cells of row (y, i) with
 * explicit vector types.  CPUs (PoCL): VW = preferred real width and a
 * whole row per work item, so the per-row tap factors are computed once and
 * the inner loop is NTAPS vector FMAs.  GPUs: VW = 1, nvec = 1, consecutive
 * work items write consecutive cells.  The last vector of a row may be
 * partial (nx % VW): fx rows are zero-padded to nxp = whole vectors by the
 * host; P and H rows are loaded lane by lane there, and outputs stored so.
 * Arithmetic in real (real; float with -DSINGLE, then every input is
 * float too); OUT (real or float) is only the storage type of signal and
 * variance.
 */

#include "vector_types.cl"

#ifndef OUT
#define OUT real
#endif
#ifndef SEPARABLE
#define SEPARABLE 1
#endif
#ifndef HAS_POINT
#define HAS_POINT 1
#endif
#ifndef HAS_HOST
#define HAS_HOST 0
#endif
#ifndef NTAPS
#define NTAPS 1
#endif

#if VW == 1
#define TO_OUT(x) ((OUT)(x))
#else
#define TO_OUT(x) CONVERT_V(OUT, x)
#endif

/* Index of bin j on a grid of n bins extended by mirror images (period 2n). */
inline int reflect_index(int j, const int n)
{
    if (j >= 0 && j < n)
        return j;
    const int period = 2 * n;
    j %= period;
    if (j < 0)
        j += period;
    return j < n ? j : period - 1 - j;
}

/* VW cells row[x0 .. x0 + VW - 1]; lanes at x >= nx read as 0. */
inline realv load_cells(__global const real *restrict row, const int x0, const int nx)
{
    if (x0 + VW <= nx)
        return VLOAD(0, row + x0);
    real lanes[VW];
    for (int t = 0; t < VW; ++t)
        lanes[t] = (x0 + t < nx) ? row[x0 + t] : 0.0;
    return VLOAD(0, lanes);
}

__kernel void pointsource_cube(
    __global const real *restrict psf_a,    /* SEPARABLE: fy (nb, ny); else P (nb, ny, nx) */
    __global const real *restrict psf_b,    /* SEPARABLE: fx (nb, nxp), rows zero-padded    */
    __global const real *restrict host,     /* HAS_HOST: H (nb, ny, nx) [ph/s/cell]         */
    __global const real *restrict rate,     /* (nb,) G = F f2p [ph/s]                       */
    __global const real *restrict uniform,  /* (nc,) U of the output bins [ph/s/cell]        */
    __global const real *restrict qe,       /* (nc,) [e-/ph]                                 */
    __global const real *restrict taps,     /* (NTAPS,) LSF weights, offsets -h .. h         */
    const int nl, const int lo, const int i0, const int c0, const int ny, const int nx, const int nxp,
    const int nvec,
    const real signal_scale,                /* t_int g r [ADU per e-/s]                      */
    const real var_a, const real var_b,   /* r A [ADU^2], r B [ADU^2 per e-/s]             */
    const real e_sat,                       /* saturation rate [e-/s/cell]                   */
    __global OUT *restrict signal,            /* planes c0 .. c0 + nplanes - 1 [ADU]           */
    __global OUT *restrict variance)          /* same planes [ADU^2]                           */
{
    const int y = (int)get_global_id(1);
    const int c = c0 + (int)get_global_id(2);  /* output bin i0 + c; stored at plane c - c0 */
    const int i = i0 + c;
    /* per tap: offset of the input row and the row's scalar factor */
    size_t row[NTAPS];
    real coef[NTAPS];
#if HAS_HOST
    size_t cells[NTAPS];
#endif
    for (int t = 0; t < NTAPS; ++t) {
        const size_t j = (size_t)(reflect_index(i + t - NTAPS / 2, nl) - lo);
#if HAS_HOST
        cells[t] = (j * (size_t)ny + (size_t)y) * (size_t)nx;
#endif
#if HAS_POINT && SEPARABLE
        row[t] = j * (size_t)nxp;
        coef[t] = rate[j] * psf_a[j * (size_t)ny + (size_t)y];
#elif HAS_POINT
        row[t] = (j * (size_t)ny + (size_t)y) * (size_t)nx;
        coef[t] = rate[j];
#else
        row[t] = 0;
        coef[t] = 0.0;
#endif
#if !HAS_HOST
        coef[t] *= taps[t];                 /* fold the LSF weight into the row factor */
#endif
    }
#if HAS_POINT && SEPARABLE
    __global const real *restrict prow = psf_b;
#else
    __global const real *restrict prow = psf_a;
#endif
    const real qe_c = qe[c], u_c = uniform[c];
    const size_t plane = ((size_t)get_global_id(2) * (size_t)ny + (size_t)y) * (size_t)nx;
    for (int v = 0; v < nvec; ++v) {
        const int x0 = ((int)get_global_id(0) * nvec + v) * VW;
        if (x0 >= nx)
            break;
        realv acc = (realv)(0.0);
        for (int t = 0; t < NTAPS; ++t) {
#if HAS_HOST && HAS_POINT
            acc += taps[t] * (coef[t] * load_cells(prow + row[t], x0, nx) + load_cells(host + cells[t], x0, nx));
#elif HAS_HOST
            acc += taps[t] * load_cells(host + cells[t], x0, nx);
#elif SEPARABLE
            acc += coef[t] * VLOAD(0, prow + row[t] + x0);      /* padded rows: whole vectors */
#else
            acc += coef[t] * load_cells(prow + row[t], x0, nx);
#endif
        }
        const realv e = qe_c * (acc + u_c);
        const maskv sat = GREATER(e, (realv)(e_sat));
        const realv s = SELECT(e * signal_scale, (realv)(NAN), sat);
        const realv var = SELECT(var_a + var_b * e, (realv)(INFINITY), sat);
        const size_t o = plane + (size_t)x0;
        if (x0 + VW <= nx) {
            VSTORE(TO_OUT(s), 0, signal + o);
            VSTORE(TO_OUT(var), 0, variance + o);
        } else {
            OUT s_l[VW], v_l[VW];
            VSTORE(TO_OUT(s), 0, s_l);
            VSTORE(TO_OUT(var), 0, v_l);
            for (int t = 0; t < nx - x0; ++t) {
                signal[o + t] = s_l[t];
                variance[o + t] = v_l[t];
            }
        }
    }
}
