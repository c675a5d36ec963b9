"""Absolute units of the signal chain, computed by hand from the documented parameters.

Every other fast test checks the model against its own ``telescope.area`` or ``flambda_to_photon``,
so a factor common to both (a ×10 collecting area, m² taken for dm²) cancels there.  Here the
expected count rate of a flat F_λ point source is written out from the configuration's numbers
alone: the photons per second of F_λ through the telescope's collecting area
A = π/4 (D_ext² − D_int²), in a bin of width Δλ at λ, are F_λ A Δλ λ / (h c); with unit throughput
and QE they are electrons, read as ``gain`` ADU each, and integrate for (n − 1)(m + d) t_frame
per MACC(n, m, d) ramp.  Only the wavelength grid (λ, Δλ) is taken from the model."""
import math

import numpy as np
import pytest

import slicersim

#: CODATA 2018 (exact): Planck constant [erg s], speed of light [Å/s]
H_ERG_S, C_AA_S = 6.62607015e-27, 2.99792458e18
#: the configuration of the test: documented keys, round values
D_EXT, D_INT, GAIN, TFRAME = 3.0, 1.0, 2.0, 2.83           # [m], [m], [ADU/e-], [s] (Lazuli CBE t_frame)
FLAMBDA = 1e-17                                           # [erg/s/cm²/Å]
NMD = (16, 8, 0)
OVERLAY = f"""
[telescope]
diameter_ext = {D_EXT}
diameter_int = {D_INT}
[spectrograph]
spectral_range = [9000, 10000]
[spectrograph.throughput]
throughput = 1.0
[detector]
QE = 1.0
gain = {GAIN}
tframe = {TFRAME}
"""


@pytest.fixture(scope="module")
def flat_source(tmp_path_factory):
    path = tmp_path_factory.mktemp("cfg") / "unit_chain.toml"
    path.write_text(OVERLAY, encoding="utf-8")
    lbda = np.arange(3000.0, 20000.0, 10.0)
    return slicersim.LazuliTarget(lbda, np.full(lbda.size, FLAMBDA), config=["cbe", str(path)])


def test_area_by_hand():
    area_cm2 = math.pi / 4 * (D_EXT**2 - D_INT**2) * 1e4       # 2π m² = 62 832 cm²
    assert area_cm2 == pytest.approx(62831.853, rel=1e-7)
    # ≈ 0.30 e-/s per Å at 9500 Å: the order of magnitude, independent of the code's grid
    assert FLAMBDA * area_cm2 * 9500.0 / (H_ERG_S * C_AA_S) == pytest.approx(0.30049, rel=1e-4)


def test_extracted_point_source_rate_in_absolute_units(flat_source):
    sim = flat_source.simulation
    lbda, signal, _ = sim.get_spectrum(nmd=NMD, nramps=1)
    n, m, d = NMD
    t_int = (n - 1) * (m + d) * TFRAME                         # [s] MACC integration time of one ramp
    area_cm2 = math.pi / 4 * (D_EXT**2 - D_INT**2) * 1e4
    electrons_per_s = FLAMBDA * area_cm2 * sim.spectrograph.dlbda * lbda / (H_ERG_S * C_AA_S)
    expected = electrons_per_s * GAIN * t_int                   # [ADU] per bin
    # the Gaussian-weighted extraction of a point source keeps all of its light (1e-5), away from
    # the two edge bins that the LSF spills over
    ratio = signal[2:-2] / expected[2:-2]
    assert np.all(np.abs(ratio - 1.0) < 2e-3), ratio
    # ≈ 300 e-/s over 9000–10000 Å: F_λ A ∫λ dλ / (h c) = 300.5 e-/s, whatever the grid
    edges = sim.spectrograph.lbda_edges
    assert (edges[0], edges[-1]) == pytest.approx((9000.0, 10000.0), abs=20.0)
    assert signal.sum() / (GAIN * t_int) == pytest.approx(300.5 * (edges[-1]**2 - edges[0]**2) / 1.9e7, rel=5e-3)
