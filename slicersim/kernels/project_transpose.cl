/*
 * Transpose of the flux-conserving projection (project.cl): detector image -> cube cells.
 *
 * The deposit puts value * scale * wx[c_x - x0] * wy[c_y - y0] on pixel (c_y, c_x) for
 * every (sub-)cell; its transpose gives every cube cell
 *
 *     out[p] = sum over the sub-cells c of p of  scale_c^k * sum_r wy[r]^k * sum_j wx[j]^k * img[y0 + r, x0 + j]
 *
 * with k = POWER = 1 (P^T img) or 2 (the squared weights, P∘P)^T img, used to propagate a
 * variance image through a pixel-to-cell sum).  Same table layout as project.cl: per cell
 * wx[0 .. nxp) (zero padded to a multiple of VW) then wy[0 .. ny).  Pixels off the detector
 * or outside the image band row0 .. row0 + nrows - 1 count as zero.
 *
 * One work item per cube cell (it loops over its ne x nq sub-cells): every output is
 * written by one item, so no atomics and a fixed summation order (bit-identical reruns).
 *
 * Compile options: -DVW=1|2|4|8|16, -DWTYPE=float|double (as project.cl).
 */

#ifndef VW
#define VW 8
#endif
#ifndef WTYPE
#define WTYPE float
#endif
#include "vector_types.cl"

#define VLOADD(p) VLOAD(0, (p))
#define VLOADW(p) CONVERT_REALV(VLOAD(0, (p)))

/* Sum of the lanes of a realv. */
inline double lane_sum(realv v)
{
#if VW == 1
    return v;
#elif VW == 2
    return v.s0 + v.s1;
#elif VW == 4
    return (v.s0 + v.s1) + (v.s2 + v.s3);
#elif VW == 8
    double4 h = v.lo + v.hi;
    return (h.s0 + h.s1) + (h.s2 + h.s3);
#else
    double8 g = v.lo + v.hi;
    double4 h = g.lo + g.hi;
    return (h.s0 + h.s1) + (h.s2 + h.s3);
#endif
}

__kernel void gather_cells(
    __global const double *restrict img,     /* image rows row0 .. row0 + nrows - 1, width W */
    __global const int *restrict meta,       /* (N, 4): x0, y0, nx, ny                       */
    __global const long *restrict offset,    /* (N,) start of the cell's weights             */
    __global const WTYPE *restrict pool,
    __global const double *restrict scale,
    const long ncube,                        /* cube cells: S * (E / ne) * (Q / nq)          */
    const int E, const int Q, const int ne, const int nq,
    const int power,                         /* 1 or 2                                      */
    const int W, const int row0, const int nrows,
    __global double *restrict out)
{
    long p = get_global_id(0);
    if (p >= ncube)
        return;
    const int Ep = E / ne, Qp = Q / nq;
    const long per_slice = (long)Ep * Qp;
    long s = p / per_slice;
    long rem = p - s * per_slice;
    int ep = (int)(rem / Qp);
    int qp = (int)(rem - (long)ep * Qp);
    double total = 0.0;
    for (int a = 0; a < ne; ++a) {
        for (int b = 0; b < nq; ++b) {
            long c = (s * E + (long)ep * ne + a) * Q + (long)qp * nq + b;
            double sc = scale[c];
            if (sc == 0.0)
                continue;
            int x0 = meta[4 * c], y0 = meta[4 * c + 1], nx = meta[4 * c + 2], ny = meta[4 * c + 3];
            int nch = (nx + VW - 1) / VW;
            __global const WTYPE *wx = pool + offset[c];
            __global const WTYPE *wy = wx + nch * VW;
            bool inside = x0 >= 0 && x0 + nch * VW <= W;
            double acc = 0.0;
            for (int r = 0; r < ny; ++r) {
                int row = y0 + r - row0;
                if (row < 0 || row >= nrows)
                    continue;
                __global const double *q = img + (long)row * W + x0;
                double line = 0.0;
                if (inside) {
                    realv v = (realv)(0.0);
                    for (int ch = 0; ch < nch; ++ch) {
                        realv w = VLOADW(wx + ch * VW);
                        v += (power == 2 ? w * w : w) * VLOADD(q + ch * VW);
                    }
                    line = lane_sum(v);
                } else {
                    for (int j = 0; j < nx; ++j) {
                        int col = x0 + j;
                        if (col >= 0 && col < W) {
                            double w = (double)wx[j];
                            line += (power == 2 ? w * w : w) * q[j];
                        }
                    }
                }
                double wr = (double)wy[r];
                acc += (power == 2 ? wr * wr : wr) * line;
            }
            total += (power == 2 ? sc * sc : sc) * acc;
        }
    }
    out[p] = total;
}
