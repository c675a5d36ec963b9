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
 * coalesces on GPUs (VW = 1).  Double precision, no fast-math.
 */

#if defined(cl_khr_fp64)
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#endif

#ifndef VW
#define VW 1
#endif

#if VW == 1
typedef double realv;
#define VLOAD(o, p) ((p)[o])
#define VSTORE(x, o, p) ((p)[o] = (x))
#elif VW == 2
typedef double2 realv;
#define VLOAD(o, p) vload2((o), (p))
#define VSTORE(x, o, p) vstore2((x), (o), (p))
#elif VW == 4
typedef double4 realv;
#define VLOAD(o, p) vload4((o), (p))
#define VSTORE(x, o, p) vstore4((x), (o), (p))
#elif VW == 8
typedef double8 realv;
#define VLOAD(o, p) vload8((o), (p))
#define VSTORE(x, o, p) vstore8((x), (o), (p))
#else
#error "VW must be 1, 2, 4 or 8"
#endif

__kernel void lsf_band_apply(
    __global const double *restrict x,      /* (n, npix_p)                 */
    __global const double *restrict band,   /* (n, bw) matrix band values  */
    __global const int *restrict jlo,       /* (n,) first input bin of row */
    __global const int *restrict nband,     /* (n,) entries used in row    */
    const int npix_p,                       /* padded pixels, % VW == 0    */
    const int bw,
    __global double *restrict out)          /* (n, npix_p)                 */
{
    const int pv = get_global_id(0);
    const int k = get_global_id(1);
    const int j0 = jlo[k];
    const int m = nband[k];
    __global const double *w = band + (size_t)k * (size_t)bw;
    __global const double *xs = x + (size_t)j0 * (size_t)npix_p;
    realv acc = (realv)(0.0);
    for (int t = 0; t < m; ++t)
        acc += w[t] * VLOAD(pv, xs + (size_t)t * (size_t)npix_p);
    VSTORE(acc, pv, out + (size_t)k * (size_t)npix_p);
}
