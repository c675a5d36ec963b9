"""truth/target: the target's truth in ramp files, HDF5 and level-1b FITS, read back as written."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from slicersim.errors import RampFileError
from slicersim.io.target_truth import COLUMNS, TargetTruth, read_target_truth
from slicersim.products.ramps import simulate


def _truth():
    lbda = np.linspace(9000.0, 9900.0, 7)
    return TargetTruth({"target_id": 4, "redshift": 0.7, "phase": -3.5, "phase_frame": "rest", "field": "wide",
                        "x1": None, "c": np.nan, "source": "hsiao-subsampled", "nmd": (8, 4, 0)},
                       lbda, np.full(7, 150.0), np.linspace(1e-17, 2e-17, 7), np.arange(7.0) + 10,
                       etc_variance=np.full(7, 2.5))


@pytest.mark.parametrize("name", ["ramps.h5", "ramps.fits"])
def test_written_with_the_ramps_and_read_back(tmp_path, name):
    truth = _truth()
    path = simulate(np.full((16, 24), 5.0), (3, 1, 0), seed=1, out=tmp_path / name, progress=False, target=truth)
    back = read_target_truth(path)
    for col in COLUMNS:
        assert np.array_equal(getattr(back, col), getattr(truth, col)), col
    # None and NaN attributes are left out; tuples as JSON; every column's unit alongside
    assert back.attrs == {"target_id": 4, "redshift": 0.7, "phase": -3.5, "phase_frame": "rest", "field": "wide",
                          "source": "hsiao-subsampled", "nmd": "[8, 4, 0]"}
    if name.endswith(".h5"):
        with h5py.File(path, "r") as fh:
            dset = fh["truth/target"]
            assert dset.fletcher32 and dset.chunks is not None      # checksummed like every truth dataset
            assert dset.attrs["unit_rate"] == "electron/s" and dset.attrs["unit_flambda"] == "erg/s/cm2/Angstrom"
            assert dset.attrs["unit_phase"].startswith("day (rest frame")
    # the same ramps without the truth: identical SCI, and no truth/target
    plain = simulate(np.full((16, 24), 5.0), (3, 1, 0), seed=1, out=tmp_path / f"plain_{name}", progress=False)
    assert read_target_truth(plain) is None


def test_columns_must_have_one_length():
    with pytest.raises(RampFileError, match="flambda has 3 values"):
        TargetTruth({}, np.arange(4.0), np.ones(4), np.ones(3), np.ones(4))
    t = TargetTruth({}, np.array([10.0, 20.0]), np.array([10.0, 10.0]), np.ones(2), np.ones(2))
    assert np.isnan(t.etc_variance).all() and t.edges().tolist() == [5.0, 15.0, 25.0]


def test_kept_by_the_conversion_to_level_1b(tmp_path):
    from slicersim.io.uncal import write_uncal_from_hdf5
    truth = _truth()
    h5 = simulate(np.full((16, 24), 5.0), (3, 1, 0), seed=1, out=tmp_path / "r.h5", progress=False, target=truth)
    back = read_target_truth(write_uncal_from_hdf5(h5, tmp_path / "r.fits"))
    assert np.array_equal(back.rate, truth.rate) and back.attrs == read_target_truth(h5).attrs
