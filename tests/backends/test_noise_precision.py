"""Noise draws in single precision (issue 12): the float build of ``kernels/noise.cl`` against the
float64 twin, its draws against the exact distributions, counter-based invariance, devices without
fp64, and bad input.

Tolerances
----------
* Gaussian (:func:`noisy_cube`): max |Δ| ≤ 1e-3 σ against the twin (the tolerance of
  ``SINGLE_PRECISION_ERRORS["noise"]``; measured 8.1e-5 σ over the 3.4e6 voxels of the Lazuli cube).
  Single and double use the same Philox words; single's uniform has 24 bits of the first word
  (``philox_u01`` of philox.cl: ≥ 2^-32, never 0 or 1), so Δ comes from (a) radii near 0 (u₁ within
  2^-24 of 1: Δr ≈ 2^-24 / r, ~2^-24 √(n/2) as the max over n draws), (b) the tails (u₁ resolved to
  2^-32, not 2^-53: Δr ≈ 2^-32 / (u₁ r), above 1e-3 only beyond 5.8 σ, ~2e-8 of the draws) and
  (c) float rounding of e + σ z (2^-24 (|e| + σ|z|), so the inputs below keep |e|/σ ≤ 100).  These
  tests also bound Δ at 2e-4 σ on 2e5 draws (measured ~3e-5), so that a regression (a lost bit, a
  coarser uniform) is caught.  1e-3 σ is why single may be "auto": a draw moved by ε σ changes any
  moment estimated from it by ≲ ε, below the sampling error of fewer than 1/ε² = 1e6 draws.
* Poisson: the integers differ from the twin's where a float rounding (of float32(mean) itself, of
  the CDF sum, of the PTRS floor) moves a decision: measured 1.1e-4 of the draws over means
  log-uniform in [1e-3, 1e5] (7e-6 where the means are float32 numbers; 8e-5 at 3e5), by 1;
  bounded here at 5e-4 (1e-3 at 3e5).
  The distribution is checked by χ² against the exact pmf (p > 1e-3, fixed seeds).
"""
import math
import shutil
import subprocess

import numpy as np
import pytest
from scipy import stats

from slicersim.backends import dispatch, opencl
from slicersim.backends import noise as cn
from slicersim.backends import precision as prec
from slicersim.errors import OpenCLUnavailableError, ParameterError

TOL = 1e-3               # σ: a draw moved by ε σ changes a moment by ≲ ε, below the error of < 1/ε² draws
TIGHT = 2e-4                                                   # σ, on the 2e5 draws below (measured ~3e-5)


@pytest.fixture(scope="module")
def flat():
    """A uniform-scene target (QTH flat): its cubes are NumPy, only the noise draw is a kernel."""
    from slicersim.targets.calibration import Lazuli3DFlat
    return Lazuli3DFlat.from_qth()


def _inputs(n=200_000, seed=5):
    """Expectations and variances of cube voxels: e in [-50, 1e4] ADU, σ² = e/2 + 15² (|e|/σ ≤ 100),
    plus variance 0, +inf, NaN and a NaN expectation."""
    g = np.random.default_rng(seed)
    e = g.uniform(-50.0, 1e4, n)
    v = np.abs(e) / 2 + 225.0
    e[:4], v[:4] = [3.3, 7.1, 2.0, np.nan], [0.0, np.inf, np.nan, 4.0]
    return e, v


