"""Band SNR (slicersim.snr.bands): bands the spectrum or the grid does not cover, default frame."""
import numpy as np
import pytest

import slicersim
from slicersim.errors import SlicersimError, SpectrumError


LBDA = np.linspace(3000.0, 20000.0, 500)


FLUX = np.full(500, 1e-18)


def target(**kw):
    return slicersim.LazuliTarget(LBDA, FLUX, **kw)


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


def test_supernova_band_snr_default_frame_matches_setup():
    """LazuliSupernova.setup_to_snr(20) defaults to frame='rest' (4000-6800 rest); then
    get_band_snr(per_resolution=True) defaults to frame='obs': 2.24 instead of 20.2."""
    sn = slicersim.LazuliSupernova(redshift=1.0)
    res = sn.setup_to_snr(20)
    assert sn.get_band_snr(per_resolution=True) == pytest.approx(res["snr_per_resolution"], rel=1e-6)
