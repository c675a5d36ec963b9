/*
 * Band-summed variance of the optimal (PSF-weighted) extraction of a point
 * source, for many targets x many candidate detector readouts.
 *
 * For target t, candidate k, bin i in [band[t,0], band[t,1]):
 *     w = sum_c  P2[i,c] / (A[k] + B[k] * Q[t,i,c])   over cells with Q <= Qsat[k]
 *     v = 1 / w            (+inf when every cell is saturated)
 *     if v is not NaN:  var_sum[t,k] += v,  nvalid[t,k] += 1
 *
 * NDRange: dimension 0 runs over groups of VW candidates, dimension 1 over
 * the targets of the current chunk.  Each work item handles VW consecutive
 * candidates with OpenCL vector types (VW = 1, 2, 4, 8 or 16, set with
 * -DVW=...).  All loads of Q and P2 are uniform scalars broadcast to the
 * vector lanes; A, B, Qsat are contiguous vector loads.  This vectorises on
 * CPU devices (PoCL) even though the kernel has inner loops; GPUs use VW=1.
 *
 * The host pads the candidate arrays to a multiple of VW (padding lanes
 * compute throw-away values), so there is no bounds branch.  The candidates
 * are shared by the targets (cand_stride = 0) or each target has its own row
 * of Kp candidates (cand_stride = Kp: A, B, Qsat are (nt, Kp)); a lane
 * computes the same operations either way.
 *
 * Q of the chunk holds only bins [lo, lo + nb); band indices are absolute.
 *
 * Cells whose weight P2[i,c] is exactly 0 are skipped: the host passes the
 * non-zero weights of each bin in CSR form (row_start[i] .. row_start[i+1]
 * index cell[] and weight[]).  Skipping is exact: A + B*Q > 0, so each
 * skipped term is +0.0 and w + 0.0 == w; the order of the other terms is kept.
 * (A NaN Q is NaN in every cell of its bin, so the bin is still skipped.)
 * Double precision by default; no fast-math build options are used, so the
 * division is IEEE correctly rounded and 1/0 = +inf, NaN propagates.  With
 * -DSINGLE (opencl.precision_options) every real is float; the sum over the
 * band's bins (up to thousands of terms) is compensated (Kahan), the sum over a
 * bin's cells (a few hundred positive terms: ~1e-7 relative, measured) is not
 * (compensating it halved the kernel's speed for no measurable gain).
 */

#include "vector_types.cl"

#ifdef SINGLE
/* s += x with the running compensation c (Kahan); a sum that becomes infinite keeps c = 0 (inf - inf
 * is NaN) */
#define KAHAN_ADD_INF(s, c, x) { const realv y_ = (x) - (c); const realv t_ = (s) + y_;                \
                                 (c) = SELECT((realv)(0.0), (t_ - (s)) - y_, isfinite(t_)); (s) = t_; }
#else
#define KAHAN_ADD_INF(s, c, x) { (s) += (x); }
#endif

__kernel void band_variance(
    __global const real *restrict Q,       /* (nt, nb, ncell), bins lo..lo+nb-1 */
    __global const real *restrict weight,     /* non-zero P2 values, bin-major   */
    __global const int *restrict cell,        /* their cell indices              */
    __global const int *restrict row_start,   /* (nlbda + 1,) CSR row pointers    */
    __global const real *restrict A,       /* (Kp,), or (nt, Kp) per target     */
    __global const real *restrict B,       /* (Kp,), or (nt, Kp) per target     */
    __global const real *restrict Qsat,    /* (Kp,), or (nt, Kp) per target     */
    __global const int *restrict band,     /* (nt, 2) absolute [i0, i1)         */
    const int Kp,                          /* padded candidate count, % VW == 0 */
    const int cand_stride,                 /* 0 (shared candidates) or Kp       */
    const int nb,
    const int ncell,
    const int lo,
    __global real *restrict var_sum,       /* (nt, Kp)                          */
    __global int *restrict nvalid)         /* (nt, Kp)                          */
{
    const int kv = get_global_id(0);       /* group of VW candidates */
    const int t = get_global_id(1);        /* target within the chunk */

    const size_t co = (size_t)t * (size_t)cand_stride;
    const realv a = VLOAD(kv, A + co);
    const realv b = VLOAD(kv, B + co);
    const realv qs = VLOAD(kv, Qsat + co);
    const int i0 = band[2 * t];
    const int i1 = band[2 * t + 1];

    __global const real *Qt = Q + (size_t)t * (size_t)nb * (size_t)ncell;
    realv acc = (realv)(0.0), acc_c = (realv)(0.0);
    longv cnt = (longv)(0);

    for (int i = i0; i < i1; ++i) {
        __global const real *q = Qt + (size_t)(i - lo) * (size_t)ncell;
        realv w = (realv)(0.0);
        const int j1 = row_start[i + 1];
        for (int j = row_start[i]; j < j1; ++j) {
            const real qc = q[cell[j]];
            const realv term = weight[j] / (a + b * qc);
            w += (qc > qs) ? (realv)(0.0) : term;   /* saturated: weight 0 */
        }
        const realv v = 1.0 / w;                      /* +inf if w == 0 */
        KAHAN_ADD_INF(acc, acc_c, isnan(v) ? (realv)(0.0) : v)   /* NaN Q: skip the bin */
        cnt += isnan(v) ? (longv)(0) : (longv)(1);
    }
    (void)acc_c;

    const size_t o = (size_t)t * (size_t)(Kp / VW) + (size_t)kv;
    VSTORE(acc, o, var_sum);
    VSTORE(CONVERT_INTV(cnt), o, nvalid);
}
