"""Random streams of the selected OpenCL device against the NumPy twin (run by device_suite.sh):
how many uniforms and Gaussians differ (and whether the differing uniforms are u - 1, the signature
of a sign-extended high word), the Poisson counts, a probe of the 32 -> 64-bit widenings philox_u01
relies on (words from a buffer, top bit set or not), and a probe of the Philox helpers' values
(default build and -cl-opt-disable)."""
import numpy as np

from slicersim.backends import noise as cn
from slicersim import rng
from slicersim.backends import opencl

un, zn = cn.uniform_normal_draw(100001, 2**63 + 12345, 5, 2, backend="numpy")
for wg, vw in ((None, 1), (64, 1), (1000, 1), (None, 2), (None, 4)):
    uc, zc = cn.uniform_normal_draw(100001, 2**63 + 12345, 5, 2, backend="opencl", work_group=wg,
                                    vector_width=vw)
    bad = uc != un
    line = f"wg={wg} vw={vw}: uniforms differing {int(bad.sum())} of {un.size}"
    if bad.any():
        idx = np.flatnonzero(bad.ravel())
        line += (f" (of them u>=0.5: {float((un.ravel()[idx] >= 0.5).mean()):.3f}, equal to u-1: "
                 f"{float((uc.ravel()[idx] == un.ravel()[idx] - 1.0).mean()):.3f}; first flat indices {idx[:6].tolist()})")
    line += f"; normals differing {int((zc != zn).sum())}, max |diff| {float(np.nanmax(np.abs(zc - zn))):.3g}"
    print(line)
for mu in (1e-3, 1.0, 30.0, 1e4):
    k = cn.poisson_draw(np.full(100000, mu), seed=7, backend="opencl")
    kn = cn.poisson_draw(np.full(100000, mu), seed=7, backend="numpy")
    print("poisson", mu, "mean", k.mean(), "var", k.var(), "numpy mean", kn.mean(),
          "differing", int(np.count_nonzero(k != kn)))

WIDEN = r"""
#define RNG_INLINE inline __attribute__((always_inline))   /* -cl-opt-disable: no external definition */
#include "philox.cl"
__kernel void widen(__global const uint *hi, __global const uint *lo, __global ulong *out)
{
    const size_t i = get_global_id(0);
    const uint h = hi[i], l = lo[i];
    __global ulong *o = out + 16 * i;
    o[0] = as_ulong(convert_long(h));
    o[1] = convert_ulong(h);
    o[2] = (ulong)h;
    o[3] = as_ulong(convert_long(h) << 20);
    o[4] = convert_ulong(h) << 20;
    o[5] = ((ulong)h) << 20;
    o[6] = convert_ulong(h) * 1048576ul;
    o[7] = upsample(h >> 12, (h << 20) | (l >> 12));
    o[8] = (convert_ulong(h) << 20) | convert_ulong(l >> 12);
    o[9] = as_ulong(convert_double(as_long(2UL * ((convert_ulong(h) << 20) | convert_ulong(l >> 12)) + 1UL)) * 0x1.0p-53);
    o[10] = as_ulong(convert_double(2L * ((convert_long(h) << 20) | convert_long(l >> 12)) + 1L) * 0x1.0p-53);
    o[11] = as_ulong(philox_u01(h, l));
    o[12] = philox_x52(h, l);
    o[13] = as_ulong(convert_double(h));
    o[14] = as_ulong((double)h);
    o[15] = (philox_x52(h, l) * (ulong)4000) >> 52;
}
"""
NAMES = ["convert_long(h)", "convert_ulong(h)", "(ulong)h", "convert_long(h)<<20", "convert_ulong(h)<<20",
         "((ulong)h)<<20", "convert_ulong(h)*2^20", "upsample", "x (convert_ulong)", "u01 679cf33 (convert_ulong)",
         "u01 run 1-3 (convert_long)", "u01 now (philox_u01)", "philox_x52", "convert_double(h)", "(double)h",
         "x52*4000>>52"]
HI = np.array([0, 1, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFF, 0x9E3779B9, 0x12345678, 0xDEADBEEF], np.uint32)
LO = np.array([0xFFFFFFFF, 0x12345678, 0, 0xFFF, 0x80000000, 1, 0xFFFFFFFF, 0xCAFEBABE], np.uint32)


def _bits(x):
    return int(np.array(x, np.float64).view(np.uint64))


want = []
for h, lo in zip(HI.tolist(), LO.tolist()):
    x = (h << 20) | (lo >> 12)
    ub = _bits(rng.words_to_uniform(np.uint32(h), np.uint32(lo)))
    want.append([h, h, h, h << 20, h << 20, h << 20, h << 20, x, x, ub, ub, ub, x, _bits(float(h)),
                 _bits(float(h)), (x * 4000) >> 52])