@pytest.mark.needs_opencl
def test_single_gaussian_within_tolerance_of_the_float64_twin():
    e, v = _inputs()
    twin = cn.noisy_cube(e, v, 2**63 + 5, backend="numpy", first_index=77)
    single = cn.noisy_cube(e, v, 2**63 + 5, backend="opencl", precision="single", first_index=77)
    assert single.dtype == np.float64
    assert single[0] == np.float32(3.3)                                # variance 0: the (float) expectation
    assert np.isnan(single[1:4]).all() and np.isfinite(single[4:]).all()
    sigma = np.sqrt(v[4:])
    err = np.abs(single[4:] - twin[4:]) / sigma
    print(f"max |Δ| = {err.max():.2e} σ")
    assert 0 < err.max() <= TIGHT <= TOL
    assert np.median(err) < 1e-5                                        # most draws: float roundings
    # Independent bound [σ], float32 rounding (2^-24 relative per operation) on these inputs:
    # (a) Box–Muller radius near 0: u₁ has 24 bits, Δr ≈ 2^-24 / r, and the smallest r among n draws
    #     is ~1/√(n/2): ≤ 2 · 2^-24 √(n/2) (factor 2: the extreme of n draws);
    # (c) float32(e) and the sum e + σ z: two roundings of 2^-24 (|e|/σ + |z|).
    # Measured 1.5e-5 σ; the bound is ≈ 5.5e-5 σ here (independent of SINGLE_PRECISION_ERRORS).
    n = sigma.size
    z = (twin[4:] - e[4:]) / sigma
    bound = 2.0**-24 * (2 * math.sqrt(n / 2) + 2 * np.max(np.abs(e[4:]) / sigma) + 2 * np.max(np.abs(z)))
    assert err.max() <= bound, (err.max(), bound)
    # a float32 out receives the draw as computed (no float64 temporary); double refuses it
    out32 = np.empty(e.size, np.float32)
    assert cn.noisy_cube(e, v, 2**63 + 5, backend="opencl", precision="single", first_index=77, out=out32) is out32
    assert np.array_equal(out32.astype(np.float64), single, equal_nan=True)
    with pytest.raises(ValueError, match="out must be"):
        cn.noisy_cube(e, v, 1, backend="opencl", precision="double", out=out32)


@pytest.mark.needs_opencl
def test_single_gaussian_moments():
    """e = 0, σ = 1: mean, variance, skewness, excess kurtosis within 5 standard errors and a KS test
    (p > 1e-3); the largest |z| is where 4e5 normal draws put it (single's uniform floor 2^-32 caps
    |z| at 6.66)."""
    n = 400_000
    z = cn.noisy_cube(np.zeros(n), np.ones(n), 31337, backend="opencl", precision="single")
    assert abs(z.mean()) < 5 / math.sqrt(n)
    assert abs(z.var() - 1) < 5 * math.sqrt(2 / n)
    assert abs(stats.skew(z)) < 5 * math.sqrt(6 / n)
    assert abs(stats.kurtosis(z)) < 5 * math.sqrt(24 / n)
    assert stats.kstest(z, "norm").pvalue > 1e-3
    assert 3.5 < np.abs(z).max() < 6.66


def _chi2_pvalue(k, mu):
    """χ² p-value of counts k against Poisson(mu): ≤ 40 bins of about equal probability (edges at
    the pmf's quantiles), pooled until each expects ≥ 20 counts; exact cdf."""
    edges = np.unique(stats.poisson.ppf(np.linspace(0.0, 1.0, 41)[1:-1], mu).astype(np.int64) + 1)
    cdf = np.concatenate([[0.0], stats.poisson.cdf(edges - 1, mu), [1.0]])   # bins [edge_(i-1), edge_i)
    expected = k.size * np.diff(cdf)
    observed = np.bincount(np.searchsorted(edges, k.astype(np.int64), side="right"), minlength=edges.size + 1)
    obs, exp, o_acc, e_acc = [], [], 0.0, 0.0
    for o, e in zip(observed, expected):
        o_acc, e_acc = o_acc + o, e_acc + e
        if e_acc >= 20:
            obs.append(o_acc), exp.append(e_acc)
            o_acc = e_acc = 0.0
    obs[-1] += o_acc
    exp[-1] += e_acc
    obs, exp = np.array(obs), np.array(exp)
    assert obs.size >= 2
    return stats.chi2.sf(np.sum((obs - exp) ** 2 / exp), obs.size - 1)


