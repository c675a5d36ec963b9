/*
 * 2-D linear convolution of a batch of planes (one kernel per plane, or one
 * shared kernel: kstride = 0), 'same' output grid, zero outside the field.
 *
 * Direct:  the host zero-pads every plane into P (B, PY, PX) with the image
 * at offset (ky/2, kx/2) and flips the kernel (Kf[a, c] = K[ky-1-a, kx-1-c]),
 * so that
 *     out[b, y, x] = sum_{a < ky} sum_{c < kx} Kf[b, a, c] P[b, y + a, x + c]
 * with no bounds tests.
 *   convolve_direct:       NDRange (nxo / VW, nyo, B); each work item makes VW
 *                          consecutive outputs of a row with vector loads
 *                          (CPU devices; VW = 1 on GPUs).
 *   convolve_direct_tiled: work group (TX, TY); the (TY + KY - 1) x
 *                          (TX + KX - 1) input tile is staged in local memory
 *                          (GPUs).  TX, TY, KY, KX are build options.
 *
 * FFT helpers (transforms in fft.cl), complex planes (B, Ny, Nx):
 *   pack_planes:    Z_b = image_b / max|image_b| + i kernel_b / max|kernel_b|, both
 *                   zero-padded at the origin.  The scaling matters: the two halves
 *                   share one transform, so rounding errors are relative to the
 *                   larger of the two (a 1e-20 erg/s/cm2/A plane next to a kernel
 *                   of order 0.1 would be lost); crop_pairs undoes it.
 *   multiply_pairs: from Z_b(m) and conj Z_b(-m) the spectra of image and
 *                   kernel, A = (Z + Z*)/2, K = (Z - Z*)/(2i), so the product
 *                   is A K = -i (Z^2 - Z*^2) / 4; planes 2q and 2q+1 are packed
 *                   as W_q = P_2q + i P_2q+1 (both inverse transforms are real).
 *   crop_pairs:     out_2q = Re w_q scale_2q, out_2q+1 = Im w_q scale_2q+1 at
 *                   offset (ky/2, kx/2) of the full linear convolution, with
 *                   scale_b = max|image_b| max|kernel_b| / (Ny Nx).
 */

#include "vector_types.cl"

__kernel void convolve_direct(
    __global const real *restrict P,    /* (B, PY, PX) zero-padded planes   */
    __global const real *restrict Kf,   /* (B or 1, ky, kx) flipped kernels */
    const int ky, const int kx,
    const int PY, const int PX,
    const int kstride,                    /* ky * kx, or 0 for a shared kernel */
    const int nyo, const int nxo,         /* output plane, nxo % VW == 0      */
    __global real *restrict out)        /* (B, nyo, nxo)                    */
{
    const int xv = get_global_id(0);
    const int y = get_global_id(1);
    const int b = get_global_id(2);
    __global const real *Pb = P + (size_t)b * (size_t)PY * (size_t)PX
                                  + (size_t)y * (size_t)PX + (size_t)xv * VW;
    __global const real *K = Kf + (size_t)b * (size_t)kstride;
    realv acc = (realv)(0.0);
    for (int a = 0; a < ky; ++a) {
        __global const real *row = Pb + (size_t)a * (size_t)PX;
        __global const real *krow = K + a * kx;
        for (int c = 0; c < kx; ++c)
            acc += krow[c] * VLOAD(0, row + c);
    }
    VSTORE(acc, 0, out + ((size_t)b * (size_t)nyo + (size_t)y) * (size_t)nxo + (size_t)xv * VW);
}

