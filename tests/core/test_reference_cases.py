"""Every public reference case reproduces in search="reference" mode.

Configured with the reference's own Lazuli files (TOML + curves), the readout
(n, m, d) and number of ramps are identical, the total exposure time agrees to
1e-6 relative and every stored array of the Gaussian path agrees to 1e-6 of its
peak (float64 everywhere; the measured agreement is ~2e-8, set by the rounded
h c constant of the reference).  Skipped when ../shared/reference is absent.
"""
import numpy as np
import pytest

from conftest import reference_case_ids, reference_target
from slicersim.simulation import VARIANCE_SOURCES

PEAK_TOL = 1e-6

pytestmark = pytest.mark.reference
CASES = reference_case_ids()


def assert_peak_close(name, got, ref, tol=PEAK_TOL, peak=None):
    got, ref = np.asarray(got, dtype=float), np.asarray(ref, dtype=float)
    assert got.shape == ref.shape, f"{name}: shape {got.shape} != {ref.shape}"
    assert np.array_equal(np.isnan(got), np.isnan(ref)), f"{name}: NaN pattern differs"
    scale = np.nanmax(np.abs(ref)) if peak is None else peak
    err = np.nanmax(np.abs(got - ref)) / scale if scale > 0 else np.nanmax(np.abs(got))
    assert err <= tol, f"{name}: max error {err:.3e} of peak > {tol}"


@pytest.fixture(scope="module", params=CASES or ["none"])
def solved(request, refdir, reference_case):
    meta, arrays = reference_case(request.param)
    inp = meta["inputs"]
    target = reference_target(refdir, meta, arrays, position=False)
    result = target.setup_to_snr(inp["snr_target_per_resolution_element"], lbda_range=inp["lbda_range_AA"],
                                 frame="obs", search="reference")
    return meta, arrays, target, result


def test_readout_and_exposure_time(solved):
    meta, _, target, result = solved
    out = meta["outputs"]
    assert tuple(result["nmd"]) == tuple(out["nmd"])
    assert result["nramps"] == out["nramps"]
    assert target.get_readout_config() == {"nmd": tuple(out["nmd"]), "nramps": out["nramps"]}
    assert target.get_exposure_time() == pytest.approx(out["exposure_time_total_s"], rel=1e-6)
    assert result["snr"] == pytest.approx(out["band_snr_per_bin"], rel=1e-6)
    assert target.get_data_volume() == pytest.approx(out["data_volume_GB"], rel=1e-12)


def test_search_trace(solved):
    meta, _, _, result = solved
    trace = meta["outputs"]["search_trace"]
    assert len(result["trace"]) == len(trace) == meta["outputs"]["n_search_snr_evaluations"]
    for (nmd, r, snr), ref in zip(result["trace"], trace):
        assert (tuple(nmd), r) == (tuple(ref["nmd"]), ref["nramps"])
        assert snr == pytest.approx(ref["snr_per_bin"], rel=1e-6)


def test_instrument_arrays(solved):
    meta, arr, target, _ = solved
    sim = target.simulation
    inst = meta["instrument"]
    assert sim.lbda.size == inst["nlbda"]
    assert len(sim.aperture[0]) == inst["aperture_ncells"]
    assert sim.thermal_dark == pytest.approx(inst["thermal_dark_e_per_s_per_px"], rel=1e-6)
    assert_peak_close("lbda", sim.lbda, arr["lbda"])
    assert_peak_close("lbda_edges", sim.spectrograph.lbda_edges, arr["lbda_edges"])
    assert_peak_close("throughput", sim.spectrograph.throughput, arr["throughput"])
    assert_peak_close("qe", sim.qe, arr["qe"])
    assert_peak_close("flambda2photon", sim.flambda_to_photon, arr["flambda2photon"])
    assert_peak_close("resolving_power", sim.spectrograph.resolving_power, arr["resolving_power"])
    assert_peak_close("pointsource", sim.pointsource_flambda, arr["scene_pointsource_flambda"])
    assert_peak_close("background", sim.background_photons, arr["background_ph_s_per_cell_noLSF"])
    assert_peak_close("thermal", sim.thermal_photons, arr["thermal_ph_s_per_cell_noLSF"])
    assert_peak_close("psf_sigma_y", sim.psf_sigmas[0], arr["psf_sigma_y_cells"])
    assert_peak_close("psf_sigma_x", sim.psf_sigmas[1], arr["psf_sigma_x_cells"])
    tint = sim.get_times()["integration_time_per_ramp"]
    assert_peak_close("photonflux_to_adu", sim.qe * tint * sim.detector.gain, arr["photonflux_to_adu"])