@pytest.mark.needs_opencl
@pytest.mark.parametrize("mu", [0.02, 3.0, 9.99, 10.0, 40.0, 2500.0, 3e5, 4e6])
def test_single_poisson_draws_follow_the_exact_distribution(mu):
    """Inversion (< 10) and PTRS (≥ 10, float acceptance by ``rng_log_poisson``) on either side of the
    switch and at large means (3e5; 4e6 near the single limit 2^22, where mu + 0.43 alone would round
    to ulp 0.5): χ² against the exact pmf, p > 1e-3, and the mean within 4 standard errors."""
    n = 60_000
    k = cn.poisson_draw(np.full(n, mu), 1000 + int(mu), backend="opencl", precision="single")
    assert np.all(k == np.floor(k)) and k.min() >= 0
    pvalue = _chi2_pvalue(k, mu)
    assert pvalue > 1e-3, (mu, pvalue)
    assert abs(k.mean() - mu) < 4 * math.sqrt(mu / n)


@pytest.mark.needs_opencl
def test_single_poisson_mostly_equals_the_float64_twin():
    g = np.random.default_rng(4)
    mean = np.concatenate([10 ** g.uniform(-3, 5, 200_000), [0.0, np.nan, np.inf, 9.999999, 10.0]])
    twin = cn.poisson_draw(mean, 21, stream=2, backend="numpy")
    single = cn.poisson_draw(mean, 21, stream=2, backend="opencl", precision="single")
    assert np.array_equal(np.isnan(single), np.isnan(mean) | np.isinf(mean))
    ok = np.isfinite(mean)
    diff = single[ok] != twin[ok]
    print(f"{diff.mean():.2e} of the counts differ")
    assert 0 < diff.mean() <= 5e-4
    assert np.abs(single[ok] - twin[ok]).max() <= 2
    assert single[-5] == 0.0
    # a mean that is a float32 number: only the kernel's own roundings move counts (measured 8e-5 at
    # 3e5; a float mu + 0.43 would round to ulp/2 = 0.016 and move 2.4 %)
    big = np.full(40_000, 3e5)
    moved = np.mean(cn.poisson_draw(big, 5, backend="opencl", precision="single")
                    != cn.poisson_draw(big, 5, backend="numpy"))
    assert moved <= 1e-3, moved


@pytest.mark.slow
@pytest.mark.needs_opencl
def test_single_is_counter_based(monkeypatch):
    """Vector width, work group, chunking (max_bytes, the float32 staging of float64 arrays), the
    scratch path (read-only inputs) and slabs (first_index) leave the single draws unchanged, bit for bit."""
    e, v = _inputs(8 * 97 + 5, seed=9)
    e32, v32 = e.astype(np.float32), v.astype(np.float32)
    ref = cn.noisy_cube(e32, v32, 17, backend="opencl", precision="single", vector_width=1,
                        out=np.empty(e.size, np.float32)).astype(np.float64)     # float32 throughout: no staging
    monkeypatch.setattr(cn, "_STAGE", 96)                                 # float64 arrays: 9 staged chunks
    for vw in (2, 4, 8, 16):
        for wg, max_bytes in ((None, cn.DEFAULT_MAX_BYTES), (3, 12 * 300)):
            got = cn.noisy_cube(e, v, 17, backend="opencl", precision="single", vector_width=vw, work_group=wg,
                                max_bytes=max_bytes)
            assert np.array_equal(got, ref, equal_nan=True), (vw, wg)
    e32.flags.writeable = v32.flags.writeable = False                    # no zero-copy: scratch buffers
    got = cn.noisy_cube(e32, v32, 17, backend="opencl", precision="single", vector_width=4, max_bytes=12 * 300,
                        out=np.empty(e.size, np.float32))
    assert np.array_equal(got, ref, equal_nan=True)
    slab = cn.noisy_cube(e[300:], v[300:], 17, backend="opencl", precision="single", first_index=300)
    assert np.array_equal(slab, ref[300:], equal_nan=True)
    mean = 10 ** np.random.default_rng(2).uniform(-2, 5, 3001)
    kref = cn.poisson_draw(mean, 8, backend="opencl", precision="single")
    for wg, max_bytes in ((7, 8 * 500), (64, cn.DEFAULT_MAX_BYTES)):
        assert np.array_equal(cn.poisson_draw(mean, 8, backend="opencl", precision="single", work_group=wg,
                                              max_bytes=max_bytes), kref)
    assert np.array_equal(cn.poisson_draw(mean[1000:], 8, backend="opencl", precision="single",
                                          first_index=1000), kref[1000:])


