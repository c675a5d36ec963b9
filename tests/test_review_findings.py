"""Review findings (adversarial use of the model API).  Every test here FAILS on the
reviewed commit (93d5788) and documents one finding; see the docstring of each test.

Principle tested: "a self-consistent model that never gives a silent wrong answer":
invalid input raises a SlicersimError and leaves the object unchanged; valid input
gives finite, physically meaningful numbers.
"""
import math
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import slicersim
from slicersim.errors import ETCError, ParameterError, ReadoutError, SlicersimError, SpectrumError

BAND = (9000.0, 12000.0)
LBDA = np.linspace(3000.0, 20000.0, 500)
FLUX = np.full(500, 1e-18)


def target(**kw):
    return slicersim.LazuliTarget(LBDA, FLUX, **kw)


def state(t):
    sim = t.simulation
    _, sig, var = sim.get_spectrum()
    return (sim.get_band_snr(BAND), float(np.sum(sig)), float(np.sum(var)),
            sim.get_times()["exposure_time"], t.get_readout_config(), sim.lbda.size)


def assert_rejected_unchanged(t, func, exc=SlicersimError, match=None):
    before = state(t)
    with pytest.raises(exc, match=match):
        func()
    assert repr(state(t)) == repr(before)


# --------------------------------------------------------------------- crashes
@pytest.mark.parametrize("params", [dict(config="eol", nramps=2), dict(field="wide", nmd=(20, 8, 0))])
def test_update_config_or_field_with_readout_crashes(params):
    """Target.update(config=..., nramps=...) / (field=..., nmd=...) raises
    TypeError "dict() got multiple values for keyword argument" for ANY (even valid)
    readout: _new_simulation builds dict(nmd=old, nramps=old, **upd)."""
    t = target()
    t.update(**params)
    assert t.simulation.nramps == params.get("nramps", 1)
    assert t.simulation.detector.nmd == params.get("nmd", (16, 8, 0))


def test_setup_to_snr_huge_target_does_not_hang():
    """setup_to_snr(1e6) (exact search) loops in Python over every nramps from r_min to
    2 r_min + 10 (~1e8 iterations): hangs for minutes.  Must answer (or raise ETCError) fast."""
    code = textwrap.dedent("""
        import numpy as np, slicersim
        from slicersim.errors import ETCError
        t = slicersim.LazuliTarget(np.linspace(3000, 20000, 500), np.full(500, 1e-18))
        try:
            print("ANSWERED", t.setup_to_snr(1e6, (9000, 12000)))
        except ETCError as exc:
            print(f"ETCError: {exc}")
    """)
    # the hang took minutes; 60 s leaves room for the import on a loaded 2-core machine (~2 s idle);
    # the answer: one ETCError naming the exposure limit (SNR 1e6 needs far more than a year)
    run = subprocess.run([sys.executable, "-c", code], timeout=60, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert run.stdout.startswith("ETCError: target SNR 1e+06 in the band 9000–12000 Å exceeds the exposure "
                                 "limit: it needs more than MAX_TOTAL_EXPOSURE"), run.stdout


def test_spectral_range_huge_is_parameter_error():
    """spectrograph.update(spectral_range=(4000, 1e9)) -> MemoryError (151 PiB array)."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.simulation.spectrograph.update(spectral_range=(4000, 1e9)))


# --------------------------------------------------------------- wrong answers
def test_throughput_curve_not_covering_grid_is_not_extrapolated():
    """set_throughput(curve on 8000-9000 Å) is cubic-extrapolated over 4000-17000 Å:
    throughput from -2168 to 258 -> negative signal/variance, NaN band SNR, no error."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.set_throughput(([8e3, 8.3e3, 8.6e3, 9e3], [0.1, 0.5, 0.9, 0.5])),
                              ParameterError, r"throughput curve total covers 8000-9000 Å only, not the "
                              r"instrument's 4000-16984.4 Å \(curves are not extrapolated\)")


@pytest.mark.parametrize("values", [[-0.5] * 4, [5.0] * 4])
def test_throughput_curve_outside_0_1_rejected(values):
    """A scalar throughput outside [0, 1] raises, but a curve of -0.5 (negative signal
    and variance, NaN SNR) or 5 (SNR x4.4) is accepted."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.set_throughput(([1e3, 2e3, 3e3, 4e4], values)))


def test_noptics_negative_rejected():
    """set_throughput(0.5, noptics=-1) gives T = 0.5**-1 = 2 (SNR 9.6 -> 25.2)."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.set_throughput(0.5, noptics=-1))


def test_spectral_range_outside_dispersion_law():
    """spectral_range=(100, 200) silently gives a 4000-5374 Å grid; (4000, 30000) gives
    943 bins with throughput extrapolated to -169 and NaN spectra."""
    for rng in ((100.0, 200.0), (4000.0, 30000.0)):
        t = target()
        spec = t.simulation.spectrograph
        assert_rejected_unchanged(t, lambda: spec.update(spectral_range=rng), ParameterError,
                                  rf"spectral_range \({rng[0]}, {rng[1]}\) Å lies outside the dispersion law's "
                                  r"wavelength coverage \[4000, 17000.1\] Å \(no extrapolation\)")


