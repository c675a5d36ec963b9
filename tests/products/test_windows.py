"""Windows: a rectangle of the detector simulated alone on the full detector's clock equals, bit for
bit, the same pixels cut from a full-detector ramp of the same seed (correlated 1/f noise, bias and
nonlinearity maps, cosmic rays, IPC included), and is written with SUBARRAY/SUBSTRT/SUBSIZE."""
import warnings

import numpy as np
import pytest
from stdatamodels.jwst import datamodels          # a [test] dependency (pyproject): never skipped

from slicersim.errors import ParameterError, RampFileError
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


# --------------------------------------------------------------------------- some rows (rows=)
ROWS = ((0, 4), (20, 37), (44, 53), (60, 64))    # border rows, two bands of a field, bottom border rows


def _rows_file(tmp_path, rows=ROWS, name="rows.h5", **kw):
    return simulate(_rate(), nmd=NMD, seed=5, backend="numpy", progress=False, effects="lazuli", rows=rows,
                    out=str(tmp_path / name), **kw)


def test_rows_are_bit_identical_to_the_full_ramp_and_the_rest_absent(tmp_path, full, monkeypatch):
    import h5py
    from slicersim.io import rampfile
    from slicersim.io.rampfile import open_hdf5_input
    monkeypatch.setattr(rampfile, "LAZY_BLOCK_BYTES", 8 * 128 * 6 * 4)       # lazy truth in blocks of 8 rows
    from slicersim.reduction.ramp_sources import open_ramps
    path = _rows_file(tmp_path)
    with h5py.File(path, "r") as fh:
        assert fh.attrs["SIMULATED_ROWS"] == "[[0, 4], [20, 37], [44, 53], [60, 64]]"
        sci = fh["SCI"]
        c = sci.chunks[2]
        held = {k for a, b in ROWS for k in range(a // c, (b - 1) // c + 1)}
        assert sci.id.get_num_chunks() == NMD[0] * len(held)        # nothing written outside the ranges
        for a, b in ROWS:
            np.testing.assert_array_equal(sci[:, :, a:b], full[0][:, :, a:b])
    # the lazy truth (nonlinearity coefficients) computed and written on those rows only
    whole = simulate(_rate(), nmd=NMD, seed=5, backend="numpy", progress=False, effects="lazuli",
                     out=str(tmp_path / "whole.h5"))
    with h5py.File(path, "r") as fh, h5py.File(whole, "r") as fw:
        for name in ("truth/nonlinearity/inverse_coefficients", "truth/nonlinearity/coefficients"):
            for a, b in ROWS:
                np.testing.assert_array_equal(fh[name][:, a:b], fw[name][:, a:b])
            assert not fh[name][:, 12:20].any()             # past the first block: never computed (fill value)
        np.testing.assert_array_equal(fh["truth/bias"][...], fw["truth/bias"][...])
    # readers of whole ramps refuse the file with one clear line; the ramp source reads its rows
    with pytest.raises(RampFileError, match=r"holds only detector rows 0:4, 20:37, 44:53, 60:64"):
        read_ramps(path)
    with pytest.raises(RampFileError, match="holds only detector rows"):
        open_hdf5_input(path).close()
    with open_ramps(path) as src:
        assert src.rows == ROWS


def test_rows_fit_as_the_full_ramp_there_and_nan_elsewhere(tmp_path):
    from slicersim.reduction.ramp_fit import fit_ramps
    whole = simulate(_rate(), nmd=NMD, seed=5, backend="numpy", progress=False, effects="lazuli",
                     out=str(tmp_path / "whole.h5"))
    part = _rows_file(tmp_path)
    a, b = fit_ramps(whole, backend="numpy"), fit_ramps(part, backend="numpy")
    held = np.zeros(64, bool)
    for y0, y1 in ROWS:
        held[y0:y1] = True
    assert np.isnan(b.rate[~held]).all() and (b.dq[~held] & 1).all()
    # away from the ranges' edges (the side reference terms are smoothed over 11 rows) the rates are the same
    inner = np.zeros(64, bool)
    inner[25:32] = True
    np.testing.assert_array_equal(b.rate[inner], a.rate[inner])
    np.testing.assert_array_equal(b.variance[inner], a.variance[inner])
    assert np.isfinite(b.rate[held]).mean() > 0.99


def test_rows_without_the_reference_rows_refuse_the_refpix_correction(tmp_path):
    from slicersim.reduction.ramp_fit import fit_ramps
    path = _rows_file(tmp_path, rows=((20, 37),))
    with pytest.raises(RampFileError, match="top and bottom 4 reference rows"):
        fit_ramps(path, backend="numpy")
    assert np.isfinite(fit_ramps(path, backend="numpy", refpix=False).rate[20:37]).mean() > 0.99


@pytest.mark.parametrize("rows, match", [(((0, 65),), "not inside"), (((5, 5),), "not inside"), ((), "at least one"),
                                         ("0 4", "sequence"), (((0.5, 4),), "sequence"), (((0, 4, 5),), "sequence"),
                                         (((0, float("inf")),), "sequence"), (np.array([[0, np.inf]]), "sequence")])
def test_bad_rows_are_one_clear_error(tmp_path, rows, match):
    with pytest.raises(ParameterError, match=match):
        _rows_file(tmp_path, rows=rows)
    assert not list(tmp_path.iterdir())


def test_rows_need_an_hdf5_file_and_no_window(tmp_path):
    with pytest.raises(ParameterError, match="HDF5 out file"):
        simulate(_rate(), nmd=NMD, seed=5, backend="numpy", progress=False, rows=ROWS)
    with pytest.raises(ParameterError, match="HDF5 out file"):
        _rows_file(tmp_path, name="r.fits")
    with pytest.raises(ParameterError, match="not both"):
        _rows_file(tmp_path, window=WIN)
    assert not list(tmp_path.iterdir())


def test_overlapping_rows_are_merged():
    from slicersim.io.row_blocks import row_ranges
    assert row_ranges([(10, 20), (0, 4), (15, 30), (30, 31)], 64) == ((0, 4), (10, 31))


@pytest.mark.parametrize("forged, match", [("[[0, 4], [8, 12], [60, 64]]", r"stores \d+ of its \d+ chunks of rows 0:4, 8:12"),
                                           ("[[0, Infinity]]", "not a list of"), ("[[0, 4], [20, 37], [60, 64]]", None)])
def test_forged_simulated_rows_are_refused_or_read_as_written(tmp_path, forged, match):
    """SIMULATED_ROWS naming rows whose chunks were never written (a count of the chunks stored passed
    them, read as zeros: rates of 0), or not integers, is one RampFileError; naming fewer rows than
    written, the file is read on those."""
    import h5py
    from slicersim.reduction.ramp_fit import fit_ramps
    path = _rows_file(tmp_path, max_bytes=60000)                  # SCI chunks of a few rows
    with h5py.File(path, "r+") as fh:
        assert fh["SCI"].chunks[2] <= 4
        fh.attrs["SIMULATED_ROWS"] = forged
    if match is None:
        assert np.isnan(fit_ramps(path, backend="numpy").rate[44:53]).all()
        return
    with pytest.raises(RampFileError, match=match):
        fit_ramps(path, backend="numpy", refpix=False)


def test_rows_files_count_only_their_rows(tmp_path, monkeypatch):
    """The free-space checks of a file of some rows: its rows' bytes before the simulation, and the
    compression measured once the first ramp's last range is written (not only at the detector's last row)."""
    from slicersim.io.rampfile import RampWriter
    writer = RampWriter(str(tmp_path / "w.h5"), 2, 3, (64, 128), rows=((0, 4), (20, 30)), pixeldq=False)
    assert writer.expected_bytes() == 2 * 3 * 14 * 128 * 3
    measured = []
    monkeypatch.setattr(RampWriter, "_check_measured_space", lambda self: measured.append(True))
    _rows_file(tmp_path, rows=((0, 4), (20, 30)), nramps=2, compression="gzip")
    assert measured == [True]
