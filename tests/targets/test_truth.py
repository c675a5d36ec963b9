"""target_truth: the expected rate and ETC variance are the simulation's own."""
from __future__ import annotations

import numpy as np
import pytest

from slicersim.targets import LazuliTarget
from slicersim.targets.truth import target_truth


def test_rate_is_flambda_through_the_instrument_and_the_etc_variance_gives_its_snr():
    lb = np.arange(3000.0, 20000.0, 10.0)
    target = LazuliTarget(lb, np.full(lb.size, 2e-18), redshift=0.9, field="wide")
    nmd, nramps = (12, 4, 0), 3
    truth = target_truth(target, nmd, nramps, target_id=7, phase=1.0)
    sim = target.simulation
    assert truth.lbda.size == sim.lbda.size and np.all(truth.dlbda > 0)
    assert truth.attrs["redshift"] == 0.9 and truth.attrs["field"] == "wide" and truth.attrs["phase"] == 1.0
    assert truth.attrs["phase_frame"] == "rest" and truth.attrs["cell_scale"] == sim.spectrograph.spatial_scale
    # a flat F_λ: the LSF leaves F_λ f2p QE unchanged away from the grid's ends
    expect = 2e-18 * sim.flambda_to_photon * sim.qe
    inner = slice(20, -20)
    assert np.allclose(truth.rate[inner], expect[inner], rtol=2e-3)
    assert np.allclose(truth.flambda, 2e-18)
    # the ETC's band SNR (per bin) from the truth's rate and variance, for the readout given
    band = (11000.0, 14000.0)
    mask = (sim.lbda >= band[0]) & (sim.lbda <= band[1])
    snr = truth.rate[mask].mean() / np.sqrt(truth.etc_variance[mask].mean())
    assert snr == pytest.approx(sim.get_band_snr(band, nmd=nmd, nramps=nramps, frame="obs"), rel=1e-9)


def test_a_supernova_records_its_own_phase_and_magnitude():
    from slicersim.targets import LazuliSupernova
    sn = LazuliSupernova(0.5, phase=-2.0, peak_absmag=-19.1)
    truth = target_truth(sn, (8, 4, 0), 1)
    assert (truth.attrs["phase"], truth.attrs["peak_absmag"], truth.attrs["source"]) == (-2.0, -19.1,
                                                                                        "hsiao-subsampled")
    assert target_truth(sn, (8, 4, 0), 1, phase=-2.5).attrs["phase"] == -2.5      # the caller's values win
