"""Random streams of the selected OpenCL device against the NumPy twin (run by device_suite.sh):
how many uniforms and Gaussians differ, the Poisson counts, and a probe of the Philox helpers'
intermediate values (default build and -cl-opt-disable) to locate a driver's divergence."""
import numpy as np

from slicersim.backends import noise as cn
from slicersim.backends import opencl, rng

un, zn = cn.uniform_normal_draw(100001, 2**63 + 12345, 5, 2, backend="numpy")
uc, zc = cn.uniform_normal_draw(100001, 2**63 + 12345, 5, 2, backend="opencl")
for name, a, b in (("uniform", un, uc), ("normal", zn, zc)):
    d = np.abs(a - b)
    print(name, "differing:", int((a != b).sum()), "of", a.size, "max |diff|", float(d.max()))
for mu in (1e-3, 1.0, 30.0, 1e4):
    k = cn.poisson_draw(np.full(100000, mu), seed=7, backend="opencl")
    kn = cn.poisson_draw(np.full(100000, mu), seed=7, backend="numpy")
    print("poisson", mu, "mean", k.mean(), "var", k.var(), "numpy mean", kn.mean(),
          "identical", bool(np.array_equal(k, kn)))

PROBE = r"""
#include "philox.cl"
__kernel void probe(__global ulong *w, __global double *d, const uint k0, const uint k1, const uint stream)
{
    const size_t i = get_global_id(0);
    uint a, b, c, e;
    philox_counter((ulong)i, stream, 0u, &a, &b, &c, &e);
    philox4x32_10(&a, &b, &c, &e, k0, k1);
    w[4 * i] = a; w[4 * i + 1] = b; w[4 * i + 2] = c; w[4 * i + 3] = e;
    double s;
    d[8 * i + 0] = philox_u01(a, b);
    d[8 * i + 1] = rng_exp(-1.0 - (double)i);
    d[8 * i + 2] = rng_log(0.3 + 0.1 * (double)i);
    d[8 * i + 3] = (double)convert_long(a);
    d[8 * i + 4] = convert_double(convert_long(a) << 20);
    d[8 * i + 5] = ldexp(1.0, -3 - (int)i);
    d[8 * i + 6] = floor(-0.94 - (double)i);
    d[8 * i + 7] = rng_sincos_2pi(0.3 + 0.1 * (double)i, &s);
}
"""
cl = opencl._cl()
key = rng.seed_to_key(7)
words = rng.philox4x32(np.array([[i, 0, 9, 0] for i in range(4)], np.uint32), key)
for opts in ((), ("-cl-opt-disable",)):
    prg = cl.Program(opencl.get_context(), PROBE).build(options=list(opts) + list(opencl._include_options()))
    w, d = np.zeros(16, np.uint64), np.zeros(32)
    bw, bd = opencl.device_buffer(w.nbytes), opencl.device_buffer(d.nbytes)
    prg.probe(opencl.get_queue(), (4,), None, bw, bd, np.uint32(key[0]), np.uint32(key[1]), np.uint32(9))
    opencl.from_device(w, bw)
    opencl.from_device(d, bd)
    print("probe", opts or "default", "words equal:", bool(np.array_equal(w.reshape(4, 4), words.astype(np.uint64))))
    for i in range(4):
        a, b = int(words[i, 0]), int(words[i, 1])
        exp = [float(rng.words_to_uniform(np.uint32(a), np.uint32(b))), float(rng.rng_exp(np.array(-1.0 - i))),
               float(rng.rng_log(np.array(0.3 + 0.1 * i))), float(a), float(a << 20), 2.0 ** (-3 - i),
               float(np.floor(-0.94 - i)), float(np.cos(2 * np.pi * (0.3 + 0.1 * i)))]
        print(f"  i={i} got {np.array2string(d[8 * i:8 * i + 8], precision=6)}\n      want {np.array2string(np.array(exp), precision=6)}")

from slicersim.backends import dispatch  # noqa: E402
print("self-check:", dispatch.device_validated())