#if defined(TX) && defined(TY) && defined(KY) && defined(KX)
#define TW (TX + KX - 1)
#define TH (TY + KY - 1)
__kernel __attribute__((reqd_work_group_size(TX, TY, 1)))
void convolve_direct_tiled(
    __global const real *restrict P,    /* (B, PY, PX), PY >= nyo + KY - 1  */
    __global const real *restrict Kf,   /* (B or 1, KY, KX) flipped kernels  */
    const int PY, const int PX,
    const int kstride,
    const int nyo, const int nxo,         /* multiples of TY, TX               */
    __global real *restrict out)        /* (B, nyo, nxo)                     */
{
    __local real tile[TH * TW];
    const int lx = get_local_id(0), ly = get_local_id(1);
    const int x0 = get_group_id(0) * TX, y0 = get_group_id(1) * TY;
    const int b = get_global_id(2);
    __global const real *Pb = P + (size_t)b * (size_t)PY * (size_t)PX;
    for (int idx = ly * TX + lx; idx < TH * TW; idx += TX * TY) {
        const int ty = idx / TW, tx = idx - ty * TW;
        tile[idx] = Pb[(size_t)(y0 + ty) * (size_t)PX + (size_t)(x0 + tx)];
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    __global const real *K = Kf + (size_t)b * (size_t)kstride;
    real acc = 0.0;
    for (int a = 0; a < KY; ++a)
        for (int c = 0; c < KX; ++c)
            acc += K[a * KX + c] * tile[(ly + a) * TW + lx + c];
    out[((size_t)b * (size_t)nyo + (size_t)(y0 + ly)) * (size_t)nxo + (size_t)(x0 + lx)] = acc;
}
#endif

__kernel void pack_planes(
    __global const real *restrict img,  /* (B, ny, nx); planes b >= nb are zero */
    __global const real *restrict kern, /* (B or 1, ky, kx)                      */
    __global const real *restrict inv,  /* (nb, 2): 1/max|img_b|, 1/max|kern_b|  */
    const int nb, const int ny, const int nx,
    const int ky, const int kx, const int kstride,
    const int Ny, const int Nx,
    __global real2 *restrict Z)         /* (B, Ny, Nx)                           */
{
    const int x = get_global_id(0), y = get_global_id(1), b = get_global_id(2);
    real re = 0.0, im = 0.0;
    if (b < nb) {
        if (y < ny && x < nx)
            re = img[((size_t)b * ny + y) * nx + x] * inv[2 * b];
        if (y < ky && x < kx)
            im = kern[(size_t)b * kstride + y * kx + x] * inv[2 * b + 1];
    }
    Z[((size_t)b * Ny + y) * Nx + x] = (real2)(re, im);
}

__kernel void multiply_pairs(
    __global const real2 *restrict Z,   /* (2 B2, Ny, Nx) forward transforms */
    const int Ny, const int Nx,
    __global real2 *restrict W)         /* (B2, Ny, Nx)                      */
{
    const int x = get_global_id(0), y = get_global_id(1), q = get_global_id(2);
    const int xm = (x == 0) ? 0 : Nx - x, ym = (y == 0) ? 0 : Ny - y;
    real2 prod[2];
    for (int h = 0; h < 2; ++h) {
        const size_t plane = (size_t)(2 * q + h) * Ny;
        const real2 z = Z[(plane + y) * Nx + x];
        const real2 zm = Z[(plane + ym) * Nx + xm];
        /* Z^2 - conj(Zm)^2, then times -i/4 */
        const real2 d = (real2)(z.x * z.x - z.y * z.y - zm.x * zm.x + zm.y * zm.y,
                                    2.0 * (z.x * z.y + zm.x * zm.y));
        prod[h] = (real2)(0.25 * d.y, -0.25 * d.x);
    }
    W[((size_t)q * Ny + y) * Nx + x] = (real2)(prod[0].x - prod[1].y, prod[0].y + prod[1].x);
}

__kernel void crop_pairs(
    __global const real2 *restrict W,   /* (B2, Ny, Nx) inverse transforms */
    const int nb, const int ny, const int nx,
    const int oy, const int ox,           /* ky/2, kx/2                     */
    const int Ny, const int Nx,
    __global const real *restrict scale,/* (nb,) max|img| max|kern| / (Ny Nx) */
    __global real *restrict out)        /* (nb, ny, nx)                   */
{
    const int x = get_global_id(0), y = get_global_id(1), q = get_global_id(2);
    const real2 w = W[((size_t)q * Ny + y + oy) * Nx + x + ox];
    out[((size_t)(2 * q) * ny + y) * nx + x] = w.x * scale[2 * q];
    if (2 * q + 1 < nb)
        out[((size_t)(2 * q + 1) * ny + y) * nx + x] = w.y * scale[2 * q + 1];
}
