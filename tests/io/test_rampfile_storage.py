"""Disk use of ramp files: GROUPDQ stored only where a group carries a flag, flags and truth
compressed losslessly, file bytes independent of the run; readers see the arrays of the earlier
(dense, uncompressed) layout."""
from __future__ import annotations

import hashlib

import h5py
import numpy as np
import pytest

from slicersim.io.rampfile import DQ, RampWriter, read_ramps

ATTRS = {"NFRAMES": 1, "GROUPGAP": 0, "TFRAME": 10.0, "GAIN": 1.0, "READNOISE": 5.0, "NINTS": 1, "NGROUPS": 4}
SHAPE, NGROUPS, ROWS = (64, 128), 4, 16


def _ramp():
    """SCI (1, 4, 64, 128) of a 2 e-/s/px sky, with 3 pixels saturating from group 2 in rows 16-31,
    GROUPDQ flagging them, PIXELDQ with one hot pixel, a smooth truth rate."""
    rng = np.random.default_rng(5)
    rate = 2.0 + 0.01 * np.arange(SHAPE[1])[None, :] + np.zeros(SHAPE)
    groups = np.arange(1, NGROUPS + 1)[:, None, None] * ATTRS["TFRAME"] * rate
    sci = (1000 + groups + rng.normal(0, 5, (NGROUPS,) + SHAPE)).round().astype(np.uint16)[None]
    gdq = np.zeros_like(sci, dtype=np.uint8)
    for y, x in ((17, 3), (20, 90), (30, 127)):
        sci[0, 2:, y, x] = 65535
        gdq[0, 2:, y, x] = DQ["SATURATED"]
    pixdq = np.zeros(SHAPE, np.uint32)
    pixdq[40, 40] = DQ["HOT"]
    return sci, gdq, pixdq, rate.astype(np.float32)


def _write(path, sci, gdq, pixdq, rate, compression=None):
    with RampWriter(path, 1, NGROUPS, SHAPE, attrs=ATTRS, row_block=ROWS, compression=compression,
                    truth_rate=True) as w:
        for y0 in range(0, SHAPE[0], ROWS):
            w.write_block(0, y0, sci[0, :, y0:y0 + ROWS], gdq[0, :, y0:y0 + ROWS])
        w.write_pixeldq(pixdq)
        w.write_truth(rate)
    return path


def _dense_copy(src, dst):
    """The same ramp in the earlier layout: every dataset whole, uncompressed (Fletcher-32 only)."""
    with h5py.File(src, "r") as a, h5py.File(dst, "w") as b:
        for key in a.attrs:
            b.attrs[key] = a.attrs[key]
        for name in ("SCI", "GROUPDQ", "PIXELDQ", "truth/rate"):
            b.create_dataset(name, data=a[name][...], chunks=a[name].chunks, fletcher32=True)
    return dst


def _stored(path, name):
    with h5py.File(path, "r") as fh:
        return fh[name].id.get_storage_size(), fh[name].id.get_num_chunks()


def test_groupdq_is_stored_only_where_a_group_has_a_flag_and_reads_as_written(tmp_path):
    sci, gdq, pixdq, rate = _ramp()
    path = _write(tmp_path / "r.h5", sci, gdq, pixdq, rate)
    # flags in rows 16-31 (one row block), groups 2 and 3: 2 of the 4 groups × 4 blocks chunks
    nbytes, nchunks = _stored(path, "GROUPDQ")
    assert nchunks == 2 and nbytes < 0.05 * gdq.nbytes
    with h5py.File(path, "r") as fh:
        assert fh["GROUPDQ"].attrs["SPARSE"] and fh["GROUPDQ"].fletcher32
        assert fh["GROUPDQ"].compression == "gzip" and fh["PIXELDQ"].compression == "gzip"
    got = read_ramps(path)
    assert np.array_equal(got[0], sci) and np.array_equal(got[1], gdq) and np.array_equal(got[2], pixdq)
    assert got[1].dtype == np.uint8 and got[1].shape == sci.shape


def test_flags_and_truth_take_a_fraction_of_their_dense_bytes(tmp_path):
    sci, gdq, pixdq, rate = _ramp()
    new = _write(tmp_path / "new.h5", sci, gdq, pixdq, rate)
    old = _dense_copy(new, tmp_path / "old.h5")
    for name, at_most in (("GROUPDQ", 0.05), ("PIXELDQ", 0.1), ("truth/rate", 0.6)):
        assert _stored(new, name)[0] < at_most * _stored(old, name)[0], name
    assert _stored(new, "SCI") == _stored(old, "SCI")              # SCI as before (no compression asked)
    import os
    assert os.path.getsize(new) < os.path.getsize(old) - 0.9 * gdq.nbytes
    with h5py.File(new, "r") as fh:
        assert np.array_equal(fh["truth/rate"][...], rate)         # lossless


@pytest.mark.parametrize("compression", [None, "lz4"])
def test_readers_give_the_same_rates_on_the_new_and_the_earlier_layout(tmp_path, compression):
    from slicersim.reduction.ramp_fit import fit_ramps
    sci, gdq, pixdq, rate = _ramp()
    new = _write(tmp_path / "new.h5", sci, gdq, pixdq, rate, compression)
    old = _dense_copy(new, tmp_path / "old.h5")
    a, b = fit_ramps(str(new)), fit_ramps(str(old))
    for name in ("rate", "variance", "dq"):
        assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=name != "dq"), name
    # the saturated pixels are fitted on their 2 good groups: the flags were read
    assert np.all(np.abs(a.rate[[17, 20, 30], [3, 90, 127]] - rate[[17, 20, 30], [3, 90, 127]]) < 3)


def test_file_bytes_depend_on_the_data_only(tmp_path):
    sci, gdq, pixdq, rate = _ramp()
    digests = {hashlib.sha256(_write(tmp_path / f"r{i}.h5", sci, gdq, pixdq, rate).read_bytes()).hexdigest()
               for i in range(2)}
    assert len(digests) == 1


def test_a_ramp_without_flags_stores_no_groupdq_chunk(tmp_path):
    """The common case (nothing saturates): GROUPDQ costs nothing, reads as zeros."""
    sci, gdq, pixdq, rate = _ramp()
    path = _write(tmp_path / "r.h5", sci, np.zeros_like(gdq), pixdq, rate)
    assert _stored(path, "GROUPDQ") == (0, 0)
    assert not read_ramps(path)[1].any()


@pytest.mark.parametrize("hold", ["SCI", "GROUPDQ", "PIXELDQ", "truth/rate"])
def test_file_bytes_do_not_depend_on_when_a_handle_is_released(tmp_path, monkeypatch, hold):
    """A Dask worker's profiler holding a frame (and a dataset handle) past the end of the writer
    must not move compressed chunks: the same ramp gives the same bytes."""
    sci, gdq, pixdq, rate = _ramp()
    create, held = h5py.Group.create_dataset, []

    def create_and_hold(group, name, *args, **kw):
        dset = create(group, name, *args, **kw)
        if name == hold:
            held.append(dset)
        return dset
    plain = _write(tmp_path / "plain.h5", sci, gdq, pixdq, rate).read_bytes()
    monkeypatch.setattr(h5py.Group, "create_dataset", create_and_hold)
    kept = _write(tmp_path / "held.h5", sci, gdq, pixdq, rate).read_bytes()
    monkeypatch.setattr(h5py.Group, "create_dataset", create)
    assert held and plain == kept
