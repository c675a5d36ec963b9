/*
 * correlated_noise.cl: random Fourier coefficients of Gaussian noise streams with a given PSD
 * (slicersim/backends/correlated_noise.py; NumPy twin: spectral_coefficients_numpy).
 *
 * spectral_coefficients: row r of the output, bin k:
 *     X[r, k] = amp[kind[r], k] * (z0 + i z1)
 * where (z0, z1) are the two Box-Muller normals of the Philox4x32-10 block with
 * counter (index = (hi[r] << 32) | k, stream[r], draw[r]) and key (key0, key1) -
 * the double-precision draws of philox.cl, bit-identical to slicersim.backends.rng.normal.
 * The product is formed in double and rounded once to float, as the twin does.
 * Work item (k0, r): bins k0*RNG_VW ... k0*RNG_VW + RNG_VW - 1 of row r (nbins a multiple
 * of RNG_VW: rows are padded).
 */
#include "philox.cl"

__kernel void spectral_coefficients(__global const float *restrict amp, __global const uint *restrict kind,
                                    __global const uint *restrict hi, __global const uint *restrict stream,
                                    __global const uint *restrict draw, const uint nbins,
                                    const uint key0, const uint key1, __global float *restrict out)
{
    const size_t g = get_global_id(0);
    const size_t r = get_global_id(1);
    if (g * RNG_VW >= nbins)
        return;
    const ulong k0 = g * RNG_VW;
    rng_uint a, b, c, d;
    philox_counter(((rng_ulong)(((ulong)hi[r] << 32) | k0)) + RNG_LANES, stream[r], draw[r], &a, &b, &c, &d);
    philox4x32_10(&a, &b, &c, &d, key0, key1);
    rng_double zs;
    const rng_double zc = box_muller_lanes(a, b, c, d, &zs);
    const rng_double w = RNG_PASTE(convert_double, RNG_SUFFIX)(RNG_VLOAD(g, amp + (size_t)kind[r] * nbins));
    float re[RNG_VW], im[RNG_VW];
    RNG_VSTORE(RNG_PASTE(convert_float, RNG_SUFFIX)(w * zc), 0, re);
    RNG_VSTORE(RNG_PASTE(convert_float, RNG_SUFFIX)(w * zs), 0, im);
    __global float *o = out + 2 * ((size_t)r * nbins + k0);
    for (int l = 0; l < RNG_VW; l++) {
        o[2 * l] = re[l];
        o[2 * l + 1] = im[l];
    }
}
