"""A real downstream client: stcal (JWST pipeline) ramp fitting of our HDF5 ramps.

The rate recovered by stcal's OLS fit agrees with the input within stcal's own
reported errors: the pull (rate − input)/err has mean ≈ 0 and width ≈ 1, and
saturated groups flagged in GROUPDQ are honoured (bright pixels stay unbiased).
"""
import numpy as np
import pytest
import stcal.ramp_fitting.ramp_fit as stcal_fit          # a [test] dependency (pyproject): never skipped
from stcal.ramp_fitting.ramp_fit_class import RampData

from slicersim.io.rampfile import read_ramps
from slicersim.products.ramps import simulate

JWST_DQ = {"GOOD": 0, "DO_NOT_USE": 1, "SATURATED": 2, "JUMP_DET": 4, "PERSISTENCE": 32,
           "CHARGELOSS": 128, "NO_GAIN_VALUE": 524288, "UNRELIABLE_SLOPE": 16777216}


def stcal_rates(path):
    sci, gdq, pdq, attrs = read_ramps(path)
    ramp = RampData()
    ramp.set_arrays(sci.astype(np.float32), gdq.copy(), pdq.copy(),
                    np.zeros(pdq.shape, np.float32))
    ramp.set_meta(name="NIRSPEC", frame_time=float(attrs["TFRAME"]), group_time=float(attrs["TGROUP"]),
                  groupgap=int(attrs["GROUPGAP"]), nframes=int(attrs["NFRAMES"]), drop_frames1=None)
    ramp.set_dqflags(JWST_DQ)
    ramp.start_row, ramp.num_rows = 0, sci.shape[2]
    ramp.suppress_one_group_ramps = False
    shape = pdq.shape
    # stcal takes the CDS read noise (of a difference of two frames) [DN]: √2 σ_frame g;
    # the ±½ ADU rounding of every group adds (1/12)·m in frame units, included here
    sigma = np.sqrt(float(attrs["READNOISE"]) ** 2 + int(attrs["NFRAMES"]) / 12.0)
    readnoise = np.full(shape, np.sqrt(2.0) * sigma * float(attrs["GAIN"]), np.float32)
    gain = np.full(shape, float(attrs["GAIN"]), np.float32)
    image, _, _ = stcal_fit.ramp_fit_data(ramp, False, readnoise, gain, "OLS_C", "optimal", "none")
    if isinstance(image, dict):
        return image["slope"], image["err"], image["dq"]
    slope, dq, _, _, err = image
    return slope, err, dq


@pytest.mark.parametrize("nmd", [(12, 4, 0), (8, 1, 2)])
def test_stcal_recovers_rates_with_unit_pull(tmp_path, nmd):
    rng = np.random.default_rng(3)
    rate = np.repeat(10 ** rng.uniform(-1, 2.3, 60), 100).reshape(60, 100)      # 0.1 … 200 e-/s
    path = simulate(rate, nmd, seed=19, out=tmp_path / "r.h5", ron=10.0, dark=0.0, roic_glow=0.0)
    slope, err, _ = stcal_rates(path)
    pull = (slope - rate) / err
    pull = pull[np.isfinite(pull)]
    assert pull.size > 0.99 * rate.size
    n = pull.size
    assert abs(pull.mean()) < 5 / np.sqrt(n) + 0.02, f"pull mean {pull.mean():.3f}"
    assert abs(pull.std() - 1.0) < 0.05, f"pull width {pull.std():.3f}"


def test_stcal_honours_saturation_flags(tmp_path):
    nmd = (10, 4, 0)
    rate = np.concatenate([np.full((20, 100), 800.0), np.full((20, 100), 20.0)])   # bright saturate mid-ramp
    path = simulate(rate, nmd, seed=4, out=tmp_path / "sat.h5", ron=10.0, dark=0.0, roic_glow=0.0)
    sci, gdq, _, _ = read_ramps(path)
    assert (gdq[0, -1, :20] == 2).all() and not gdq[0, :, 20:].any()
    slope, err, _ = stcal_rates(path)
    bright = slope[:20]
    assert abs(np.nanmean(bright) - 800.0) < 4 * np.nanstd(bright) / np.sqrt(bright.size)
    pull = ((slope[:20] - 800.0) / err[:20]).ravel()
    assert abs(pull.std() - 1) < 0.1


def test_stcal_runs_on_a_lazuli_level1b_file_with_its_header_units(tmp_path):
    """A level-1b file with every Lazuli effect: RampModel opens it (no GROUPDQ: zeros), stcal fits it
    with the gain [e-/DN] and CDS read noise [DN] of its header as they are, and the slopes of faint
    pixels agree with the input (pull width near 1 with the white read noise alone)."""
    from stdatamodels.jwst import datamodels

    from slicersim.io.uncal import read_uncal
    nmd = (10, 4, 0)
    rate = np.full((64, 128), 20.0)
    path = simulate(rate, nmd, seed=8, out=tmp_path / "lz.fits", ron=10.0, dark=0.0, roic_glow=0.0, gain=0.8,
                    effects="lazuli", progress=False)
    h = read_uncal(path)[3]
    model = datamodels.RampModel(str(path))
    assert not model.groupdq.any() and h["INSTRUME"] == "LAZULI_IFS"
    ramp = RampData()
    ramp.set_arrays(model.data.astype(np.float32), model.groupdq.copy(), model.pixeldq.copy(),
                    np.zeros(model.pixeldq.shape, np.float32))
    ramp.set_meta(name="NIRSPEC", frame_time=h["TFRAME"], group_time=h["TGROUP"], groupgap=h["GROUPGAP"],
                  nframes=h["NFRAMES"], drop_frames1=None)
    ramp.set_dqflags(JWST_DQ)
    ramp.start_row, ramp.num_rows = 0, model.data.shape[2]
    ramp.suppress_one_group_ramps = False
    shape = model.pixeldq.shape
    # the header's CDS read noise plus the rounding of each group mean (1/12 DN², m/6 DN² in CDS frame units)
    readnoise = np.full(shape, np.sqrt(h["RDNCDSDN"] ** 2 + h["NFRAMES"] / 6.0), np.float32)
    gain = np.full(shape, h["GAINEDN"], np.float32)
    image, _, _ = stcal_fit.ramp_fit_data(ramp, False, readnoise, gain, "OLS_C", "optimal", "none")
    slope, err = (image["slope"], image["err"]) if isinstance(image, dict) else (image[0], image[4])
    science = (model.pixeldq == 0) & np.isfinite(slope)         # not a reference or bad pixel
    rates = slope[science] * h["GAINEDN"]                         # DN/s → e-/s
    assert abs(np.median(rates) - 20.0) < 0.5, np.median(rates)   # bias/IPC/nonlinearity: small at 20 e-/s
    pull = ((slope - 20.0 / h["GAINEDN"]) / err)[science]
    width = 1.4826 * np.median(np.abs(pull - np.median(pull)))    # robust: cosmic-ray outliers aside
    print(f"median rate {np.median(rates):.3f} e-/s, robust pull width {width:.3f}")
    assert 0.9 < width < 3.0                     # ≥ 1: correlated noise adds to the header's white read noise
