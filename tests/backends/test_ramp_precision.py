"""Raw ramps in single precision (issue 12): the float build of ``kernels/ramp.cl`` against the
float64 twin, its Poisson draws against the exact distribution, counter-based invariance, devices
without fp64, and bad input.  The slope statistics (unbiased, Rauscher07 variance) run for both
precisions in tests/test_ramps.py."""
import math
import shutil
import subprocess

import h5py
import numpy as np
import pytest
from scipy import stats

from slicersim.backends import opencl
from slicersim.backends import precision as prec
from slicersim.backends.ramp import simulate_block_numpy, simulate_block_opencl
from slicersim.errors import OpenCLUnavailableError, ParameterError
from slicersim.physics.ramp import RampParameters
from slicersim.products.ramps import simulate


def _mixed_rates(seed, size):
    """μ [e-/frame] over sparse, inversion, PTRS, Gaussian and saturating pixels."""
    return 10 ** np.random.default_rng(seed).uniform(-3, 4.5, size)


@pytest.mark.needs_opencl_device
def test_single_equals_float64_twin_but_for_float_roundings():
    """Same Philox words: SCI differs from the float64 twin only where a float rounding moves rint
    (by 1 ADU) or a Poisson decision; the fraction stays below a bound derived here from float32
    rounding (not from the implementation's own table)."""
    p = RampParameters(nmd=(16, 8, 2), ron=12.0, ktc_noise=30.0, bias=1000.0, full_well=60000.0,
                       gauss_min_mean=3e3)
    mu = _mixed_rates(1, 40000)
    dead = np.zeros(mu.size, bool)
    twin = simulate_block_numpy(mu, dead, 11, 2, 77, p)
    single = simulate_block_opencl(mu, dead, 11, 2, 77, p, precision="single")
    diff = single[0].astype(np.int64) - twin[0].astype(np.int64)
    frac = np.mean(diff != 0)
    # Independent bound: a value is rint(bias + gain·(reset + mean)) evaluated in float32, 3 roundings
    # of ≤ 2^-24 relative each, so |error| ≤ 3·2^-24·|x| ADU; rint moves only where the fractional part
    # lies within |error| of ½ (fractional parts ~uniform): probability ≤ 3·2^-24·|x|, averaged over the
    # values (≈ 2.9e-3 here); + 1e-4 for the rarer moved Poisson decisions (bounded below).  Measured 6.6e-4.
    bound = 3 * 2.0**-24 * np.mean(np.abs(twin[0].astype(np.float64))) + 1e-4
    assert 0 < frac <= bound, (frac, bound)
    assert np.mean(np.abs(diff) > 1) < 1e-4                   # Poisson decisions moved: rarer still
    assert np.mean(single[1] != twin[1]) < 1e-3               # saturation flags
    dark = mu < 0.01                                          # sparse path, few events: rint only
    assert np.abs(diff[:, dark]).max() <= 1


@pytest.mark.needs_opencl_device
@pytest.mark.parametrize("mu", [0.3, 4.0, 25.0, 900.0, 2.2e4])
def test_single_poisson_draws_follow_the_exact_distribution(mu):
    """One frame's charge (MACC(2, 1, 0), no read or kTC noise, gain 1, bias 0): χ² of the single
    build's counts against the exact Poisson pmf (sparse, inversion and PTRS paths, the last at a
    mean whose float ln k! would lose 2^-24·2e5 ≈ 0.01 without the Stirling form), p > 1e-3."""
    npix = 60000
    p = RampParameters(nmd=(2, 1, 0), ron=0.0, ktc_noise=0.0, bias=0.0, gain=1.0, full_well=6e4,
                       saturation=65535, gauss_min_mean=np.inf)
    sci = simulate_block_opencl(np.full(npix, mu), np.zeros(npix, bool), 0, 0, 5, p, precision="single")[0]
    k = sci[0].astype(np.int64)
    edges = np.unique(stats.poisson.ppf(np.linspace(0.0, 1.0, 41)[1:-1], mu).astype(np.int64))
    observed = np.bincount(np.searchsorted(edges, k, side="right"), minlength=edges.size + 1)
    cdf = np.concatenate([[0.0], stats.poisson.cdf(edges - 1, mu), [1.0]])
    expected = npix * np.diff(cdf)
    keep = expected > 0
    chi2 = np.sum((observed[keep] - expected[keep]) ** 2 / expected[keep])
    pvalue = stats.chi2.sf(chi2, keep.sum() - 1)
    assert pvalue > 1e-3, (mu, chi2, keep.sum())
    assert abs(k.mean() - mu) < 4 * math.sqrt(mu / npix)