def test_spectrum_snr_and_variance_budget(solved):
    _, arr, target, _ = solved
    lbda, signal, variance = target.get_spectrum()
    assert_peak_close("spectrum_signal", signal, arr["spectrum_signal_adu"])
    assert_peak_close("spectrum_variance", variance, arr["spectrum_variance_adu2"])
    assert_peak_close("snr", signal / np.sqrt(variance), arr["snr_per_bin"])
    contrib = target.get_variance_contribution()
    peak = np.nanmax(arr["spectrum_variance_adu2"])
    for src in VARIANCE_SOURCES:
        assert_peak_close(f"var_contrib_{src}", contrib[src], arr[f"var_contrib_{src}_adu2"], peak=peak)


def test_band_variance_budget(solved):
    meta, _, target, _ = solved
    ref = meta["outputs"]["band_variance_contribution"]
    got = target.simulation.get_band_variance_contribution(meta["inputs"]["lbda_range_AA"])
    for src in VARIANCE_SOURCES:
        assert got[src] == pytest.approx(ref[src], abs=1e-6 * ref["variance"])
    assert got["exposure_time"] == pytest.approx(ref["obstime"], rel=1e-9)   # reference: "obstime"


def test_gaussian_cube(solved):
    meta, arr, target, _ = solved
    readout = meta["cube"]["readout"]
    signal, variance = target.simulation.get_cube(nmd=tuple(readout["nmd"]), nramps=readout["nramps"])
    idx = meta["cube"]["slice_indices"]
    assert signal.shape == tuple(meta["cube"]["default"]["shape"])
    assert int(np.count_nonzero(~np.isfinite(signal))) == meta["cube"]["default"]["n_nonfinite"]
    assert_peak_close("cube signal sum", signal.sum(axis=(1, 2)), arr["cube_default_signal_sum_adu"])
    assert_peak_close("cube variance sum", variance.sum(axis=(1, 2)), arr["cube_default_variance_sum_adu2"])
    assert_peak_close("cube signal slices", signal[idx], arr["cube_default_signal_slices_adu"])
    assert_peak_close("cube variance slices", variance[idx], arr["cube_default_variance_slices_adu2"])
    assert signal.sum() == pytest.approx(meta["cube"]["default"]["sum_signal_adu"], rel=1e-6)
    _, sig, var = target.simulation.get_spectrum(nmd=tuple(readout["nmd"]), nramps=readout["nramps"])
    assert_peak_close("cube-readout spectrum", sig, arr["cubero_spectrum_signal_adu"])
    assert_peak_close("cube-readout variance", var, arr["cubero_spectrum_variance_default_adu2"])


def test_compare_helper_agrees(solved, refdir):
    """The reference's own checker accepts our numbers."""
    import importlib.util
    spec = importlib.util.spec_from_file_location("ref_compare", refdir / "compare.py")
    compare = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(compare)
    meta, _, target, _ = solved
    lbda, signal, variance = target.get_spectrum()
    candidate = {"outputs.nmd": list(target.get_readout_config()["nmd"]),
                 "outputs.nramps": target.get_readout_config()["nramps"],
                 "outputs.exposure_time_total_s": target.get_exposure_time(),
                 "spectrum_signal_adu": signal, "spectrum_variance_adu2": variance}
    res = compare.compare_case(meta["case_id"], candidate, rtol=1e-6, peak_atol=1e-6, root=str(refdir),
                               verbose=False)
    assert res["__all_passed__"], {k: v for k, v in res.items() if k != "__all_passed__"}
