"""Our exact Airy cube against slicersim 1.0's (whose sub-sample grid is off and sums high).

Our Airy cube sums (true sub-cell centres, exact quadrature) are within 2 % of
the reference's per wavelength, and our point-source flux in the field equals
the analytic fraction of the Airy ⊗ jitter ⊗ blur pattern inside the field.
"""
import numpy as np
import pytest

from conftest import reference_config
from slicersim.targets import LazuliTarget

CASES = ["sn_z1.00_cbe_narrow_snr20", "sn_z1.00_cbe_wide_snr20"]


@pytest.mark.reference
@pytest.mark.parametrize("case", CASES)
def test_airy_cube_sums_within_two_percent_of_reference(case, refdir, reference_case):
    meta, arr = reference_case(case)
    inp = meta["inputs"]
    target = LazuliTarget(arr["input_lbda"], arr["input_flux"], config=reference_config(refdir, "cbe"),
                          field=inp["field"])
    readout = meta["cube"]["readout"]
    signal, _ = target.simulation.get_cube(nmd=tuple(readout["nmd"]), nramps=readout["nramps"],
                                           psf_profile="airy")
    ours = signal.sum(axis=(1, 2))
    ref = arr["cube_airy_signal_sum_adu"]
    ratio = ours / ref
    assert np.all(np.abs(ratio - 1) < 0.02), f"max deviation {np.max(np.abs(ratio - 1)):.3%}"
    # the reference is known high: ours is lower on average
    assert np.mean(ratio) < 1.0


def test_airy_field_flux_matches_analytic_fraction():
    """Point-source flux captured by the field = exact flux of the blurred Airy pattern in the field."""
    from slicersim.backends.psf import psf_cube
    from slicersim.physics.psf import airy_rectangle_fraction
    lbda = np.array([4000.0, 9000.0, 16000.0])
    shape = (21, 41)
    kw = dict(spatial_scale=0.04, guiding_sigma=0.0, instrumental_sigma=0.0, diameter=3.0)
    cube = psf_cube(lbda, shape, (0.0, 0.0), profile="airy", oversampling=9, **kw)
    for i, lam in enumerate(lbda):
        kwave = np.pi * 3.0 * 0.04 * np.pi / 648000.0 / (lam * 1e-10)      # v = k r, r in cells
        expected = airy_rectangle_fraction(shape[1] / 2, shape[0] / 2, kwave)
        assert cube[i].sum() == pytest.approx(expected, abs=2e-4)
