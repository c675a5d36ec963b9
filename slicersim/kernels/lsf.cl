/*
 * Line-spread function along the wavelength axis as a banded mixing matrix.
 *
 *     out[k, p] = sum_{t < nband[k]}  band[k, t] * x[jlo[k] + t, p]
 *
 * x is (n, npix) with the wavelength index first and the pixels of the cube
 * flattened and contiguous.  Row k of the matrix holds the weights of the
 * input bins jlo[k] .. jlo[k] + nband[k] - 1 that land in output bin k; the
 * host builds it (reflect folding at the edges, constant or varying sigma),
 * so this kernel is a plain band-matrix product and conserves whatever the
 * matrix conserves.
 *
 * NDRange: dimension 0 runs over groups of VW consecutive pixels (the host
 * pads npix to a multiple of VW), dimension 1 over output bins k.  The
 * weights are uniform per work item group along dimension 0 and the pixel
 * loads are contiguous vector loads, which vectorises on CPUs (PoCL) and
 * coalesces on GPUs (VW = 1).  real: real, or float with -DSINGLE; no fast-math.
 */

#include "vector_types.cl"

__kernel void lsf_band_apply(
    __global const real *restrict x,      /* (n, npix_p)                 */
    __global const real *restrict band,   /* (n, bw) matrix band values  */
    __global const int *restrict jlo,       /* (n,) first input bin of row */
    __global const int *restrict nband,     /* (n,) entries used in row    */
    const int npix_p,                       /* padded pixels, % VW == 0    */
    const int bw,
    __global real *restrict out)          /* (n, npix_p)                 */
{
    const int pv = get_global_id(0);
    const int k = get_global_id(1);
    const int j0 = jlo[k];
    const int m = nband[k];
    __global const real *w = band + (size_t)k * (size_t)bw;
    __global const real *xs = x + (size_t)j0 * (size_t)npix_p;
    realv acc = (realv)(0.0);
    for (int t = 0; t < m; ++t)
        acc += w[t] * VLOAD(pv, xs + (size_t)t * (size_t)npix_p);
    VSTORE(acc, pv, out + (size_t)k * (size_t)npix_p);
}
