"""The batch ETC's band-variance kernel in single precision (issue 12): float kernel with
compensated sums against the float64 NumPy twin, a survey plan in both precisions, the dial's
plumbing (solve_many, plan_survey, ``slicersim survey plan --precision``) and bad input.  The
single-target ETC stays float64 whatever the device."""
import shutil
import subprocess
import warnings

import numpy as np
import pytest

from slicersim.backends import opencl
from slicersim.backends import precision as prec
from slicersim.backends.band_variance import band_variance_table
from slicersim.errors import ParameterError


def _tables(seed=1, N=60, nl=200, nc=40, K=70):
    g = np.random.default_rng(seed)
    Q = g.uniform(0, 50, (N, nl, nc))
    Q[min(3, N - 1), min(17, nl - 1)] = np.nan                    # an invalid bin
    P2 = g.uniform(0, 1, (nl, nc))
    P2[P2 < 0.3] = 0
    A, B = g.uniform(50, 200, K), g.uniform(0.5, 2, K)
    S = np.full(K, 40.0)
    S[::7] = np.inf
    S[min(5, K - 1)] = -1.0                                       # every cell saturated: +inf
    band = np.stack([g.integers(0, nl // 4 + 1, N), g.integers(nl // 2, nl + 1, N)], 1)
    return Q, P2, A, B, S, band


@pytest.mark.needs_opencl_device
def test_single_band_variance_matches_the_float64_twin():
    """Relative error ≤ 5e-7 (measured 1.1e-7: float32 inputs, compensated sums), the same +inf
    (saturated) pattern and the same valid-bin counts."""
    args = _tables()
    want = band_variance_table(*args, backend="numpy")
    got = band_variance_table(*args, precision="single")
    assert got[0].dtype == np.float64
    assert np.array_equal(np.isinf(got[0]), np.isinf(want[0])) and np.isinf(want[0]).any()
    assert np.array_equal(got[1], want[1])
    fin = np.isfinite(want[0])
    assert np.max(np.abs(got[0][fin] / want[0][fin] - 1)) <= 5e-7


@pytest.mark.needs_opencl_device
def test_single_band_sum_is_compensated():
    """4000 bins of one cell each, variances spread over 1e-3 … 1e3: a plain float sum drifts by
    ~1e-5 (n ulps in the worst case), the compensated one stays within 3e-7."""
    g = np.random.default_rng(4)
    nl = 4000
    Q = np.zeros((2, nl, 1))
    P2 = 10 ** g.uniform(-3, 3, (nl, 1))
    A, B, S = np.array([100.0]), np.array([1.0]), np.array([np.inf])
    band = np.array([[0, nl], [10, nl - 10]])
    want = band_variance_table(Q, P2, A, B, S, band, backend="numpy")[0]
    got = band_variance_table(Q, P2, A, B, S, band, precision="single")[0]
    assert np.max(np.abs(got / want - 1)) <= 3e-7


@pytest.mark.skipif(shutil.which("cpp") is None, reason="no C preprocessor")
def test_single_band_variance_source_holds_no_double():
    out = subprocess.run(["cpp", "-P", "-DSINGLE", "-DVW=8", f"-I{opencl.kernel_dir()}",
                          f"{opencl.kernel_dir()}/band_variance.cl"], capture_output=True, text=True, check=True).stdout
    assert "band_variance" in out and "double" not in out


@pytest.mark.needs_opencl_device
def test_survey_plan_in_both_precisions():
    """A 24-SN plan: the same readouts, SNR within 1e-6 relative; the totals record the precision."""
    from slicersim.campaign.plan import plan_survey
    from slicersim.campaign.population import SNIaPopulation
    from slicersim.campaign.products import spectrum_grid
    lbda = spectrum_grid()
    pop = SNIaPopulation(24, redshift={"distribution": "uniform", "min": 0.1, "max": 1.4})
    table = pop.draw(5)
    fluxes = np.nan_to_num(pop.spectra(table, lbda))
    plans = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for p in ("double", "single"):
            plans[p] = plan_survey(np.asarray(table["redshift"]), lbda, fluxes, precision=p)
    a, b = plans["double"].table, plans["single"].table
    for key in ("n", "m", "d", "nramps"):
        assert np.array_equal(a[key], b[key]), key
    assert np.max(np.abs(np.asarray(b["snr"]) / np.asarray(a["snr"]) - 1)) <= 1e-6
    assert plans["single"].totals["precision"] == "single" and plans["double"].totals["precision"] == "double"


def test_bad_precision_refused_before_work():
    from slicersim.campaign.plan import plan_survey
    from slicersim.etc.solve import solve_many
    for bad in ("half", None, 1):
        with pytest.raises(ParameterError, match="precision.*'auto', 'double', 'single'"):
            plan_survey([0.5], np.array([1000.0, 2e4]), np.ones((1, 2)), precision=bad)
        with pytest.raises(ParameterError, match="precision.*'auto', 'double', 'single'"):
            solve_many(np.array([1000.0, 2e4]), np.ones((1, 2)), 20.0, (4000, 6000), precision=bad)
        if bad is not None:                                     # None: the single-target ETC's float64
            with pytest.raises(ParameterError, match="precision.*'auto', 'double', 'single'"):
                band_variance_table(*_tables(N=2, nl=4, nc=2, K=2), precision=bad)


@pytest.mark.needs_opencl_device
def test_without_fp64_batch_runs_single_and_the_etc_stays_float64(monkeypatch):
    """fp64 forced off: the batch ETC's "auto" runs the float kernel; the single-target ETC
    (precision None) takes the float64 NumPy twin, as before."""
    args = _tables(N=4, nl=30, nc=6, K=9)
    single = band_variance_table(*args, precision="single")
    monkeypatch.setattr(opencl, "device_supports_fp64", lambda: False)
    assert np.array_equal(band_variance_table(*args, precision="auto")[0], single[0])
    etc = band_variance_table(*args)
    assert np.array_equal(etc[0], band_variance_table(*args, backend="numpy")[0])
    assert prec.resolve_precision("auto", "auto", "batch_etc") == ("opencl", "single")
