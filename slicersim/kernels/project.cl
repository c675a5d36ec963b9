/*
 * Flux-conserving projection of a spectro-imaging cube onto the detector.
 *
 * Every (sub-)cell of the cube is an axis-aligned box [ax, bx] x [ay, by]
 * on the detector [px], blurred by a Gaussian spot of rms (sx, sy) [px].
 * Its deposit is separable: pixel (c_y, c_x) receives
 *
 *     value * scale * wx[c_x - x0] * wy[c_y - y0]
 *
 * with the 1-D weight of pixel [c, c+1) (exact integral of the blurred box)
 *
 *     W(c) = [D(c+1) - D(c)] / (b - a),   D(c) = G(c - a) - G(c - b),
 *     G(u) = integral_{-inf}^{u} Phi(t / s) dt = s [t Phi(t) + phi(t)],  t = u / s,
 *
 * G(u) = max(u, 0) when s = 0 (exact area overlap of the box with the
 * pixel); a point (b = a) uses W(c) = Phi((c+1-a)/s) - Phi((c-a)/s).  The
 * Gaussian integrals come from a cubic Hermite table (absolute error
 * < 4e-12).  The window x0 .. x0 + nx - 1 covers [a - T s, b + T s]; scale =
 * factor / (sum wx * sum wy) renormalises the truncated window (sums of the
 * stored, possibly float32-rounded, weights), so that every cell deposits
 * exactly value * factor (minus what falls off the detector).
 *
 * Weight pool layout per cell: wx[0 .. nxp) (nxp = nx rounded up to VW,
 * zero padded) followed by wy[0 .. ny).
 *
 * Compile options: -DVW=1|2|4|8|16 (x vector width of the deposit),
 * -DWTYPE=float|double (weight storage), -DTMAX, -DTINV (table range and
 * density, must match the host table).
 *
 * Precision: cell_weights is double only (box coordinates up to 4096 px; the
 * tables are built once and cached) and is left out of a -DSINGLE build.
 * deposit_cells is written in `real` (vector_types.cl): with -DSINGLE
 * (and WTYPE=float) value, scale and the image are float and the program
 * holds no double, so a device without fp64 builds it.
 */

#ifndef VW
#define VW 8
#endif
#ifndef WTYPE
#define WTYPE float
#endif
#include "vector_types.cl"

#define VLOADD(p) VLOAD(0, (p))
#define VSTORED(x, p) VSTORE((x), 0, (p))
#define VLOADW(p) CONVERT_REALV(VLOAD(0, (p)))

/*
 * G and Phi through a cubic Hermite table (host-built from exact values):
 * tab[8k .. 8k+3] = cubic coefficients of Ht(t) = t Phi(t) + phi(t), tab[8k+4
 * .. 8k+7] those of Phi, on t in [t_k, t_k + 1/TINV), t_k = -TMAX + k/TINV:
 * value = ((c3 f + c2) f + c1) f + c0 with f = (t - t_k) TINV.  Absolute
 * error < 4e-12; beyond |t| = TMAX: Ht = max(t, 0), Phi = step (< 1e-17).
 */
#ifndef TMAX
#define TMAX 8.5
#endif
#ifndef TINV
#define TINV 128.0
#endif

#ifndef SINGLE            /* the tables: double only (see the header) */

/* Table evaluation for |t| < TMAX: col 0 -> Ht(t), col 1 -> Phi(t). */
inline double herm1(double t, __global const double *tab, int col)
{
    double x = (t + TMAX) * TINV;
    double fk = floor(x);
    int k = (int)fk;
    double f = x - fk;
    __global const double *c = tab + 8 * k + 4 * col;
    return ((c[3] * f + c[2]) * f + c[1]) * f + c[0];
}

/* D(c) = G(c - a) - G(c - b) for a box, Phi((c - a)/s) for a point. */
inline double edge_value(double c, double a, double b, double s, bool point, __global const double *tab)
{
    double ua = c - a, ub = c - b;
    if (s <= 0.0)
        return point ? (ua >= 0.0 ? 1.0 : 0.0) : fmax(ua, 0.0) - fmax(ub, 0.0);
    if (point)
        return fabs(ua) >= TMAX * s ? (ua >= 0.0 ? 1.0 : 0.0) : herm1(ua / s, tab, 1);
    double ga = fabs(ua) >= TMAX * s ? fmax(ua, 0.0) : s * herm1(ua / s, tab, 0);
    double gb = fabs(ub) >= TMAX * s ? fmax(ub, 0.0) : s * herm1(ub / s, tab, 0);
    return ga - gb;
}

/* Fill w[0 .. n) with the blurred-box weights of pixels c0 .. c0 + n - 1
 * (W = (D(c+1) - D(c)) / (b - a), or D(c+1) - D(c) for a point), zero-pad to
 * npad; returns the sum of the stored values. */