want = np.array(want, np.uint64)
cl = opencl._cl()
for opts in ((), ("-cl-opt-disable",)):
    prg = cl.Program(opencl.get_context(), WIDEN).build(options=list(opts) + list(opencl._include_options()))
    out = np.zeros((HI.size, 16), np.uint64)
    d_o = opencl.device_buffer(out.nbytes)
    prg.widen(opencl.get_queue(), (HI.size,), None, opencl.to_device(HI), opencl.to_device(LO), d_o)
    opencl.from_device(out, d_o)
    print("widening probe", opts or "default")
    for j, name in enumerate(NAMES):
        wrong = np.flatnonzero(out[:, j] != want[:, j])
        if wrong.size == 0:
            print(f"  {name:28s} ok")
        else:
            print(f"  {name:28s} WRONG for hi = " + ", ".join(
                f"{int(HI[i]):#010x} (got {int(out[i, j]):#x}, want {int(want[i, j]):#x})" for i in wrong[:2])
                + f" [{wrong.size}/{HI.size}]")

PROBE = r"""
#define RNG_INLINE inline __attribute__((always_inline))
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
key = rng.seed_to_key(7)
words = rng.philox4x32(np.array([[i, 0, 9, 0] for i in range(4)], np.uint32), key)
for opts in ((), ("-cl-opt-disable",)):
    prg = cl.Program(opencl.get_context(), PROBE).build(options=list(opts) + list(opencl._include_options()))
    w, d = np.zeros(16, np.uint64), np.zeros(32)
    bw, bd = opencl.device_buffer(w.nbytes), opencl.device_buffer(d.nbytes)
    prg.probe(opencl.get_queue(), (4,), None, bw, bd, np.uint32(key[0]), np.uint32(key[1]), np.uint32(9))
    opencl.from_device(w, bw)
    opencl.from_device(d, bd)
    exp = []
    for i in range(4):
        a, b = int(words[i, 0]), int(words[i, 1])
        exp += [float(rng.words_to_uniform(np.uint32(a), np.uint32(b))), float(rng.rng_exp(np.array(-1.0 - i))),
                float(rng.rng_log(np.array(0.3 + 0.1 * i))), float(a), float(a << 20), 2.0 ** (-3 - i),
                float(np.floor(-0.94 - i)), float(np.cos(2 * np.pi * (0.3 + 0.1 * i)))]
    exp = np.array(exp).reshape(4, 8)
    got = d.reshape(4, 8)
    cols = ["u01", "exp", "log", "cvt_long", "cvt_long<<20", "ldexp", "floor", "cos2pi"]
    same = [(c, bool(np.array_equal(got[:, j], exp[:, j])) if c != "cos2pi" else bool(np.allclose(got[:, j], exp[:, j], 0, 1e-15)))
            for j, c in enumerate(cols)]
    print("helper probe", opts or "default", "words equal:", bool(np.array_equal(w.reshape(4, 4), words.astype(np.uint64))),
          "; ".join(f"{c} {'ok' if s else 'WRONG'}" for c, s in same), "; words[:,0] =", [hex(int(x)) for x in words[:, 0]])

# ramps of tests/products/test_ramps.py::test_slope_variance_matches_rauscher07 (failed on the H200 in run 4): kernel vs twin
from slicersim.products.ramps import simulate  # noqa: E402
for nmd in ((16, 8, 0), (8, 4, 2), (12, 1, 0), (5, 8, 4), (32, 1, 3)):
    kw = dict(seed=11, ron=12.0, dark=0.0, roic_glow=0.0)
    a = simulate(np.full((200, 200), 2.0), nmd, backend="numpy", **kw)[0].astype(np.int64)
    b = simulate(np.full((200, 200), 2.0), nmd, backend="opencl", **kw)[0].astype(np.int64)
    bad = a != b
    line = f"ramp {nmd}: differing {int(bad.sum())} of {a.size}"
    if bad.any():
        g, pix = np.nonzero(bad.reshape(a.shape[0], -1))
        d = (b - a)[bad]
        line += (f", per group {np.bincount(g, minlength=a.shape[0]).tolist()}, first pixels {pix[:5].tolist()}, "
                 f"diff min/max/mean {int(d.min())}/{int(d.max())}/{float(d.mean()):.3g}")
    print(line)

from slicersim.backends import dispatch  # noqa: E402
from slicersim.backends.selfcheck import device_selfcheck  # noqa: E402
print("self-check:", device_selfcheck(), "| dispatch:", dispatch.device_validated())