@pytest.mark.skipif(shutil.which("cpp") is None, reason="no C preprocessor")
@pytest.mark.parametrize("vw", [1, 16])
def test_single_noise_source_holds_no_double(vw):
    """A device without fp64 compiles the single build: after preprocessing with -DSINGLE, noise.cl
    (with philox.cl and vector_types.cl) contains no double type."""
    kdir = opencl.kernel_dir()
    out = subprocess.run(["cpp", "-P", "-DSINGLE", f"-DRNG_VW={vw}", f"-I{kdir}", f"{kdir}/noise.cl"],
                         capture_output=True, text=True, check=True).stdout
    assert "gaussian_noise" in out and "uniform_normal" in out
    assert ("poisson_draw" in out) == (vw == 1)
    assert "double" not in out


@pytest.mark.needs_opencl
def test_device_without_fp64_runs_single_noise(monkeypatch, flat):
    """fp64 flag forced off: "auto" runs the single kernels (not NumPy, and without the fp64 device
    self-check: only the single builds' own), bit for bit what "single" gives; "double" is one clear
    error; a cube's noise draw follows."""
    e, v = _inputs(5000)
    mean = 10 ** np.random.default_rng(1).uniform(-2, 4, 3000)
    single = cn.noisy_cube(e, v, 3, precision="single")
    ksingle = cn.poisson_draw(mean, 3, precision="single")
    assert not np.array_equal(single, cn.noisy_cube(e, v, 3), equal_nan=True)     # auto: double on a CPU
    monkeypatch.setattr(opencl, "device_supports_fp64", lambda: False)

    def no_fp64_selfcheck(*args):
        raise AssertionError("the fp64 backend check (and its self-check) ran")
    monkeypatch.setattr(prec, "resolve_backend", no_fp64_selfcheck)
    assert dispatch.device_validated("single")[0]                      # the float builds' check passes
    assert np.array_equal(cn.noisy_cube(e, v, 3), single, equal_nan=True)
    assert np.array_equal(cn.poisson_draw(mean, 3, backend="opencl"), ksingle)
    for call in (lambda: cn.noisy_cube(e, v, 3, precision="double"),
                 lambda: cn.poisson_draw(mean, 3, precision="double")):
        with pytest.raises(OpenCLUnavailableError, match="precision 'double' needs fp64"):
            call()
    with pytest.raises(ParameterError, match="cannot be drawn in single"):         # no double to fall back to
        cn.poisson_draw(np.array([1.0, 5e6]), 3)
    signal, variance, noisy = flat.get_cube(seed=4, dtype=np.float32)
    assert noisy.dtype == np.float32
    assert np.array_equal(noisy, cn.noisy_cube(signal, variance, 4, precision="single").astype(np.float32),
                          equal_nan=True)


@pytest.mark.needs_opencl
def test_large_poisson_means_stay_double_under_auto(monkeypatch):
    """Above 2^22 a float count loses its PTRS resolution: "single" refuses, "auto" (single where the
    device lacks fast fp64) draws in double when fp64 exists."""
    mean = np.array([3.0, 5e6, np.inf])
    with pytest.raises(ParameterError, match="cannot be drawn in single"):
        cn.poisson_draw(mean, 1, backend="opencl", precision="single")
    monkeypatch.setattr(prec, "fp64_throughput_ratio", lambda: 32.0)              # a consumer GPU: auto → single
    assert prec.resolve_precision("auto", "opencl", "noise") == ("opencl", "single")
    got = cn.poisson_draw(mean, 1, backend="opencl")
    assert np.array_equal(got, cn.poisson_draw(mean, 1, backend="numpy"), equal_nan=True)


