/*
 * FMA throughput probe (slicersim.backends.precision.fp64_throughput_ratio):
 * 8 independent chains of n vector FMAs (VW lanes: CPUs' SIMD width; GPUs
 * VW = 1) per work item, in real (double, or float with -DSINGLE).  The ratio
 * of the double and single launch times tells whether the device has fast
 * fp64.  The result is stored so that the chains are not optimised away.
 */
#include "vector_types.cl"

__kernel void fma_chains(const int n, __global real *restrict out)
{
    const int i = get_global_id(0);
    const realv a = (realv)(0.999);
    const realv b = (realv)(1e-3);
    realv c0 = (realv)((real)i), c1 = c0 + 1, c2 = c0 + 2, c3 = c0 + 3;
    realv c4 = c0 + 4, c5 = c0 + 5, c6 = c0 + 6, c7 = c0 + 7;
    for (int k = 0; k < n; ++k) {
        c0 = fma(c0, a, b); c1 = fma(c1, a, b); c2 = fma(c2, a, b); c3 = fma(c3, a, b);
        c4 = fma(c4, a, b); c5 = fma(c5, a, b); c6 = fma(c6, a, b); c7 = fma(c7, a, b);
    }
    const realv s = ((c0 + c1) + (c2 + c3)) + ((c4 + c5) + (c6 + c7));
#if VW == 1
    out[i] = s;
#else
    real lanes[VW];
    VSTORE(s, 0, lanes);
    real t = 0;
    for (int l = 0; l < VW; ++l)
        t += lanes[l];
    out[i] = t;
#endif
}