@pytest.mark.slow
@pytest.mark.needs_opencl_device
def test_single_is_counter_based():
    """Vector width, work-group size and chunking leave the single build's integers unchanged."""
    p = RampParameters(nmd=(8, 4, 1), ron=12.0, ktc_noise=20.0, gauss_min_mean=3e3)
    mu = _mixed_rates(3, 9000)
    dead = np.zeros(mu.size, bool)
    ref = simulate_block_opencl(mu, dead, 5, 0, 9, p, precision="single")[0]
    for vw, wg in ((1, None), (4, 1), (16, 256)):
        got = simulate_block_opencl(mu, dead, 5, 0, 9, p, vector_width=vw, work_group=wg, precision="single")[0]
        assert np.array_equal(got, ref), (vw, wg)
    a = simulate_block_opencl(mu[:4321], dead[:4321], 5, 0, 9, p, precision="single")[0]
    b = simulate_block_opencl(mu[4321:], dead[4321:], 5 + 4321, 0, 9, p, precision="single")[0]
    assert np.array_equal(np.concatenate([a, b], axis=1), ref)


@pytest.mark.skipif(shutil.which("cpp") is None, reason="no C preprocessor")
@pytest.mark.parametrize("vw", [1, 16])
@pytest.mark.parametrize("source, options, kernel", [("ramp.cl", (), "macc_ramp_dense"),
                                                     ("ramp.cl", ("-DRAMP_EFFECTS=1",), "take_deposits"),
                                                     ("ramp_readout.cl", (), "ramp_readout")])
def test_single_ramp_sources_hold_no_double(vw, source, options, kernel):
    """A device without fp64 compiles the single builds: after preprocessing with -DSINGLE, the
    samplers (plain and effects) and the readout (with philox.cl, vector_types.cl) hold no double."""
    kdir = opencl.kernel_dir()
    out = subprocess.run(["cpp", "-P", "-DSINGLE", f"-DRNG_VW={vw}", *options, f"-I{kdir}", f"{kdir}/{source}"],
                         capture_output=True, text=True, check=True).stdout
    assert kernel in out
    assert "double" not in out


@pytest.mark.needs_opencl_device
def test_device_without_fp64_runs_single_ramps(monkeypatch):
    """fp64 flag forced off: "auto" runs the single samplers (not NumPy), the same integers as
    "single"; "double" is one clear error; ramps with effects (double only) fall back to NumPy."""
    rate = np.random.default_rng(2).uniform(0, 300, (40, 50))
    single = simulate(rate, (6, 2, 1), seed=3, ktc_noise=10.0, precision="single")
    double = simulate(rate, (6, 2, 1), seed=3, ktc_noise=10.0)                  # auto: double on a CPU
    assert not np.array_equal(single, double)
    monkeypatch.setattr(opencl, "device_supports_fp64", lambda: False)
    assert np.array_equal(simulate(rate, (6, 2, 1), seed=3, ktc_noise=10.0), single)
    with pytest.raises(OpenCLUnavailableError, match="precision 'double' needs fp64"):
        simulate(rate, (6, 2, 1), seed=3, precision="double")
    fx = dict(seed=3, effects="cosmic_rays,ipc,nonlinearity")
    assert np.array_equal(simulate(rate, (6, 2, 1), **fx), simulate(rate, (6, 2, 1), precision="single", **fx))


def test_bad_precision_refused_before_any_file(tmp_path):
    out = tmp_path / "r.h5"
    for bad in ("half", None, 32, "SINGLE"):
        for effects in (None, "ipc"):
            with pytest.raises(ParameterError, match="precision.*'auto', 'double', 'single'"):
                simulate(np.ones((4, 4)), (3, 1, 0), out=str(out), precision=bad, effects=effects)
    assert not out.exists() and not list(tmp_path.iterdir())


