"""GROUPDQ of level-1b files: absent by default (flight level-1b files carry none), saturation seen in
the observed DN with ``groupdq="observed"``, the simulator's (true-charge) flags only when asked."""
import numpy as np
import pytest
from stdatamodels.jwst import datamodels          # a [test] dependency (pyproject): never skipped

from slicersim.errors import ParameterError
from slicersim.io import uncal_meta
from slicersim.io.uncal import observed_saturation, read_uncal
from slicersim.products.ramps import simulate

NMD = (6, 2, 0)


def _rate(bright=3000.0):
    """Rows 0–3 saturate mid-ramp, rows 4–7 stay far below [e-/s]."""
    return np.concatenate([np.full((4, 12), bright), np.full((4, 12), 5.0)])


def _ramp(tmp_path, name, nmd=NMD, bright=3000.0, **kw):
    return simulate(_rate(bright), nmd=nmd, seed=7, out=str(tmp_path / name), tframe=2.0, ron=10.0,
                    backend="numpy", progress=False, **kw)


def test_default_level1b_has_no_groupdq(tmp_path):
    path = _ramp(tmp_path, "none.fits")
    sci, gdq, pdq, header = read_uncal(path)
    assert gdq is None and pdq is not None
    assert (sci[0, -1, :4] > 65400).all()                                    # saturated in the data
    model = datamodels.RampModel(path)                                       # a pipeline sees no flags
    assert not model.groupdq.any()


def _level(h):
    """The linear saturation reference level [DN] of a header's simulation parameters."""
    sigma = uncal_meta.group_sigma_dn(h["SLICERSIM GAIN"], h["SLICERSIM READNOISE"], h["NFRAMES"])
    plateau = h["SLICERSIM BIAS"] + h["SLICERSIM GAIN"] * h["SLICERSIM FULLWELL"]
    return uncal_meta.saturation_reference(plateau, h["SLICERSIM SATURATION"], sigma)


def test_observed_flags_follow_the_observed_signal(tmp_path):
    """SATURATED from the first group at or above the level (5 σ below the plateau, where a full
    pixel reads: the plateau's noise straddles 65535 and half of the full groups read below it)."""
    path = _ramp(tmp_path, "obs.fits", groupdq="observed")
    sci, gdq, _, header = read_uncal(path)
    level = _level(header)
    assert level == pytest.approx(65535 - 5 * 10.0 / np.sqrt(2))
    expected = np.where(np.logical_or.accumulate(sci >= level, axis=1), 2, 0)
    np.testing.assert_array_equal(gdq, expected)
    assert gdq[0, -1, :4].all() and not gdq[0, 0].any() and not gdq[0, :, 4:].any()
    assert (sci[0, -1, :4] < 65535).any()                   # flagged though below SATURATION


def test_truth_flags_only_when_asked_and_observed_ones_see_the_nonlinear_plateau(tmp_path):
    """With nonlinearity the true charge reaches the full well while the observed DN plateaus at
    61–64k, below SATURATION: the observed flags use that per-pixel plateau, so every flagged group
    reads within the noise of it, and the truth flags are the simulator's, given only when asked."""
    # 2750 e-/s: the full well (63535 e-) is crossed between the two frames of group 5
    kw = dict(effects="nonlinearity", nmd=(8, 2, 0), bright=2750.0)
    truth = read_uncal(_ramp(tmp_path, "t.fits", groupdq="truth", **kw))
    obs = read_uncal(_ramp(tmp_path, "o.fits", groupdq="observed", **kw))
    np.testing.assert_array_equal(truth[0], obs[0])                           # same seed, same SCI
    sci, flagged, true_flags = obs[0][0], obs[1][0] != 0, truth[1][0] != 0
    plateau = sci[-1, :4]
    assert plateau.max() < 65535 - 200                                        # never reaches SATURATION
    assert flagged[-1, :4].all() and not flagged[:, 4:].any()                 # yet flagged from the data
    np.testing.assert_array_equal(flagged, np.logical_or.accumulate(flagged, axis=0))
    assert (np.argmax(true_flags, axis=0)[:4] == 5).all()                     # the truth: charge full in group 5
    assert (sci[5, :4] < plateau - 500).all()                                 # ... which reads below the plateau
    assert (np.argmax(flagged, axis=0)[:4] == 6).all()                        # observed: the plateau, group 6
    assert (np.abs(sci[6, :4].astype(int) - plateau) < 5 * 10.0).all()


def test_observed_saturation_is_cumulative():
    sci = np.array([[10], [70], [60], [80]])                                 # dips after reaching 65
    np.testing.assert_array_equal(observed_saturation(sci, 65)[:, 0], [0, 2, 2, 2])


def test_groupdq_choice_is_checked(tmp_path):
    with pytest.raises(ParameterError, match="groupdq"):
        _ramp(tmp_path, "x.fits", groupdq="maybe")
    with pytest.raises(ParameterError, match="level-1b"):
        _ramp(tmp_path, "x.h5", groupdq="observed")
