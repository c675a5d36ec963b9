"""Calibration values in the JWST conventions (:mod:`slicersim.physics.calibration`)."""
import numpy as np
import pytest

from slicersim.errors import EffectsError
from slicersim.physics.calibration import (cds_read_noise, dark_frames, frame_read_noise_dn, gain_e_per_dn,
                                           saturation_level)
from slicersim.physics.nonlinearity import measured_charge


def test_gain_and_cds_read_noise_in_jwst_units():
    assert gain_e_per_dn(0.5) == 2.0
    # a CDS of two single-frame reads: √2 × one read's noise, rounding to integer DN included
    assert cds_read_noise(12.0, 1.0) == pytest.approx(np.sqrt(2 * (144 + 1 / 12)))
    assert cds_read_noise(0.0, 1.0) == pytest.approx(np.sqrt(1 / 6))
    assert frame_read_noise_dn(10.0, 2.0) == pytest.approx(np.sqrt(400 + 1 / 12))
    with pytest.raises(EffectsError, match="gain"):
        gain_e_per_dn(0.0)


def test_the_saturation_level_lies_below_every_full_pixel_read():
    a2 = np.array([-6e-7, -9e-7])
    a3 = np.array([-2e-12, -4e-12])
    bias, gain, fw = np.array([2000.0, 2300.0]), 0.9, 60000.0
    full = bias + gain * measured_charge(fw, a2, a3)
    level = saturation_level(bias, gain, fw, a2, a3, read_noise_dn=10.0)
    assert np.allclose(level, full - 50.0)                    # 5 read noises below the full-well read
    under_ipc = saturation_level(bias, gain, fw, a2, a3, ipc_centre=0.9, read_noise_dn=10.0)
    assert np.allclose(under_ipc, bias + 0.9 * (full - bias) - 50.0)
    clipped = saturation_level(np.array([5000.0]), 1.0, 63000.0, read_noise_dn=2.0)
    assert clipped[0] == pytest.approx(65535.0 - 10.0)         # the ADC saturates first


def test_the_dark_ramp_grows_one_frame_charge_per_frame():
    mu = np.array([[0.0, 1.5], [10.0, 0.25]])
    dark = dark_frames(mu, 2.0, 5)
    assert dark.shape == (5, 2, 2) and dark.dtype == np.float32
    assert np.allclose(dark[0], 2.0 * mu) and np.allclose(np.diff(dark, axis=0), 2.0 * mu)
    with pytest.raises(EffectsError, match="dark frames"):
        dark_frames(mu, 1.0, 1)