@pytest.mark.needs_opencl_device
def test_single_with_effects_equals_float64_twin_but_for_float_roundings():
    """Every effect on (cosmic-ray deposits and nonlinearity in the charge sampler; IPC, correlated
    noise, bias map and digitisation in the readout): the single build differs from the float64
    NumPy twin by 1 ADU where a float rounding moves rint, in ≤ the ramp tolerance of the values
    (measured 8e-4), and by more only where it moves a Poisson decision (≤ 2e-4 of the values)."""
    rate = np.random.default_rng(2).uniform(0, 300, (64, 128))
    kw = dict(seed=3, ktc_noise=10.0, effects="all")
    twin = simulate(rate, (8, 4, 1), backend="numpy", **kw).astype(np.int64)
    single = simulate(rate, (8, 4, 1), precision="single", **kw).astype(np.int64)
    diff = single - twin
    assert 0 < np.mean(diff != 0) <= prec.SINGLE_PRECISION_ERRORS["ramp"].tolerance
    assert np.mean(np.abs(diff) > 1) <= 2e-4                  # a moved Poisson (PTRS) decision: rarer


@pytest.mark.needs_opencl_device
def test_file_records_the_precision(tmp_path):
    out = simulate(np.full((8, 8), 2.0), (3, 1, 0), out=str(tmp_path / "r.h5"), precision="single")
    with h5py.File(out) as f:
        assert f.attrs["PRECISION"] == "single"
    out = simulate(np.full((8, 8), 2.0), (3, 1, 0), out=str(tmp_path / "n.h5"), backend="numpy", precision="single")
    with h5py.File(out) as f:
        assert f.attrs["PRECISION"] == "double"               # the NumPy twin computes in float64


@pytest.mark.needs_opencl_device
def test_single_ptrs_log_acceptance_has_no_cancellation():
    """The PTRS acceptance ln P(k; μ) of the single build (``rng_log_poisson``) against SciPy's
    float64 logpmf: error ≤ 2e-6 + 2e-7 (|ln P| + |k − μ|) up to μ = 3e5 (measured 3e-6 there), where the direct float sum
    k ln μ − μ − ln k! would be off by ~2^-24 · 4e6 ≈ 0.2 (the acceptance biased by 20 %)."""
    import pyopencl as cl
    src = ('#include "ramp.cl"\n'
           "__kernel void logp(__global const float *k, __global const float *mu, __global float *out)\n"
           "{ const size_t i = get_global_id(0); out[i] = rng_log_poisson(k[i], mu[i], log(mu[i])); }\n")
    opts = [f"-I{opencl.kernel_dir()}", "-DRNG_VW=1", *opencl.precision_options("single")]
    logp = cl.Kernel(cl.Program(opencl.get_context(), src).build(options=opts), "logp")
    mus, ks = [], []
    for mu in (10.0, 20.0, 400.0, 2.2e4, 3e5):
        k = np.unique(np.rint(mu + math.sqrt(mu) * np.linspace(-6, 6, 241)).clip(0))
        mus.append(np.full(k.size, mu))
        ks.append(k)
    mu, k = (np.concatenate(a).astype(np.float32) for a in (mus, ks))
    out = np.empty_like(mu)
    buf = [opencl.to_device(a) for a in (k, mu)] + [opencl.device_buffer(out.nbytes)]
    opencl.launch(logp, (mu.size,), None, *buf)
    opencl.from_device(out, buf[2])
    exact = stats.poisson.logpmf(k.astype(np.float64), mu.astype(np.float64))
    err = np.abs(out - exact)
    assert np.all(err <= 2e-6 + 2e-7 * (np.abs(exact) + np.abs(k - mu))), err.max()


