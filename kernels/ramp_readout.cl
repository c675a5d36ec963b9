/*
 * ramp_readout.cl: the voltage-domain end of an H4RG read chain for ramps with
 * detector effects (ramp.cl built with -DRAMP_EFFECTS=1 gives the group means of
 * the read values).  One work item = one pixel of the block's output rows, all
 * groups g of one ramp:
 *   v    = sum_{dy,dx} K[dy][dx] * gmean[g, y+dy, x+dx]   inter-pixel capacitance
 *          (3x3 kernel, rows in the halo of the block, zero outside the detector)
 *   mean = v + read_sigma * z_g + extra[g, y, x]          white read noise (the same
 *          Philox counters as the plain ramp) + correlated read noise [e-]
 *   adu  = rint(bias[y, x] + gain * (reset + mean)),  clipped to [0, 65535]
 * reset = kTC noise (plain ramp's counters).  GROUPDQ bit 2 (SATURATED) is sticky
 * from the first group flagged by the charge sampler or reaching `saturation`.
 * The NumPy twin is slicersim/backends/ramp_effects.py (readout_numpy).
 */
#define RNG_INLINE inline __attribute__((always_inline))
#include "philox.cl"

#define P_READ 1u
#define P_KTC 2u

__kernel void ramp_readout(
    __global const double *restrict gmean,   /* (n, rows_in, nx) group means [e-], rows y_in0 .. */
    __global const uchar *restrict qsat,     /* (n, rows_in, nx) charge-saturation flags */
    __global const float *restrict extra,    /* (n, rows, nx) read-domain noise [e-] or unused */
    __global const float *restrict bias_map, /* (rows, nx) [ADU] or unused */
    __constant double *ipc,                  /* 3x3, row-major */
    __global ushort *restrict sci, __global uchar *restrict gdq,   /* (n, rows, nx) */
    const uint rows, const uint nx, const uint rows_in, const uint halo_top, const uint y0,
    const uint ny, const uint ramp, const uint k0, const uint k1, const int n, const double read_sigma,
    const double gain, const double bias, const double ktc, const double saturation,
    const int use_ipc, const int use_extra, const int use_bias_map)
{
    const size_t i = get_global_id(0);
    if (i >= (size_t)rows * nx)
        return;
    const uint r = (uint)(i / nx), x = (uint)(i % nx);
    const uint y = y0 + r;                     /* detector row */
    const uint ri = r + halo_top;              /* row in gmean */
    const ulong pix = (ulong)y * nx + x;
    const uint sbase = 4u * ramp;
    double reset = 0.0;
    if (ktc > 0.0) {
        uint a, b, c, d;
        double unused;
        philox_counter(pix, sbase + P_KTC, 0u, &a, &b, &c, &d);
        philox4x32_10(&a, &b, &c, &d, k0, k1);
        reset = ktc * box_muller_lanes(a, b, c, d, &unused);
    }
    const double b0 = use_bias_map ? (double)bias_map[i] : bias;
    const size_t plane_in = (size_t)rows_in * nx, plane = (size_t)rows * nx;
    int sat = 0;
    double z_even = 0.0, z_odd = 0.0;
    for (int g = 0; g < n; ++g) {
        __global const double *gm = gmean + (size_t)g * plane_in;
        double v;
        if (use_ipc) {
            v = 0.0;
            for (int dy = -1; dy <= 1; ++dy) {
                const int yy = (int)y + dy, rr = (int)ri + dy;
                for (int dx = -1; dx <= 1; ++dx) {
                    const int xx = (int)x + dx;
                    const double s = (yy >= 0 && yy < (int)ny && xx >= 0 && xx < (int)nx && rr >= 0 &&
                                      rr < (int)rows_in) ? gm[(size_t)rr * nx + xx] : 0.0;
                    v = v + ipc[(dy + 1) * 3 + (dx + 1)] * s;
                }
            }
        } else {
            v = gm[(size_t)ri * nx + x];
        }
        if ((g & 1) == 0) {
            uint a, b, c, d;
            philox_counter((((ulong)(g >> 1)) << 32) | pix, sbase + P_READ, 0u, &a, &b, &c, &d);
            philox4x32_10(&a, &b, &c, &d, k0, k1);
            z_even = box_muller_lanes(a, b, c, d, &z_odd);
        }
        double mean = v + read_sigma * ((g & 1) ? z_odd : z_even);
        if (use_extra)
            mean = mean + (double)extra[(size_t)g * plane + i];
        double adu = rint(b0 + gain * (reset + mean));
        adu = adu < 0.0 ? 0.0 : adu;
        adu = adu > 65535.0 ? 65535.0 : adu;
        sat = sat || qsat[(size_t)g * plane_in + (size_t)ri * nx + x] || (adu >= saturation);
        sci[(size_t)g * plane + i] = (ushort)adu;
        gdq[(size_t)g * plane + i] = sat ? (uchar)2 : (uchar)0;
    }
}
