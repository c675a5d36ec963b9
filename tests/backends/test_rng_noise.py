"""Philox4x32-10 RNG (slicersim.rng) and its OpenCL twin (kernels/philox.cl, noise.cl).

* Known-answer vectors of Random123 for both implementations.
* OpenCL and NumPy streams are bit-identical (uniforms, Gaussians, noisy
  cubes, Poisson draws) for odd sizes, any work-group size and chunking:
  both use only IEEE +, −, ×, ÷, √ and exact bit operations, no FMA
  contraction, so exact equality is the right test (no tolerance).
* Statistics with quantified Monte Carlo error: sample means and variances
  within 4σ of their MC standard error, KS / χ² goodness of fit at p > 1e-3
  (seeds are fixed, so these tests are deterministic; a broken generator
  fails them by many σ).
"""
import numpy as np
import pytest
from scipy import stats
from scipy.special import gammaln

from slicersim.backends import noise as cn
from slicersim import rng
from slicersim.backends import opencl
from slicersim.backends.dispatch import resolve_backend

BACKENDS = ["numpy", pytest.param("opencl", marks=pytest.mark.needs_opencl)]

# Random123 kat_vectors, philox4x32 with 10 rounds: (counter, key, expected output)
KAT = [((0, 0, 0, 0), (0, 0), (0x6627E8D5, 0xE169C58D, 0xBC57AC4C, 0x9B00DBD8)),
       ((0xFFFFFFFF,) * 4, (0xFFFFFFFF,) * 2, (0x408F276D, 0x41C83B0E, 0xA20BC7C6, 0x6D5451FD)),
       ((0x243F6A88, 0x85A308D3, 0x13198A2E, 0x03707344), (0xA4093822, 0x299F31D0),
        (0xD16CFE09, 0x94FDCCEB, 0x5001E420, 0x24126EA1))]


@pytest.mark.parametrize("backend", BACKENDS)
def test_philox_known_answers(backend):
    ctr = np.array([c for c, _, _ in KAT], np.uint32)
    key = np.array([k for _, k, _ in KAT], np.uint32)
    got = cn.philox_blocks(ctr, key, backend=backend)
    assert got.tolist() == [list(e) for _, _, e in KAT]
    # fewer rounds give different words (the round count matters)
    assert rng.philox4x32(ctr, key, rounds=7).tolist() != got.tolist()


def test_keying_and_uniform_mapping():
    w = rng.random_words(2**40 + 5, np.array([3, 2**33 + 1], np.uint64), stream=9, draw=4)
    ctr = np.array([[3, 0, 9, 4], [1, 2, 9, 4]], np.uint32)
    assert np.array_equal(w, rng.philox4x32(ctr, [5, 256]))
    # extreme words map strictly inside (0, 1), exactly
    u = rng.words_to_uniform(np.array([0, 0xFFFFFFFF], np.uint32), np.array([0, 0xFFFFFFFF], np.uint32))
    assert u[0] == 2.0**-53 and u[1] == 1.0 - 2.0**-53
    from slicersim.errors import ParameterError
    with pytest.raises(ParameterError, match="seed"):
        rng.seed_to_key(-1)
    with pytest.raises(ParameterError, match="seed must be an integer"):
        rng.seed_to_key(1.5)
    with pytest.raises(ParameterError, match="seed must be an integer.*Generator"):
        rng.seed_to_key(np.random.default_rng(1))


# words whose top bit is set (the high word of every u >= 0.5): NVIDIA's OpenCL (H200, driver
# 580.159) computed convert_long(uint h) << 20 as if h were signed, so each such u came out as u - 1
TOP_BIT_HI = np.array([0, 1, 0x7FFFFFFF, 0x80000000, 0x80000001, 0xFFFFFFFF, 0x9E3779B9, 0xDEADBEEF,
                       0x12345678, 0xC0000000, 0xFFFFF000, 0x80000FFF, 0xBB67AE85, 0x3, 0xF0F0F0F0, 0xAAAAAAAA],
                      np.uint32)
TOP_BIT_LO = TOP_BIT_HI[::-1].copy()


def _sign_extended_uniform(hi, lo):
    """philox_u01 as the H200 computed it (high word sign-extended before the shift)."""
    x = (np.asarray(hi, np.uint32).astype(np.int32).astype(np.int64) << 20) \
        | (np.asarray(lo, np.uint32) >> np.uint32(12)).astype(np.int64)
    return (2 * x + 1).astype(np.float64) * 2.0**-53