@pytest.mark.needs_opencl_device
def test_single_precision_selfcheck_guards_the_float_kernels(monkeypatch):
    """The single builds run only on a device that passes their own self-check (no fp64 needed):
    it passes here; a device whose float samplers are wrong makes "single" with backend="opencl"
    one clear error and "auto" fall back to NumPy with one warning, with or without fp64."""
    import warnings

    from slicersim.backends import dispatch, selfcheck
    from slicersim.backends import ramp as ramp_backend
    monkeypatch.delenv("SLICERSIM_TRUST_DEVICE", raising=False)
    monkeypatch.setattr(dispatch, "_SELFCHECK", {})
    ok, msg = selfcheck.device_selfcheck_single()
    assert ok, msg
    real_draws = selfcheck._single_noise_draws

    def biased():
        z, counts = real_draws()
        return [zz + 2e-3 for zz in z], counts                  # 2e-3 σ: beyond the noise tolerance
    monkeypatch.setattr(selfcheck, "_single_noise_draws", biased)
    ok, msg = selfcheck.device_selfcheck_single()
    assert not ok and "Gaussians off by up to 0.002 σ" in msg
    monkeypatch.setattr(selfcheck, "_single_noise_draws", real_draws)
    real = ramp_backend.simulate_block_opencl

    def broken(*args, precision="double", **kw):
        sci, gdq = real(*args, precision=precision, **kw)
        return (sci // 2 if precision == "single" else sci), gdq      # a miscompiled float path
    monkeypatch.setattr(ramp_backend, "simulate_block_opencl", broken)
    ok, msg = selfcheck.device_selfcheck_single()
    assert not ok and "single-precision noise and ramp self-check" in msg and "SCI" in msg
    assert selfcheck.device_selfcheck()[0]                      # the fp64 check does not see it
    monkeypatch.setattr(prec, "_warned_single", set())
    for fp64 in (True, False):
        monkeypatch.setattr(dispatch, "_SELFCHECK", {})
        monkeypatch.setattr(opencl, "device_supports_fp64", lambda fp64=fp64: fp64)
        with pytest.raises(OpenCLUnavailableError, match="single-precision noise and ramp self-check"):
            prec.resolve_precision("single", "opencl", "ramp")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            assert prec.resolve_precision("single", "auto", "ramp") == ("numpy", "double")
            if not fp64:
                assert prec.resolve_precision("auto", "auto", "cube") == ("numpy", "double")
        assert sum("single-precision noise and ramp self-check" in str(w.message) for w in caught) == (1 if fp64 else 0)


def test_opencl_backend_without_a_device_is_refused(monkeypatch):
    """Review finding: backend="opencl" with no usable OpenCL device (e.g. SLICERSIM_DEVICE=none) ran
    NumPy silently; it is one clear OpenCLUnavailableError again, "auto" still falls back."""
    def no_device():
        raise OpenCLUnavailableError("OpenCL disabled by SLICERSIM_DEVICE='none'.")
    monkeypatch.setattr(opencl, "is_available", lambda: False)
    monkeypatch.setattr(opencl, "get_device", no_device)
    monkeypatch.setattr(prec, "DOUBLE_ONLY_PRODUCTS", ("double_only",))     # a product without single kernels
    for product in ("cube", "ramp", "noise", "projection", "batch_etc", "double_only"):
        for precision in ("auto", "double", "single") if product != "double_only" else ("auto", "double"):
            with pytest.raises(OpenCLUnavailableError, match="SLICERSIM_DEVICE"):
                prec.resolve_precision(precision, "opencl", product)
            assert prec.resolve_precision(precision, "auto", product) == ("numpy", "double")
    with pytest.raises(OpenCLUnavailableError, match="SLICERSIM_DEVICE"):
        simulate(np.ones((4, 4)), (3, 1, 0), backend="opencl")


@pytest.mark.needs_opencl_device
def test_single_ramp_of_an_absurdly_bright_pixel_saturates():
    """μ beyond float32's range (rate 3e38 e-/s) came out at bias level, unflagged, in single: such
    rates (more than 1e9 e- per frame, ~1.6e4 full wells) are refused in both precisions, naming the
    rate; a bright but real pixel (1e7 e-/s) saturates in the first frame, with the same SCI and
    flags in single as in double (μ capped 64 σ above the full well).  A full well above 2^22 e- is
    refused in single."""
    for rate in (3e38, 1e100):
        for precision in ("single", "double"):
            with pytest.raises(ParameterError, match=r"^rate reaches .* e- per frame .* more than the 1e\+09 e- accepted"):
                simulate(np.full((2, 3), rate), (3, 1, 0), seed=0, precision=precision)
    s, q = simulate(np.full((2, 3), 1e7), (3, 1, 0), seed=0, precision="single", return_dq=True)
    d, qd = simulate(np.full((2, 3), 1e7), (3, 1, 0), seed=0, precision="double", return_dq=True)
    assert np.array_equal(s, d) and np.array_equal(q, qd) and np.all(q == 2)
    with pytest.raises(ParameterError, match="at most 4.194e\\+06 e- per frame"):
        simulate(np.full((2, 2), 1e8), (3, 1, 0), precision="single", gain=0.001)