inline double box_weights(double a, double b, double s, int c0, int n, int npad,
                          __global WTYPE *w, __global const double *tab)
{
    double width = b - a;
    bool point = !(width > 1e-9);
    double d0 = edge_value((double)c0, a, b, s, point, tab);
    double sum = 0.0;
    for (int j = 0; j < n; ++j) {
        double d1 = edge_value((double)(c0 + j + 1), a, b, s, point, tab);
        double diff = d1 - d0;
        WTYPE v = (WTYPE)fmax(point ? diff : diff / width, 0.0);
        w[j] = v;
        sum += (double)v;
        d0 = d1;
    }
    for (int j = n; j < npad; ++j)
        w[j] = (WTYPE)0;
    return sum;
}

/* One work item per cell: weight tables and normalisation. */
__kernel void cell_weights(
    __global const double *restrict box,   /* (N, 6): ax, bx, sx, ay, by, sy [px] */
    __global const int *restrict meta,     /* (N, 4): x0, y0, nx, ny              */
    __global const long *restrict offset,  /* (N,) start of the cell's weights    */
    const long ncell,
    const double factor,                   /* value fraction per sub-cell         */
    __global const double *restrict tab,   /* Hermite table, see above            */
    __global WTYPE *restrict pool,
    __global double *restrict scale)
{
    long c = get_global_id(0);
    if (c >= ncell)
        return;
    __global const double *bx = box + 6 * c;
    int x0 = meta[4 * c], y0 = meta[4 * c + 1], nx = meta[4 * c + 2], ny = meta[4 * c + 3];
    int nxp = ((nx + VW - 1) / VW) * VW;
    __global WTYPE *w = pool + offset[c];
    double sx = box_weights(bx[0], bx[1], bx[2], x0, nx, nxp, w, tab);
    double sy = box_weights(bx[3], bx[4], bx[5], y0, ny, ny, w + nxp, tab);
    scale[c] = (sx > 0.0 && sy > 0.0) ? factor / (sx * sy) : 0.0;
}

#endif /* SINGLE */

/*
 * Deposit: one work item per "item", a contiguous range of cells of one
 * slice (a block of wavelength rows).  The host colours the items so that
 * no two items of one launch touch the same pixel (padded windows
 * included): no atomics, and every pixel receives its contributions in a
 * fixed order, so repeated runs are bit-identical.
 *
 * Sub-cell c = (s * E + e) * Q + q belongs to cube cell
 * (s * (E / ne) + e / ne) * (Q / nq) + q / nq of `value`.
 * img holds detector rows row0 .. row0 + nrows - 1 (width W).
 */
__kernel void deposit_cells(
    __global const real *restrict value,
    __global const int *restrict meta,
    __global const long *restrict offset,
    __global const WTYPE *restrict pool,
    __global const real *restrict scale,
    __global const long *restrict item_first,
    __global const long *restrict item_last,
    const int nitems,
    const int E, const int Q, const int ne, const int nq,
    __global real *restrict img,
    const int W, const int row0, const int nrows)
{
    int it = get_global_id(0);
    if (it >= nitems)
        return;
    const long EQ = (long)E * Q;
    const int Ep = E / ne, Qp = Q / nq;
    for (long c = item_first[it]; c < item_last[it]; ++c) {
        long s = c / EQ;
        long rem = c - s * EQ;
        int e = (int)(rem / Q);
        int q = (int)(rem - (long)e * Q);
        real v = value[(s * Ep + e / ne) * Qp + q / nq];
        if (v == 0)
            continue;
        v *= scale[c];
        int x0 = meta[4 * c], y0 = meta[4 * c + 1], nx = meta[4 * c + 2], ny = meta[4 * c + 3];
        int nch = (nx + VW - 1) / VW;
        __global const WTYPE *wx = pool + offset[c];
        __global const WTYPE *wy = wx + nch * VW;
        bool inside = x0 >= 0 && x0 + nch * VW <= W;
        for (int r = 0; r < ny; ++r) {
            int row = y0 + r - row0;
            if (row < 0 || row >= nrows)
                continue;
            real f = v * (real)wy[r];
            __global real *p = img + (long)row * W + x0;
            if (inside) {
                for (int ch = 0; ch < nch; ++ch) {
                    realv acc = VLOADD(p + ch * VW);
                    acc += f * VLOADW(wx + ch * VW);
                    VSTORED(acc, p + ch * VW);
                }
            } else {
                for (int j = 0; j < nch * VW; ++j) {
                    int col = x0 + j;
                    if (col >= 0 && col < W)
                        p[j] += f * (real)wx[j];
                }
            }
        }
    }
}
