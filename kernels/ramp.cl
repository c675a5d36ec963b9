/*
 * ramp.cl: per-frame up-the-ramp sampling of MACC(n, m, d) H4RG ramps.
 *
 * One work item = one pixel of one ramp; it walks the n(m+d)-d frames of the
 * ramp.  Random numbers come from Philox4x32-10 keyed by
 *   key = seed, counter = (pixel, frame or group, 4*ramp + purpose, attempt)
 * (see slicersim/rng.py), so the output is the same for any work-group size,
 * chunking or device count.  The NumPy twin is slicersim/ramps.py
 * (_simulate_block_numpy); both use the same operations in the same order and
 * agree bit for bit.
 *
 * Paths (chosen from the expected charge only, never from a draw):
 *   dense : Poisson increment of mean mu = rate*t_f + glow in every frame
 *           (inversion below 10, PTRS above; optional Gaussian approximation
 *           above gauss_min_mean, rounded to an integer and clipped at 0);
 *   sparse: mu*(m+d) < sparse_max_group: total count N ~ Poisson(mu*F), then
 *           the N events are spread over the F frames with sequential
 *           binomials Bin(R, 1/(F-k)) (exact: uniform arrival frames), which
 *           costs nothing in frames where no event is left.
 * Charge is clipped at the full well; the m reads of a group are averaged and
 * carry read noise of variance ron^2/m (one Gaussian per group, exactly the
 * distribution of the mean of m independent reads); the reset level adds kTC
 * noise once per ramp; output = rint(bias + gain*(kTC + mean)) clipped to
 * [0, 65535] as uint16; GROUPDQ bit 2 (SATURATED) from the first group whose
 * charge reached the full well or whose ADU hit the saturation level.
 */
#include "philox.cl"
#include "noise.cl"

#define P_POISSON 0u
#define P_READ 1u
#define P_KTC 2u
#define P_SPARSE 3u

/* Poisson increment of one frame.  Inversion (mu < 10) uses one uniform; frames
 * 2k and 2k+1 share one Philox block (words x,y and z,w).  PTRS (mu >= 10) and
 * the Gaussian approximation (mu >= gauss_min_mean) key their own blocks. */
inline double frame_increment(const double mu, const double exp_neg_mu, const uint2 key, const uint pix,
                              const int frame, const uint stream, const double gauss_min_mean)
{
    if (mu <= 0.0)
        return 0.0;
    if (mu >= gauss_min_mean) {
        const uint4 w = philox_block(key, ((ulong)(frame >> 1) << 32) | (ulong)pix, stream, 1u);
        const double2 z = box_muller(w);
        const double k = rint(mu + sqrt(mu) * ((frame & 1) ? z.y : z.x));
        return k > 0.0 ? k : 0.0;
    }
    if (mu >= PTRS_MIN_MEAN)
        return poisson_ptrs(mu, key, ((ulong)frame << 32) | (ulong)pix, stream + 0x80000000u);
    const uint4 w = philox_block(key, ((ulong)(frame >> 1) << 32) | (ulong)pix, stream, 0u);
    const double u = (frame & 1) ? philox_u01(w.z, w.w) : philox_u01(w.x, w.y);
    double p = exp_neg_mu;
    double cdf = p;
    double k = 0.0;
    while (u > cdf && p > 0.0) {
        k = k + 1.0;
        p = p * mu / k;
        cdf = cdf + p;
    }
    return k;
}

/* Binomial(R, p) by inversion of the CDF, one uniform (R small: sparse path). */
inline double binomial_inversion(const double R, const double p, const double u)
{
    if (p >= 1.0)
        return R;
    const double q = 1.0 - p;
    double prob = rng_exp(R * rng_log(q));
    double cdf = prob;
    double x = 0.0;
    const double ratio = p / q;
    while (u > cdf && x < R) {
        prob = prob * ((R - x) / (x + 1.0)) * ratio;
        x = x + 1.0;
        cdf = cdf + prob;
    }
    return x;
}

__kernel void macc_ramp(__global const double *restrict mu_frame,   /* e-/frame per pixel */
                        __global const uchar *restrict dead,         /* 1 = no charge collected */
                        __global ushort *restrict sci,               /* (ngroups, npix) */
                        __global uchar *restrict gdq,                /* (ngroups, npix) */
                        const uint npix, const uint pixel0, const uint ramp,
                        const uint key0, const uint key1, const int n, const int m, const int d,
                        const double ron, const double gain, const double bias, const double ktc,
                        const double full_well, const double saturation,
                        const double sparse_max_group, const double gauss_min_mean)
{
    const uint i = get_global_id(0);
    if (i >= npix)
        return;
    const uint2 key = (uint2)(key0, key1);
    const uint pix = pixel0 + i;
    const double mu = dead[i] ? 0.0 : mu_frame[i];
    const int nframes = n * (m + d) - d;
    const uint sbase = 4u * ramp;
    const double read_sigma = ron / sqrt((double)m);

    double reset = 0.0;
    if (ktc > 0.0)
        reset = ktc * box_muller(philox_block(key, (ulong)pix, sbase + P_KTC, 0u)).x;

    const int sparse = mu * (double)(m + d) < sparse_max_group;
    const double exp_neg_mu = rng_exp(-mu);
    double remaining = 0.0;
    if (sparse && mu > 0.0) {
        const double mt = mu * (double)nframes;
        remaining = mt < PTRS_MIN_MEAN ? poisson_inversion(mt, key, (ulong)pix, sbase + P_SPARSE)
                                       : poisson_ptrs(mt, key, (ulong)pix, sbase + P_SPARSE);
    }

    double charge = 0.0;
    int saturated = 0;
    int frame = 0;
    double2 z2 = (double2)(0.0, 0.0);
    for (int g = 0; g < n; ++g) {
        double sum = 0.0;
        const int last = (g == n - 1) ? m : m + d;
        if (sparse && remaining == 0.0) {        /* nothing left to collect: constant charge */
            sum = charge * (double)m;
            frame += last;
        } else {
            for (int j = 0; j < last; ++j, ++frame) {
                double inc = 0.0;
                if (sparse) {
                    if (remaining > 0.0) {
                        const uint4 w = philox_block(key, ((ulong)(frame + 1) << 32) | (ulong)pix,
                                                     sbase + P_SPARSE, 1u);
                        inc = binomial_inversion(remaining, 1.0 / (double)(nframes - frame),
                                                 philox_u01(w.x, w.y));
                        remaining = remaining - inc;
                    }
                } else {
                    inc = frame_increment(mu, exp_neg_mu, key, pix, frame, sbase + P_POISSON, gauss_min_mean);
                }
                charge = charge + inc;
                if (charge >= full_well) {
                    charge = full_well;
                    saturated = 1;
                }
                if (j < m)
                    sum = sum + charge;
            }
        }
        if ((g & 1) == 0)
            z2 = box_muller(philox_block(key, ((ulong)(g >> 1) << 32) | (ulong)pix, sbase + P_READ, 0u));
        const double z = (g & 1) ? z2.y : z2.x;
        const double mean = sum / (double)m + read_sigma * z;
        double adu = rint(bias + gain * (reset + mean));
        adu = adu < 0.0 ? 0.0 : (adu > 65535.0 ? 65535.0 : adu);
        if (adu >= saturation)
            saturated = 1;
        sci[(size_t)g * npix + i] = (ushort)adu;
        gdq[(size_t)g * npix + i] = saturated ? (uchar)2 : (uchar)0;
    }
}