def test_bad_precision_refused_before_any_work(monkeypatch, flat):
    """One ParameterError for an unknown precision name, before any array is read or drawn."""
    def no_work(*args, **kwargs):
        raise AssertionError("work started")
    monkeypatch.setattr(cn, "_gaussian_noise_opencl", no_work)
    monkeypatch.setattr(cn.rng, "normal", no_work)
    monkeypatch.setattr(cn.rng, "poisson", no_work)
    out = np.full(3, -1.0)
    for bad in ("half", None, 32, "SINGLE"):
        with pytest.raises(ParameterError, match="precision.*'auto', 'double', 'single'"):
            cn.noisy_cube(np.ones(3), -np.ones(3), 1, out=out, precision=bad)       # before the variance check
        with pytest.raises(ParameterError, match="precision.*'auto', 'double', 'single'"):
            cn.poisson_draw(-np.ones(3), 1, precision=bad)
        with pytest.raises(ParameterError, match="precision.*'auto', 'double', 'single'"):
            cn.noisy_cube(np.ones(3), np.ones(3), 1, backend="numpy", precision=bad)
    assert np.all(out == -1.0)
    monkeypatch.setattr(flat, "_field_cube", no_work)
    for seed in (1, None):
        with pytest.raises(ParameterError, match="precision.*'auto', 'double', 'single'"):
            flat.get_cube(seed=seed, precision="quad")


@pytest.mark.slow
@pytest.mark.needs_opencl
def test_cube_noise_follows_the_precision():
    """build_cube's precision is also the noise draw's (``paths["noise_precision"]``): the single cube's
    noisy realisation is the single draw of its own signal and variance, whatever the λ chunking and
    the stored dtype; "double" keeps the twin's draw."""
    from slicersim import LazuliSupernova
    from slicersim.products.cube import build_cube
    sim = LazuliSupernova(0.5).simulation
    one = build_cube(sim, seed=8, precision="single", progress=False)
    assert one.paths["noise_precision"] == "single" and one.chunks == 1
    want = cn.noisy_cube(one.signal, one.variance, 8, precision="single")
    assert np.array_equal(one.noisy, want, equal_nan=True)
    chunked = build_cube(sim, seed=8, precision="single", progress=False, max_bytes=60 * 2**20, dtype=np.float32)
    assert chunked.chunks > 1 and chunked.noisy.dtype == np.float32
    want32 = cn.noisy_cube(chunked.signal, chunked.variance, 8, precision="single").astype(np.float32)
    assert np.array_equal(chunked.noisy, want32, equal_nan=True)
    double = build_cube(sim, seed=8, precision="double", progress=False)
    assert double.paths["noise_precision"] == "double" and "noise_precision" not in build_cube(sim).paths
    assert np.array_equal(double.noisy, cn.noisy_cube(double.signal, double.variance, 8, backend="numpy"))


@pytest.mark.needs_opencl
def test_noise_backend_refused_before_the_cube(monkeypatch):
    """P7: without fp64, build_cube(seed=…, backend="opencl") built the single-precision cube and only
    then refused the (double) noise draw.  The noise draw has single kernels now (runs without fp64:
    the tests above); a noise draw without them must still be refused before the cube."""
    from slicersim import LazuliSupernova
    from slicersim.backends import precision as prec
    from slicersim.errors import OpenCLUnavailableError
    from slicersim.products import cube as cube_module
    sim = LazuliSupernova(0.5).simulation
    monkeypatch.setattr(opencl, "device_supports_fp64", lambda: False)
    monkeypatch.delitem(prec.SINGLE_PRECISION_ERRORS, "noise")
    monkeypatch.setattr(prec, "DOUBLE_ONLY_PRODUCTS", ("noise",))   # still a product, without single kernels
    monkeypatch.setattr(prec, "DOUBLE_ONLY_PRODUCTS", ("noise",))      # registered, without single kernels
    called = []
    monkeypatch.setattr(cube_module, "detector_chunk", lambda *a, **k: called.append(1))
    with pytest.raises(OpenCLUnavailableError):
        cube_module.build_cube(sim, psf_profile="airy", seed=3, backend="opencl")
    assert not called
