"""Windows: a rectangle of the detector simulated alone on the full detector's clock equals, bit for
bit, the same pixels cut from a full-detector ramp of the same seed (correlated 1/f noise, bias and
nonlinearity maps, cosmic rays, IPC included), and is written with SUBARRAY/SUBSTRT/SUBSIZE."""
import warnings

import numpy as np
import pytest
from stdatamodels.jwst import datamodels          # a [test] dependency (pyproject): never skipped

from slicersim.errors import ParameterError
from slicersim.io.rampfile import read_ramps
from slicersim.io.uncal import read_uncal, read_uncal_truth, write_uncal_from_hdf5
from slicersim.products.ramps import simulate
from slicersim.products.windows import check_window

NMD = (3, 2, 0)
WIN = (40, 16, 32, 24)                            # x0, y0, nx, ny: 8 of 32 outputs, rows 16–39


def _rate():
    return np.random.default_rng(1).uniform(0, 50, (64, 128))        # a 64×128 detector, 32 outputs of 4


@pytest.fixture(scope="module")
def full():
    return simulate(_rate(), nmd=NMD, seed=5, backend="numpy", progress=False, effects="lazuli", return_dq=True)


def _cut(a):
    x0, y0, nx, ny = WIN
    return a[..., y0:y0 + ny, x0:x0 + nx]


@pytest.mark.parametrize("backend", ["numpy", "auto"])
def test_window_is_bit_identical_to_the_cut_full_ramp(full, backend):
    sci, gdq = simulate(_rate(), nmd=NMD, seed=5, backend=backend, progress=False, effects="lazuli",
                        return_dq=True, window=WIN)
    assert sci.shape == (1, NMD[0], 24, 32)
    np.testing.assert_array_equal(sci, _cut(full[0]))
    np.testing.assert_array_equal(gdq, _cut(full[1]))
    # the window does carry correlated noise: its CDS rows are not white (row means vary beyond white)
    cds = np.diff(sci[0].astype(float), axis=0)[0]
    assert np.std(cds.mean(axis=1)) > 0


def test_window_level1b_file(tmp_path, full):
    path = simulate(_rate(), nmd=NMD, seed=5, backend="numpy", progress=False, effects="lazuli", window=WIN,
                    out=str(tmp_path / "w.fits"))
    sci, gdq, pdq, h = read_uncal(path)
    np.testing.assert_array_equal(sci, _cut(full[0]))
    assert gdq is None and pdq.shape == (24, 32)
    assert (h["SUBARRAY"], h["SUBSTRT1"], h["SUBSTRT2"], h["SUBSIZE1"], h["SUBSIZE2"]) == ("GENERIC", 41, 17, 32, 24)
    assert (h["FASTAXIS"], h["SLOWAXIS"]) == (1, 2)
    np.testing.assert_array_equal(read_uncal_truth(path)["truth/rate"], _cut(_rate()).astype(np.float32))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = datamodels.Level1bModel(path)
        model.validate()
    complaints = {str(w.message).split()[2] for w in caught}
    assert complaints <= {"meta.instrument.name", "meta.instrument.detector", "meta.exposure.type",
                          "meta.exposure.readpatt"}, complaints
    assert (model.meta.subarray.xstart, model.meta.subarray.ystart, model.meta.subarray.xsize) == (41, 17, 32)


def test_window_hdf5_converts_with_its_place(tmp_path, full):
    h5 = simulate(_rate(), nmd=NMD, seed=5, backend="numpy", progress=False, effects="lazuli", window=WIN,
                  out=str(tmp_path / "w.h5"))
    sci, _, _, attrs = read_ramps(h5)
    np.testing.assert_array_equal(sci, _cut(full[0]))
    assert (attrs["SUBSTRT1"], attrs["SUBSTRT2"]) == (41, 17) and (attrs["DETECTOR_NY"], attrs["DETECTOR_NX"]) == (64, 128)
    h = read_uncal(write_uncal_from_hdf5(h5, tmp_path / "w.fits"))[3]
    assert (h["SUBARRAY"], h["SUBSTRT1"], h["SUBSTRT2"], h["SUBSIZE1"], h["SUBSIZE2"]) == ("GENERIC", 41, 17, 32, 24)


def test_whole_detector_window_is_full():
    assert check_window((0, 0, 128, 64), (64, 128)).substrt == (1, 1)


@pytest.mark.parametrize("window", [(0, 0, 129, 64), (-1, 0, 4, 4), (0, 60, 4, 5), (1, 2, 3), (0, 0, 0, 4),
                                    (0.5, 0, 4, 4), "1 2 3 4"])
def test_bad_window_is_one_clear_error(window):
    with pytest.raises(ParameterError, match="window"):
        simulate(_rate(), nmd=NMD, seed=5, backend="numpy", progress=False, window=window)