@pytest.mark.parametrize("qe", [([1e3, 3e4], [-1.0, -1.0]), ([1e3, 3e4], [np.nan, np.nan]),
                                ([1.0, 2.0], [3.0]), 5.0])
def test_qe_validated(qe):
    """QE curves are not validated at all: negative QE gives band SNR -55.9, NaN QE NaN
    spectra, mismatched lengths are accepted and break every later call; a scalar QE up
    to 10 e-/ph is accepted."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.update(qe=qe))


@pytest.mark.parametrize("params", [dict(gain=math.inf), dict(tframe=math.inf), dict(pixel_size=math.inf),
                                    dict(saturation=math.nan), dict(saturation=-5.0),
                                    dict(diameter_ext=math.inf), dict(spatial_scale=math.nan),
                                    dict(spatial_scale=math.inf), dict(emissivity=5.0)])
def test_nonfinite_or_unphysical_instrument_values_rejected(params):
    """Accepted silently; results become inf/NaN SNRs, SNR 0 (all cells 'saturated') or
    no saturation at all (saturation=nan), emissivity 5."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.update(**params))


def test_optics_negative_emissivity_rejected():
    """spectrograph optics emissivity -1 accepted: negative thermal photons lower the variance."""
    t = target()
    k = len(t.simulation.spectrograph.optics["emissivity"])
    assert_rejected_unchanged(t, lambda: t.simulation.spectrograph.update(optics={"emissivity": [-1.0] * k}))


@pytest.mark.parametrize("rng", [(5.0, 1.0), "x", (math.nan, 1.0)])
def test_thermal_dark_range_validated(rng):
    """Reversed range silently gives thermal dark 0; 'x' / NaN are accepted and every
    later get_spectrum raises a bare ValueError (object broken)."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.update(thermal_dark_range=rng))


def test_max_group_enforced_by_simulation_update():
    """change_detector checks max_group but Simulation.update(nmd=(100, 8, 0)) does not
    (max_group 64): the ETC and the current readout disagree."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.simulation.update(nmd=(100, 8, 0)), ReadoutError)


def test_max_group_below_current_n_rejected():
    """update(max_group=5) with nmd n = 16 is accepted: inconsistent state."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.update(max_group=5))


@pytest.mark.parametrize("value", [0, -5, 1.5])
def test_max_group_invalid_values(value):
    """max_group 0 / -5 silently mean 'no limit' (None); change_detector(max_group=1.5)
    truncates to 1."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.change_detector(max_group=value))


def test_band_snr_does_not_ignore_uncovered_bins():
    """Spectrum covers 8000-10000 Å only; the band SNR is a nanmean, so the band
    7000-11000 reports the SNR of 8000-10000 (33.7) as if it were covered."""
    t = slicersim.LazuliTarget(np.linspace(8000, 10000, 100), np.full(100, 1e-17))
    with pytest.raises(SpectrumError, match=r"the source spectrum \(8000–10000 Å\) covers only 50.0 % of the "
                                            r"band 7000–11000 Å.*allow_partial=True in Python, --allow-partial"):
        t.get_band_snr((7000, 11000))


def test_band_snr_outside_spectrum_raises():
    """Band 4000-6800 entirely outside the spectrum (8000-10000): returns nan, no error
    (errors.py: SpectrumError is for 'a band the spectrum/grid does not cover')."""
    t = slicersim.LazuliTarget(np.linspace(8000, 10000, 100), np.full(100, 1e-17))
    with pytest.raises(SpectrumError):
        t.get_band_snr((4000, 6800))


def test_band_partially_outside_grid_raises():
    """(3000, 5000) on a 4000-16984 Å grid is silently truncated to 4000-5000."""
    t = target()
    with pytest.raises(SlicersimError):
        t.get_band_snr((3000, 5000))


def test_reference_search_far_below_target_is_flagged():
    """search='reference' with snr=1e9 returns SNR 1.2e6 (1000x below) as a normal result."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.setup_to_snr(1e9, BAND, search="reference"), ETCError,
                              r"target SNR 1e\+09 in the band 9000–12000 Å cannot be reached within the "
                              r"exposure limit: it needs more than MAX_TOTAL_EXPOSURE")


@pytest.mark.parametrize("z", [-1.0, math.nan, "x"])
def test_target_constructor_validates_redshift(z):
    """Target.update rejects these redshifts, the constructor accepts them; frame='rest'
    then maps bands to (0, 0) / (nan, nan) Å."""
    with pytest.raises(SlicersimError):
        target(redshift=z)


def test_mag_nan_rejected():
    """LazuliTarget(..., mag=nan) is accepted: every spectrum is NaN, band SNR nan."""
    with pytest.raises(SpectrumError):
        target(mag=math.nan)


def test_position_outside_field_rejected():
    """position=(1000, 0) is accepted: empty aperture, variance inf, band SNR 0.0 while the
    signal stays the full spectrum."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.update(position=(1000.0, 0.0)))