def test_sign_extended_high_word_is_the_h200_signature(monkeypatch):
    """The twin with a sign-extended high word reproduces the H200's wrong draws of run 2
    (benchmarks/results/gpu_h200.md) exactly: u - 1 for every u >= 0.5, Poisson mean 0.134 at mu = 1."""
    seed, index = 2**63 + 12345, np.arange(100001, dtype=np.uint64)
    good = rng.uniform(seed, index, 5, 2)
    monkeypatch.setattr(rng, "words_to_uniform", _sign_extended_uniform)
    bad = rng.uniform(seed, index, 5, 2)
    assert int((bad != good).sum()) == 100116
    assert np.array_equal(bad[good >= 0.5], good[good >= 0.5] - 1.0)
    assert np.array_equal(bad[good < 0.5], good[good < 0.5])
    assert rng.poisson(np.full(100000, 1.0), 7, np.arange(100000, dtype=np.uint64), 0).mean() == 0.13353


@pytest.mark.needs_opencl
@pytest.mark.parametrize("vw", [1, 4])
def test_uniform_mapping_of_top_bit_words_in_the_kernel(vw):
    """philox_u01 and philox_x52 (kernels/philox.cl) on words with and without the top bit set,
    scalar and vector: exactly rng.words_to_uniform and its 52-bit integer."""
    src = f"""
#define RNG_INLINE inline __attribute__((always_inline))
#include "philox.cl"
__kernel void probe(__global const uint *hi, __global const uint *lo, __global double *u, __global ulong *x)
{{
    const size_t i = get_global_id(0);
    const rng_uint h = RNG_VLOAD(i, hi), l = RNG_VLOAD(i, lo);
    RNG_VSTORE(philox_u01(h, l), i, u);
    RNG_VSTORE(philox_x52(h, l), i, x);
}}"""
    cl = opencl._cl()
    prg = cl.Program(opencl.get_context(), src).build(options=[f"-DRNG_VW={vw}", *opencl._include_options()])
    u, x = np.zeros(TOP_BIT_HI.size), np.zeros(TOP_BIT_HI.size, np.uint64)
    d_u, d_x = opencl.device_buffer(u.nbytes), opencl.device_buffer(x.nbytes)
    prg.probe(opencl.get_queue(), (TOP_BIT_HI.size // vw,), None, opencl.to_device(TOP_BIT_HI),
              opencl.to_device(TOP_BIT_LO), d_u, d_x)
    opencl.from_device(u, d_u)
    opencl.from_device(x, d_x)
    want_x = (TOP_BIT_HI.astype(np.uint64) << np.uint64(20)) | (TOP_BIT_LO.astype(np.uint64) >> np.uint64(12))
    assert np.array_equal(x, want_x)
    assert np.array_equal(u.view(np.uint64), rng.words_to_uniform(TOP_BIT_HI, TOP_BIT_LO).view(np.uint64))
    assert not np.array_equal(u, _sign_extended_uniform(TOP_BIT_HI, TOP_BIT_LO))


def test_elementary_functions_accuracy():
    u = rng.uniform(11, np.arange(200_000))[:, 0]
    u = np.concatenate([u, [2.0**-53, 1.0 - 2.0**-53, 0.5, np.sqrt(0.5), 1.0]])
    ref = np.log(u)
    assert np.max(np.abs(rng.rng_log(u) - ref) / np.maximum(np.abs(ref), 1e-300)) < 5e-16
    c, s = rng.sincos_2pi(u)
    # reference from exact reduction: cos 2πu = cos(2π(u − round(u)))
    assert np.max(np.abs(c - np.cos(2 * np.pi * (u - np.round(u))))) < 1e-15
    assert np.max(np.abs(s - np.sin(2 * np.pi * (u - np.round(u))))) < 1e-15
    x = -30.0 * u
    assert np.max(np.abs(rng.rng_exp(x) / np.exp(x) - 1)) < 5e-16
    k = np.arange(0.0, 3e5, 7.0)
    assert np.max(np.abs(rng.log_factorial(k) - gammaln(k + 1)) / np.maximum(gammaln(k + 1), 1)) < 1e-15


@pytest.mark.needs_opencl
@pytest.mark.parametrize("n, first, stream, draw", [(1, 0, 0, 0), (1001, 2**40 + 3, 7, 2), (4099, 17, 2**32 - 1, 5)])
def test_streams_bit_identical(n, first, stream, draw):
    un, zn = cn.uniform_normal_draw(n, 2**63 + 12345, stream, draw, backend="numpy", first_index=first)
    for wg, vw in ((None, None), (1, 1), (7, 2), (64, 8), (None, 16)):
        uc, zc = cn.uniform_normal_draw(n, 2**63 + 12345, stream, draw, backend="opencl", work_group=wg,
                                        first_index=first, vector_width=vw)
        assert np.array_equal(uc, un) and np.array_equal(zc, zn), f"work_group={wg}, vector_width={vw}"


@pytest.mark.needs_opencl
@pytest.mark.parametrize("rows, ncols, first, stride", [(3, 37, 5 << 16, 1 << 16), (17, 4096, 0, 1 << 16),
                                                         (2, 1001, 2**40 + 3, 1001), (1, 9, 0, 0)])
def test_grid_streams_bit_identical_to_rng(rows, ncols, first, stride):
    """The grid kernel (maps keyed y << 16 | x) gives rng.uniform/normal of the same indices, bit for bit."""
    index = np.uint64(first) + np.arange(rows, dtype=np.uint64)[:, None] * np.uint64(stride) \
        + np.arange(ncols, dtype=np.uint64)[None, :]
    ur, zr = rng.uniform(77, index, 9, 3), rng.normal(77, index, 9, 3)
    for wg, vw in ((None, None), (1, 1), (7, 4), (None, 16)):
        uc, zc = cn.uniform_normal_grid(rows, ncols, 77, 9, 3, "opencl", wg, first_index=first, row_stride=stride,
                                        vector_width=vw)
        assert uc.shape == zc.shape == (rows, ncols, 2)
        assert np.array_equal(uc, ur) and np.array_equal(zc, zr), f"work_group={wg}, vector_width={vw}"


def test_grid_rejects_indices_past_64_bits():
    with pytest.raises(ValueError, match="2\\*\\*64"):
        cn.uniform_normal_grid(2, 10, 1, first_index=2**64 - 5, row_stride=1, backend="numpy")
    with pytest.raises(ValueError, match="2\\*\\*64"):
        rng.uniform_normal_grid(2, 10, 1, first_index=2**64 - 5, row_stride=1)


def test_physics_grids_use_the_registered_engine_with_the_same_numbers():
    """slicersim.rng (below physics) computes the detector-effect grids; backends.noise registers its
    device grid as their engine on import.  Engine or not, the numbers are rng.uniform/normal's."""
    assert rng._grid_engine is not None                 # registered by importing backends.noise
    index = (3 << 16) + np.arange(2, dtype=np.uint64)[:, None] * np.uint64(1 << 16) + np.arange(5, dtype=np.uint64)
    want = rng.uniform(11, index, 4, 1), rng.normal(11, index, 4, 1)
    calls = []

    def engine(*args):
        calls.append(args)
        return cn.uniform_normal_grid(*args[:5], backend="numpy", first_index=args[5], row_stride=args[6])
    previous = rng.register_grid_engine(engine)
    try:
        got = rng.uniform_normal_grid(2, 5, 11, 4, 1, first_index=3 << 16, row_stride=1 << 16)
        assert calls == [(2, 5, 11, 4, 1, 3 << 16, 1 << 16)]
        rng.register_grid_engine(None)
        plain = rng.uniform_normal_grid(2, 5, 11, 4, 1, first_index=3 << 16, row_stride=1 << 16)
        u1, z1 = rng.uniform_normal_draw(5, 11, 4, 1, first_index=3 << 16)
    finally:
        rng.register_grid_engine(previous)
    for u, z in (got, plain):
        assert np.array_equal(u, want[0]) and np.array_equal(z, want[1])
    assert np.array_equal(u1, want[0][0]) and np.array_equal(z1, want[1][0])


def test_uniform_and_normal_statistics():
    n = 200_000
    u = rng.uniform(2024, np.arange(n))
    assert u.min() > 0 and u.max() < 1
    for col in u.T:
        assert stats.kstest(col, "uniform").pvalue > 1e-3
    z = rng.normal(99, np.arange(n))
    for col in z.T:                                 # cos and sin branches
        assert abs(col.mean()) < 4 / np.sqrt(n)
        assert abs(col.var() - 1) < 4 * np.sqrt(2.0 / n)
        assert stats.kstest(col, "norm").pvalue > 1e-3
    # the two branches and neighbouring indices are uncorrelated
    assert abs(np.corrcoef(z[:, 0], z[:, 1])[0, 1]) < 4 / np.sqrt(n)
    assert abs(np.corrcoef(z[:-1, 0], z[1:, 0])[0, 1]) < 4 / np.sqrt(n)
    # tails: fraction beyond 4σ within its binomial error
    p4 = 2 * stats.norm.sf(4)
    assert abs(np.mean(np.abs(z) > 4) - p4) < 4 * np.sqrt(p4 / (2 * n))


# --------------------------------------------------------------------------- noisy cube
def _cube(shape=(13, 7, 11), seed=5):
    g = np.random.default_rng(seed)
    expectation = g.uniform(-50, 1e4, shape)
    variance = g.uniform(0, 1e3, shape)
    variance[0, 0, :3] = [np.inf, 0.0, np.nan]
    expectation[1, 2, 3] = np.nan
    return expectation, variance


@pytest.mark.parametrize("backend", BACKENDS)
def test_noisy_cube_semantics(backend):
    e, v = _cube()
    out = cn.noisy_cube(e, v, 17, backend=backend)
    assert np.isnan(out[0, 0, 0]) and np.isnan(out[0, 0, 2])      # non-finite variance → NaN
    assert out[0, 0, 1] == e[0, 0, 1]                             # variance 0 → expectation exactly
    assert np.isnan(out[1, 2, 3])                                 # NaN expectation propagates
    assert np.count_nonzero(np.isnan(out)) == 3
    assert np.array_equal(out, cn.noisy_cube(e, v, 17, backend=backend), equal_nan=True)
    other = cn.noisy_cube(e, v, 18, backend=backend)
    ok = np.isfinite(out) & (v > 0)
    assert np.all(out[ok] != other[ok])
    assert not np.array_equal(out, cn.noisy_cube(e, v, 17, backend=backend, stream=1), equal_nan=True)
    with pytest.raises(ValueError, match="≥ 0"):
        cn.noisy_cube(e, -np.abs(v), 1, backend=backend)
    # a slab drawn with its first_index equals the same slab of the full cube
    slab = cn.noisy_cube(e[4:9], v[4:9], 17, backend=backend, first_index=4 * 7 * 11)
    assert np.array_equal(slab, out[4:9], equal_nan=True)


@pytest.mark.needs_opencl
def test_noisy_cube_identical_across_backends_workgroups_chunks_vector_widths():
    e, v = _cube((37, 5, 9))                          # 1665 voxels, odd sizes
    ref = cn.noisy_cube(e, v, 2**64 - 1, backend="numpy")
    for wg in (None, 1, 7, 64):
        for max_bytes in (cn.DEFAULT_MAX_BYTES, 24 * 300 + 5, 24 * 1000):
            for vw in (None, 1, 4):
                got = cn.noisy_cube(e, v, 2**64 - 1, backend="opencl", work_group=wg, max_bytes=max_bytes,
                                    vector_width=vw)
                assert np.array_equal(got, ref, equal_nan=True), (wg, max_bytes, vw)
    assert np.array_equal(cn.noisy_cube(e, v, 2**64 - 1, backend="numpy", max_bytes=2000), ref, equal_nan=True)


def test_noisy_cube_pulls_are_standard_normal():
    shape = (40, 50, 60)
    g = np.random.default_rng(1)
    e, v = g.uniform(0, 1e5, shape), g.uniform(1, 1e4, shape)
    pull = ((cn.noisy_cube(e, v, 31337) - e) / np.sqrt(v)).ravel()
    n = pull.size
    assert abs(pull.mean()) < 4 / np.sqrt(n)
    assert abs(pull.var() - 1) < 4 * np.sqrt(2.0 / n)
    assert stats.kstest(pull, "norm").pvalue > 1e-3


# --------------------------------------------------------------------------- Poisson
def _poisson_chi2_pvalue(k, mu, min_expected=20.0):
    """χ² goodness-of-fit p-value of integer draws k against Poisson(mu), pooling bins to E ≥ min_expected."""
    n = k.size
    lo, hi = int(stats.poisson.ppf(1e-9, mu)), int(stats.poisson.isf(1e-9, mu)) + 1
    support = np.arange(lo, hi + 1)
    expected = n * stats.poisson.pmf(support, mu)
    expected[0] += n * stats.poisson.cdf(lo - 1, mu)               # lower tail into the first bin
    expected[-1] += n * stats.poisson.sf(hi, mu)                   # upper tail into the last bin
    observed = np.bincount(np.clip(k.astype(np.int64), lo, hi) - lo, minlength=support.size)
    obs_b, exp_b, o_acc, e_acc = [], [], 0.0, 0.0
    for o, e in zip(observed, expected):
        o_acc, e_acc = o_acc + o, e_acc + e
        if e_acc >= min_expected:
            obs_b.append(o_acc), exp_b.append(e_acc)
            o_acc = e_acc = 0.0
    obs_b[-1] += o_acc
    exp_b[-1] += e_acc
    obs_b, exp_b = np.array(obs_b), np.array(exp_b)
    chi2 = np.sum((obs_b - exp_b) ** 2 / exp_b)
    return stats.chi2.sf(chi2, max(obs_b.size - 1, 1)), obs_b.size


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("mu", [1e-3, 0.1, 1.0, 5.0, 30.0, 100.0, 1e4])
def test_poisson_statistics(backend, mu):
    n = 100_000
    k = cn.poisson_draw(np.full(n, mu), seed=int(mu * 1000) + 7, backend=backend)
    assert np.all(k == np.floor(k)) and k.min() >= 0
    assert abs(k.mean() - mu) < 4 * np.sqrt(mu / n)
    assert abs(k.var() - mu) < 4 * np.sqrt((mu + 2 * mu**2) / n)
    pvalue, nbins = _poisson_chi2_pvalue(k, mu)
    assert nbins >= 2 and pvalue > 1e-3, f"chi2 p={pvalue:.2e} over {nbins} bins"


@pytest.mark.needs_opencl
def test_poisson_bit_identical_and_chunk_independent():
    g = np.random.default_rng(3)
    mean = np.concatenate([g.uniform(0, 12, 2000), 10 ** g.uniform(1, 7, 1001),
                           [0.0, 9.999999, 10.0, np.nan, np.inf]])
    ref = cn.poisson_draw(mean, 77, stream=3, backend="numpy")
    for wg, max_bytes in ((None, cn.DEFAULT_MAX_BYTES), (7, 16 * 500 + 3), (64, 16 * 1000)):
        got = cn.poisson_draw(mean, 77, stream=3, backend="opencl", work_group=wg, max_bytes=max_bytes)
        assert np.array_equal(got, ref, equal_nan=True), (wg, max_bytes)


@pytest.mark.parametrize("backend", BACKENDS)
def test_poisson_edge_cases(backend):
    k = cn.poisson_draw(np.array([[0.0, np.nan], [np.inf, 0.0]]), 1, backend=backend)
    assert k.shape == (2, 2) and k[0, 0] == 0 and k[1, 1] == 0 and np.isnan(k[0, 1]) and np.isnan(k[1, 0])
    with pytest.raises(ValueError, match="≥ 0"):
        cn.poisson_draw(np.array([1.0, -1e-9]), 1, backend=backend)
    # keyed by element index and stream: a slab reproduces the full draw
    mean = np.linspace(0, 50, 101)
    full = cn.poisson_draw(mean, 9, backend=backend)
    assert np.array_equal(cn.poisson_draw(mean[40:], 9, backend=backend, first_index=40), full[40:])
    assert not np.array_equal(cn.poisson_draw(mean, 9, stream=1, backend=backend), full)


@pytest.mark.needs_opencl
def test_philox_header_is_included_by_noise_kernel():
    assert '#include "philox.cl"' in opencl.kernel_source("noise.cl")
    assert "__kernel" not in opencl.kernel_source("philox.cl")   # header-like: functions only


def test_noise_arguments_are_parameter_errors_naming_them():
    from slicersim.errors import ParameterError
    with pytest.raises(ParameterError, match=r"stream must be an integer in \[0, 4294967295\]"):
        cn.noisy_cube(np.zeros(4), np.ones(4), 1, backend="numpy", stream=2**32)
    with pytest.raises(ParameterError, match="variance must be ≥ 0"):
        cn.noisy_cube(np.zeros(4), -np.ones(4), 1, backend="numpy")
    with pytest.raises(ParameterError, match="Poisson mean must be an array of real numbers"):
        rng.poisson(["a"], 1)
    with pytest.raises(ParameterError, match=r"unknown backend 'numpyy' \(did you mean 'numpy'\?\)"):
        resolve_backend("numpyy")
    with pytest.raises(ParameterError, match="rows must be an integer"):
        cn.uniform_normal_grid(1.5, 4, 1, backend="numpy")