def test_empty_aperture_rejected():
    """aperture_radius_insigma=1e-9: no aperture cell, band SNR 0.0, no error."""
    t = target()
    assert_rejected_unchanged(t, lambda: t.update(aperture_radius_insigma=1e-9))


def test_supernova_band_snr_default_frame_matches_setup():
    """LazuliSupernova.setup_to_snr(20) defaults to frame='rest' (4000-6800 rest); then
    get_band_snr(per_resolution=True) defaults to frame='obs': 2.24 instead of 20.2."""
    sn = slicersim.LazuliSupernova(redshift=1.0)
    res = sn.setup_to_snr(20)
    assert sn.get_band_snr(per_resolution=True) == pytest.approx(res["snr_per_resolution"], rel=1e-6)


# --------------------------------------------------------------- unclear errors
@pytest.mark.parametrize("call", [
    lambda t: t.update(nramps=math.nan),                     # ValueError: cannot convert float NaN
    lambda t: t.update(nramps=math.inf),                     # OverflowError
    lambda t: t.update(nramps=None),                         # TypeError
    lambda t: t.change_detector(max_group="x"),              # ValueError: invalid literal for int()
    lambda t: t.update(redshift="1"),                        # TypeError: ufunc 'isfinite'
    lambda t: t.update(config=None),                         # TypeError: 'NoneType' not iterable
    lambda t: t.setup_to_snr("x", (9000, 12000)),            # TypeError: ufunc 'isfinite'
    lambda t: t.simulation.get_band_snr((100, 200)),         # ValueError (doc: SpectrumError)
    lambda t: t.set_throughput("0.5"),                       # CurveError, not a SlicersimError
    lambda t: t.get_spectrum(incl_error=True, seed=-1),      # ValueError
    lambda t: t.simulation.get_cube(seed=1.5),               # TypeError
])
def test_bad_input_raises_slicersim_error(call):
    """errors.py: 'All user-facing errors derive from SlicersimError'.  These raise bare
    ValueError / TypeError / OverflowError / CurveError."""
    t = target()
    assert_rejected_unchanged(t, lambda: call(t))


def test_spectrum_outside_instrument_is_spectrum_error():
    """A spectrum at 30000-40000 Å raises a bare ValueError from Simulation._check_overlap."""
    with pytest.raises(SpectrumError):
        slicersim.LazuliTarget(np.linspace(30000, 40000, 10), np.full(10, 1e-17))


def test_supernova_out_of_range_redshift_message():
    """LazuliSupernova(redshift=50) says 'pointsource: empty wavelength array'."""
    with pytest.raises(SlicersimError, match="redshift"):
        slicersim.LazuliSupernova(redshift=50)


# ------------------------------------------------------------------------ CLI
def test_cli_etc_prints_units_and_no_object_repr():
    """`slicersim etc --redshift 1 --snr 20` prints exposure_time / data_volume /
    lbda_range_obs without units and 'target : <slicersim.targets.LazuliSupernova object at 0x..>'."""
    out = subprocess.run([sys.executable, "-m", "slicersim", "etc", "--redshift", "1.0", "--snr", "20"],
                         capture_output=True, text=True, timeout=30, check=True).stdout
    assert "object at 0x" not in out
    # the CLI now prints units in brackets after the key ("exposure_time [s]", "data_volume [GB]")
    assert "[GB]" in out and "[s]" in out and "[Angstrom]" in out


def test_partial_spectral_range_starts_at_its_own_wavelength():
    """A spectral_range that does not begin where the dispersion law's offset is 0 gave (like slicersim
    1.0) the right number of bins at the wrong wavelengths (47 bins at 4000–4255 Å for 9000–11000 Å).
    Now the bins are the sub-grid of the full grid that covers the range."""
    import numpy as np

    from slicersim import LazuliTarget
    t = LazuliTarget(np.linspace(3000, 18000, 100), np.full(100, 1e-17))
    full = t.simulation.spectrograph.lbda.copy()
    full_edges = t.simulation.spectrograph.lbda_edges.copy()
    t.update(spectral_range=(9000, 11000))
    part = t.simulation.spectrograph.lbda
    edges = t.simulation.spectrograph.lbda_edges
    assert part[0] - 9000 < np.diff(edges)[0] and 11000 - part[-1] < np.diff(edges)[-1]
    i = np.argmin(abs(full - part[0]))
    np.testing.assert_allclose(part, full[i:i + part.size], rtol=1e-12)
    np.testing.assert_allclose(edges, full_edges[i:i + part.size + 1], rtol=1e-12)
