"""JWST level-1b ("uncal") export: stdatamodels reads and validates it, SCI is bit-identical to
the HDF5 ramp, GROUP / INT_TIMES / exposure keywords follow the JWST definitions, writes are
atomic and refused early, truth extensions survive a round trip."""
import datetime as dt
import os
import subprocess
import sys
import tracemalloc
import warnings

import numpy as np
import pytest
from stdatamodels.jwst import datamodels          # a [test] dependency (pyproject): never skipped

from slicersim.errors import RampFileError
from slicersim.io import uncal, uncal_meta
from slicersim.io.atomic import _host_tag
from slicersim.io.rampfile import read_ramps
from slicersim.io.uncal import UncalWriter, read_uncal, read_uncal_truth, truth_extname, write_uncal_from_hdf5
from slicersim.products.ramps import simulate

NMD, NINTS, TFRAME = (4, 2, 1), 2, 2.83
CR_DTYPE = [("ramp", "<u4"), ("frame", "<u4"), ("y", "<u2"), ("x", "<u2"), ("electrons", "<f4")]


def _attrs(**extra):
    n, m, d = NMD
    return {"NINTS": NINTS, "NGROUPS": n, "NFRAMES": m, "GROUPGAP": d, "TFRAME": TFRAME,
            "TGROUP": (m + d) * TFRAME, "READPATT": "MACC(4,2,1)", "SEED": 5, "BUNIT": "ADU", **extra}


#: schema paths of the keywords JWST enumerates with JWST names only (our instrument's names differ)
INSTRUMENT_PATHS = {"meta.instrument.name", "meta.instrument.detector", "meta.exposure.type",
                    "meta.exposure.readpatt"}


def _schema_complaints(path, strict=False):
    """(model, {schema path stdatamodels complains about: its message}); other warnings count too."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = datamodels.Level1bModel(str(path), strict_validation=strict)
        model.validate()
    found = {}
    for w in caught:
        text = str(w.message)
        found[text.split()[2] if text.startswith("While validating ") else f"other: {text}"] = text
    return model, found


def _open_strict(path):
    """Level1bModel with every schema violation an error except the four enumerated instrument
    keywords, which must hold our values (stdatamodels otherwise drops bad values with a warning
    and validate() then passes)."""
    model, found = _schema_complaints(path)
    assert set(found) <= INSTRUMENT_PATHS, found
    return model


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A 64×64 MACC(4,2,1) ramp, 2 integrations, simulated to HDF5 and converted to FITS (with the
    simulator's GROUPDQ: tests/io/test_uncal_groupdq.py checks the flight-like default, none)."""
    d = tmp_path_factory.mktemp("uncal")
    rate = np.random.default_rng(3).uniform(0.0, 50.0, (64, 64))
    h5 = simulate(rate, nmd=NMD, nramps=NINTS, seed=11, out=str(d / "ramp.h5"), tframe=TFRAME,
                  backend="numpy", progress=False)
    fits_path = write_uncal_from_hdf5(h5, d / "ramp_uncal.fits", start_mjd=60000.25, groupdq_flags="truth")
    return h5, fits_path, rate


# --------------------------------------------------------------------------- stdatamodels
def test_level1b_model_opens_and_validates(exported):
    h5, path, _ = exported
    model = _open_strict(path)
    sci, gdq, pdq, attrs = read_ramps(h5)
    assert model.data.dtype == np.uint16 and model.data.shape == (NINTS, NMD[0], 64, 64)
    np.testing.assert_array_equal(model.data, sci)               # same seed, same SCI values
    assert model.meta.exposure.nints == NINTS and model.meta.exposure.ngroups == NMD[0]
    assert model.meta.telescope == "Lazuli"
    assert model.meta.subarray.name == "FULL"
    # GROUPDQ / PIXELDQ are not Level1bModel attributes: RampModel reads them from the same file
    ramp_model = datamodels.RampModel(str(path))
    np.testing.assert_array_equal(ramp_model.groupdq, gdq)
    np.testing.assert_array_equal(ramp_model.pixeldq, pdq)


def test_schema_enumerations_are_enforced_by_the_check(tmp_path):
    """The check used above does catch a non-JWST name (so passing it means something): our
    instrument's four names are its only complaints; JWST stand-in names validate strictly."""
    path = tmp_path / "ours.fits"
    with UncalWriter(path, 1, 2, (4, 4), attrs=_attrs(NINTS=1, NGROUPS=2, GAIN=0.5, READNOISE=10.0)):
        pass
    _, found = _schema_complaints(path)
    assert set(found) == INSTRUMENT_PATHS
    for value in ("LAZULI_IFS", "H4RG-1", "LZ_IFU", "MACC_2_1"):
        assert any(value in text for text in found.values()), (value, found)
    with pytest.raises(Exception, match="LAZULI_IFS"):
        _schema_complaints(path, strict=True)
    stand_in = tmp_path / "jwst.fits"
    with UncalWriter(stand_in, 1, 2, (4, 4), attrs=_attrs(NINTS=1, NGROUPS=2), keywords=uncal_meta.JWST_STAND_IN):
        pass
    model, found = _schema_complaints(stand_in, strict=True)
    assert not found and model.meta.instrument.name == "NIRSPEC" and model.meta.exposure.type == "NRS_IFU"


def test_instrument_keywords_and_pipeline_units(tmp_path):
    """INSTRUME/DETECTOR/EXP_TYPE/READPATT from the one table; gain in e-/DN and CDS read noise in
    DN beside slicersim's own GAIN [ADU/e-] and READNOISE [e-/frame]."""
    path = tmp_path / "k.fits"
    with UncalWriter(path, 1, 2, (4, 4), attrs=_attrs(NINTS=1, NGROUPS=2, GAIN=0.5, READNOISE=10.0)):
        pass
    h = read_uncal(path)[3]
    assert (h["INSTRUME"], h["DETECTOR"], h["EXP_TYPE"]) == (uncal_meta.INSTRUMENT, uncal_meta.DETECTOR,
                                                           uncal_meta.EXP_TYPE)
    assert h["READPATT"] == "MACC_2_1" and h["TELESCOP"] == "Lazuli"
    assert h["GAINEDN"] == pytest.approx(2.0) and h["SLICERSIM GAIN"] == 0.5        # 1/(0.5 ADU/e-)
    assert h["RDNCDSDN"] == pytest.approx(np.sqrt(2) * 10.0 * 0.5)                  # √2·σ·g
    assert h["SLICERSIM READNOISE"] == 10.0
    assert uncal_meta.readout_pattern(8, 0) == "MACC_8_0"


def test_sci_groupdq_pixeldq_identical_to_hdf5(exported):
    h5, path, _ = exported
    sci, gdq, pdq, _ = read_ramps(h5)
    fsci, fgdq, fpdq, header = read_uncal(path)
    assert fsci.dtype == np.uint16 and fgdq.dtype == np.uint8 and fpdq.dtype == np.uint32
    np.testing.assert_array_equal(fsci, sci)
    np.testing.assert_array_equal(fgdq, gdq)
    np.testing.assert_array_equal(fpdq, pdq)
    assert header["SLICERSIM SEED"] == read_ramps(h5)[3]["SEED"]


# --------------------------------------------------------------------------- keywords and tables
def test_exposure_keywords_follow_the_jwst_definitions(exported):
    _, path, _ = exported
    n, m, d = NMD
    h = read_uncal(path)[3]
    assert (h["NINTS"], h["NGROUPS"], h["NFRAMES"], h["GROUPGAP"]) == (NINTS, n, m, d)
    assert h["TFRAME"] == TFRAME and h["TGROUP"] == pytest.approx((m + d) * TFRAME, rel=1e-12)
    # EFFINTTM: first to last group, (n − 1)(m + d) t_f = 3·3·2.83 s (JWST keyword dictionary)
    assert h["EFFINTTM"] == pytest.approx((n - 1) * (m + d) * TFRAME, rel=1e-12)
    assert h["EFFINTTM"] == pytest.approx(25.47, rel=1e-12)
    assert h["TMEASURE"] == pytest.approx(NINTS * 25.47, rel=1e-12)
    # photon collection n m + (n − 1) d = 11 frames per integration; one reset frame each
    assert h["EFFEXPTM"] == pytest.approx(NINTS * 11 * TFRAME, rel=1e-12)
    assert h["DURATION"] == pytest.approx((NINTS * 11 + NINTS) * TFRAME, rel=1e-12)
    assert (h["NRSTSTRT"], h["NRESETS"], h["DRPFRMS1"], h["DRPFRMS3"]) == (1, 1, 0, 0)
    assert h["FRMDIVSR"] == m and h["ZEROFRAM"] is False and h["DATAPROB"] is False
    assert (h["SUBSTRT1"], h["SUBSTRT2"], h["SUBSIZE1"], h["SUBSIZE2"]) == (1, 1, 64, 64)
    assert h["READPATT"] == "MACC_2_1" and h["SLICERSIM READPATT"] == "MACC(4,2,1)"
    assert h["ORIGIN"] == "slicersim" and h["EXPSTART"] == 60000.25
    assert h["EXPEND"] == pytest.approx(60000.25 + h["DURATION"] / 86400, abs=1e-9)
    model = _open_strict(path)
    assert model.meta.exposure.effective_exposure_time == pytest.approx(h["EFFEXPTM"])   # XPOSURE (SCI)
    assert model.meta.exposure.elapsed_exposure_time == pytest.approx(h["DURATION"])      # TELAPSE (SCI)
    assert model.meta.bunit_data == "DN"


def test_group_table_times(exported):
    _, path, _ = exported
    n, m, d = NMD
    group = _open_strict(path).group
    assert len(group) == NINTS * n
    assert list(group["integration_number"]) == [1] * n + [2] * n
    assert list(group["group_number"]) == [1, 2, 3, 4] * NINTS
    ends = np.array([(dt.datetime.fromisoformat(t) - dt.datetime(2000, 1, 1)).total_seconds()
                     for t in group["group_end_time"]])
    # the split day / millisecond / microsecond fields say the same as the ISO string
    split = group["end_day"] * 86400.0 + group["end_milliseconds"] / 1e3 + group["end_submilliseconds"] / 1e6
    np.testing.assert_allclose(split, ends, atol=1e-6, rtol=0)
    steps = np.diff(ends.reshape(NINTS, n), axis=1)
    np.testing.assert_allclose(steps, (m + d) * TFRAME, atol=2e-6)          # TGROUP apart
    # a group ends with its m-th frame: the first one m frames after the start reset frame,
    # the next integration's first one its own reset frame and m frames after the last group
    start = (60000.25 - 51544.0) * 86400.0                                   # EXPSTART since 2000-01-01
    assert ends[0] - start == pytest.approx((1 + m) * TFRAME, abs=2e-6)
    assert ends[n] - ends[n - 1] == pytest.approx((1 + m) * TFRAME, abs=2e-6)
    assert set(group["number_of_columns"]) == {64} and set(group["number_of_rows"]) == {64}


def test_int_times_table(exported):
    _, path, _ = exported
    model = _open_strict(path)
    it, group = model.int_times, model.group
    assert len(it) == NINTS and list(it["integration_number"]) == [1, 2]
    length = (it["int_end_MJD_UTC"] - it["int_start_MJD_UTC"]) * 86400.0
    np.testing.assert_allclose(length, 11 * TFRAME, atol=1e-4)               # 11 frames each
    np.testing.assert_allclose(it["int_mid_MJD_UTC"], 0.5 * (it["int_start_MJD_UTC"] + it["int_end_MJD_UTC"]))
    last = group[group["group_number"] == NMD[0]]
    last_mjd = 51544.0 + (last["end_day"] + last["end_milliseconds"] / 86400e3
                          + last["end_submilliseconds"] / 86400e6)
    np.testing.assert_allclose(it["int_end_MJD_UTC"], last_mjd, atol=1e-4 / 86400)   # ends with its last group
    assert np.all(np.isnan(it["int_mid_BJD_TDB"]))                            # no position known: not faked


# --------------------------------------------------------------------------- truth
def test_truth_extensions_round_trip(tmp_path, exported):
    _, path, rate = exported
    truth = read_uncal_truth(path)
    np.testing.assert_array_equal(truth["truth/rate"], rate.astype(np.float32))
    rng = np.random.default_rng(0)
    cr = np.zeros(7, dtype=CR_DTYPE)
    cr["ramp"], cr["frame"] = rng.integers(0, 2, 7), [0, 1, 2, 3, 4, 2**32 - 1, 9]
    cr["y"], cr["x"], cr["electrons"] = [0, 65535, 3, 4, 5, 6, 7], rng.integers(0, 64, 7), rng.random(7) * 1e4
    inverse = rng.normal(size=(3, 8, 8))
    mask = rng.random((8, 8)) > 0.5
    out = tmp_path / "truth.fits"
    with UncalWriter(out, 1, 4, (8, 8), attrs=_attrs(NINTS=1)) as w:
        w.write_block(0, 0, np.zeros((4, 8, 8), np.uint16))
        w.write_dataset("truth/cosmic_rays", cr)
        w.write_dataset("truth/nonlinearity/inverse_coefficients", inverse)
        w.write_dataset("truth/bad_pixels/mask", mask)
        with pytest.raises(RampFileError, match="already written"):
            w.write_dataset("truth/cosmic_rays", cr)
    back = read_uncal_truth(out)
    assert back["truth/cosmic_rays"].dtype == np.dtype(CR_DTYPE)
    np.testing.assert_array_equal(back["truth/cosmic_rays"], cr)
    np.testing.assert_array_equal(back["truth/nonlinearity/inverse_coefficients"], inverse)
    assert back["truth/bad_pixels/mask"].dtype == bool
    np.testing.assert_array_equal(back["truth/bad_pixels/mask"], mask)
    model = _open_strict(out)                        # tolerated as extra extensions
    assert "TRUTH_CR" in model.extra_fits.instance and "TRUTH_NONLINEARITY_INVERSE_COEFFICIENTS" in model.extra_fits.instance
    assert truth_extname("cosmic_rays") == "TRUTH_CR" and truth_extname("truth/rate") == "TRUTH_RATE"


def _checksum_warnings(path):
    from astropy.io import fits
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with fits.open(path, checksum=True) as hdul:
            cards = [(h.name, "CHECKSUM" in h.header, "DATASUM" in h.header) for h in hdul]
            for h in hdul:
                if h.data is not None:
                    h.data                                   # noqa: B018 (loads and verifies the data)
    return cards, [str(w.message) for w in caught if "checksum" in str(w.message).lower()]


def test_every_hdu_carries_a_valid_checksum(tmp_path, exported):
    """CHECKSUM / DATASUM summed as the blocks are written (odd widths: blocks at 2-byte phases),
    verified by astropy; one flipped byte of SCI is detected."""
    _, path, _ = exported
    cards, bad = _checksum_warnings(path)
    assert bad == [] and all(c and d for _, c, d in cards) and [n for n, *_ in cards][:3] == ["PRIMARY", "SCI",
                                                                                                  "GROUPDQ"]
    odd = tmp_path / "odd.fits"
    rng = np.random.default_rng(2)
    with UncalWriter(odd, 1, 4, (7, 9), attrs=_attrs(NINTS=1)) as w:
        for y0 in (0, 3, 5):                                 # blocks of 3, 2 and 2 rows of 9 columns
            rows = 3 if y0 == 0 else 2
            w.write_block(0, y0, rng.integers(0, 65535, (4, rows, 9), dtype=np.uint16),
                          rng.integers(0, 255, (4, rows, 9), dtype=np.uint8))
        w.write_pixeldq(rng.integers(0, 2**31, (7, 9), dtype=np.uint32))
        w.write_dataset("truth/rate", rng.random((7, 9)).astype(np.float32))
        w.write_dataset("truth/cosmic_rays", np.zeros(3, dtype=CR_DTYPE))
    cards, bad = _checksum_warnings(odd)
    assert bad == [] and all(c and d for _, c, d in cards)
    from astropy.io import fits
    with fits.open(odd) as hdul:
        offset = hdul.fileinfo(1)["datLoc"] + 7
    raw = bytearray(odd.read_bytes())
    raw[offset] ^= 0x01
    odd.write_bytes(bytes(raw))
    assert any("SCI" in m or "Checksum" in m or "checksum" in m for m in _checksum_warnings(odd)[1])
    with pytest.raises(RampFileError, match=r"odd.fits: checksum mismatch"):
        read_uncal(odd)
    fifo = tmp_path / "fifo.fits"
    os.mkfifo(fifo)
    with pytest.raises(RampFileError, match=r"fifo.fits is not a regular file"):
        read_uncal(fifo)


@pytest.mark.parametrize("damage", ["header_byte", "cut_in_a_header"])
def test_a_changed_header_or_a_file_cut_inside_a_header_is_refused(tmp_path, exported, damage):
    """A flipped header byte (only CHECKSUM covers it) and a file cut inside the PIXELDQ header (astropy
    dropped that HDU and the rest with a multi-line warning) were reduced as if whole."""
    from astropy.io import fits

    from slicersim.reduction.checks import check_ramp_file
    from slicersim.reduction.ramp_fit import fit_ramps
    _, path, _ = exported
    raw = bytearray(open(path, "rb").read())
    with fits.open(path) as hdul:
        names = [h.name for h in hdul]
        pixeldq = hdul.fileinfo(names.index("PIXELDQ"))
    bad = tmp_path / "bad.fits"
    if damage == "header_byte":
        raw[pixeldq["hdrLoc"] + 1500] ^= 0x40                     # a blank of the header becomes '`'
        bad.write_bytes(bytes(raw))
        match = r"bad.fits: checksum mismatch in the header of extension PIXELDQ \(CHECKSUM"
    else:
        bad.write_bytes(bytes(raw[:pixeldq["hdrLoc"] + 1440]))
        match = r"bad.fits: truncated or damaged FITS file: it has \d+ bytes but its last complete HDU \(GROUPDQ\)"
    for call in (read_uncal, check_ramp_file, lambda p: fit_ramps(p, progress=False)):
        with pytest.raises(RampFileError, match=match):
            call(bad)


def test_checksum_encoding_is_the_fits_one():
    from astropy.io import fits

    from slicersim.io.fits_checksum import encode_checksum, ones_add, ones_sum
    rng = np.random.default_rng(5)
    for _ in range(20):
        hdu = fits.ImageHDU(rng.integers(0, 65535, (5, 7)).astype(np.int16))
        hdu.add_checksum()
        datasum = int(hdu.header["DATASUM"])
        assert ones_sum(hdu.data.astype(">i2").tobytes()) == datasum
        header = hdu.header.copy()
        header["CHECKSUM"] = "0" * 16
        total = ones_add(ones_sum(header.tostring().encode()), datasum)
        assert encode_checksum(total) == hdu.header["CHECKSUM"]


# --------------------------------------------------------------------------- atomic writes, refusals
def test_exception_leaves_no_file(tmp_path):
    out = tmp_path / "x.fits"
    with pytest.raises(ZeroDivisionError):
        with UncalWriter(out, 1, 2, (4, 4), attrs=_attrs(NINTS=1, NGROUPS=2)) as w:
            w.write_block(0, 0, np.ones((2, 4, 4), np.uint16))
            1 / 0
    assert os.listdir(tmp_path) == []


def test_existing_file_refused_unless_overwrite(tmp_path):
    out = tmp_path / "x.fits"
    out.write_bytes(b"precious")
    with pytest.raises(RampFileError, match="exists"):
        UncalWriter(out, 1, 2, (4, 4), attrs=_attrs(NINTS=1, NGROUPS=2)).check()
    assert out.read_bytes() == b"precious"
    with UncalWriter(out, 1, 2, (4, 4), attrs=_attrs(NINTS=1, NGROUPS=2), overwrite=True) as w:
        w.write_block(0, 0, np.full((2, 4, 4), 7, np.uint16))
    assert read_uncal(out)[0].max() == 7


def test_two_writers_one_wins(tmp_path):
    out = tmp_path / "x.fits"
    first = UncalWriter(out, 1, 2, (4, 4), attrs=_attrs(NINTS=1, NGROUPS=2)).__enter__()
    second = UncalWriter(out, 1, 2, (4, 4), attrs=_attrs(NINTS=1, NGROUPS=2)).__enter__()
    first.write_block(0, 0, np.full((2, 4, 4), 1, np.uint16))
    second.write_block(0, 0, np.full((2, 4, 4), 2, np.uint16))
    first.__exit__(None, None, None)
    with pytest.raises(RampFileError, match="another writer finished first"):
        second.__exit__(None, None, None)
    assert read_uncal(out)[0].max() == 1 and os.listdir(tmp_path) == ["x.fits"]


def test_killed_writer_temporary_is_cleaned(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = tmp_path / f".x.fits.tmp-{dead.pid}-{_host_tag()}00aa"
    stale.write_bytes(b"half")
    with UncalWriter(tmp_path / "y.fits", 1, 2, (4, 4), attrs=_attrs(NINTS=1, NGROUPS=2)):
        pass
    assert sorted(os.listdir(tmp_path)) == ["y.fits"]


def test_disk_space_refused_before_anything(tmp_path, monkeypatch):
    class Usage:
        total, used, free = 10**9, 10**9 - 10**6, 10**6
    monkeypatch.setattr(uncal.shutil, "disk_usage", lambda _: Usage)
    writer = UncalWriter(tmp_path / "big.fits", 2, 16, (2048, 2048), attrs=_attrs(NINTS=2, NGROUPS=16))
    with pytest.raises(RampFileError, match="not enough disk space"):
        writer.check()
    with pytest.raises(RampFileError, match="not enough disk space"):
        writer.__enter__()
    assert os.listdir(tmp_path) == []


def test_bad_input_is_one_clear_error(tmp_path):
    out = tmp_path / "x.fits"
    with pytest.raises(RampFileError, match="TFRAME"):
        UncalWriter(out, 1, 2, (4, 4), attrs={"NFRAMES": 1, "GROUPGAP": 0}).check()
    with pytest.raises(RampFileError, match="NGROUPS"):
        UncalWriter(out, 1, 2, (4, 4), attrs=_attrs(NINTS=1)).check()          # says 4 groups
    with pytest.raises(RampFileError, match="uncompressed"):
        UncalWriter(out, 1, 2, (4, 4), compression="gzip")
    with pytest.raises(RampFileError, match="directory does not exist"):
        UncalWriter(tmp_path / "no" / "x.fits", 1, 2, (4, 4)).check()
    with UncalWriter(out, 1, 2, (4, 4), attrs=_attrs(NINTS=1, NGROUPS=2)) as w:
        with pytest.raises(RampFileError, match="SCI block"):
            w.write_block(0, 0, np.zeros((3, 4, 4), np.uint16))
        with pytest.raises(RampFileError, match="outside"):
            w.write_block(0, 2, np.zeros((2, 4, 4), np.uint16))
        with pytest.raises(RampFileError, match=r"\[0, 65535\]"):
            w.write_block(0, 0, np.full((2, 4, 4), 70000))
        w.write_block(0, 0, np.full((2, 4, 4), 65535))                        # int64 in range: fine
    assert read_uncal(out)[0].min() == 65535


def test_conversion_streams_in_blocks(tmp_path):
    """Converting a 16 MiB SCI with a 1 MiB budget never holds SCI in memory."""
    n, ny, nx = 8, 512, 512
    h5 = tmp_path / "big.h5"
    from slicersim.io.rampfile import RampWriter
    sci = np.arange(n * ny * nx, dtype=np.uint64).astype(np.uint16).reshape(n, ny, nx)
    with RampWriter(h5, 2, n, (ny, nx), attrs=_attrs(NINTS=2, NGROUPS=n, NFRAMES=1, GROUPGAP=0)) as w:
        for ramp in range(2):
            w.write_block(ramp, 0, sci)
    del w
    write_uncal_from_hdf5(h5, tmp_path / "warm.fits")             # imports (astropy) outside the trace
    tracemalloc.start()
    write_uncal_from_hdf5(h5, tmp_path / "big.fits", max_bytes=1 << 20)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    print(f"peak traced memory {peak / 2**20:.2f} MiB for a {2 * 2 * n * ny * nx / 2**20:.0f} MiB SCI")
    assert peak < 2 * 2 * n * ny * nx / 4                                   # < a quarter of SCI
    back = read_uncal(tmp_path / "big.fits")[0]
    np.testing.assert_array_equal(back[1], sci)


def test_simulate_through_the_writer_interface(tmp_path, monkeypatch, exported):
    """UncalWriter is a drop-in for RampWriter in simulate() (what ``--format jwst-uncal`` does):
    the same seed gives the same SCI in both formats, and the root attributes (CONFIG as JSON)
    are kept as SLICERSIM keywords."""
    import json

    import slicersim.products.ramps as ramps
    h5, _, rate = exported
    monkeypatch.setattr(ramps, "RampWriter", UncalWriter)
    config = {"detector": {"ron": 12.0, "note": "σ ≥ 0"}, "list": list(range(40))}
    out = simulate(rate, nmd=NMD, nramps=NINTS, seed=11, out=str(tmp_path / "direct.fits"), tframe=TFRAME,
                   backend="numpy", progress=False, config=config)
    model = _open_strict(out)
    np.testing.assert_array_equal(model.data, read_ramps(h5)[0])
    header = read_uncal(out)[3]
    assert json.loads(header["SLICERSIM CONFIG"]) == config
    assert header["SLICERSIM READPATT"] == "MACC(4,2,1)" and header["SLICERSIM GAIN"] == 1.0
    np.testing.assert_array_equal(read_uncal_truth(out)["truth/rate"], rate.astype(np.float32))


def test_memory_budget_is_the_deprecated_name_of_max_bytes(tmp_path):
    """write_uncal_from_hdf5(memory_budget=) still works, with a DeprecationWarning; the same file as
    max_bytes=; a bad budget or an unknown writer option is a ParameterError naming it."""
    from slicersim.errors import ParameterError
    h5 = simulate(np.full((12, 10), 3.0), (3, 1, 0), seed=1, out=tmp_path / "r.h5", progress=False)
    with pytest.warns(DeprecationWarning, match="memory_budget.*max_bytes"):
        old = write_uncal_from_hdf5(h5, tmp_path / "old.fits", memory_budget=400)
    new = write_uncal_from_hdf5(h5, tmp_path / "new.fits", max_bytes=400)
    assert np.array_equal(read_uncal(old)[0], read_uncal(new)[0])
    with pytest.raises(ParameterError, match="max_bytes"):
        write_uncal_from_hdf5(h5, tmp_path / "bad.fits", max_bytes=0)


def test_conversion_refuses_a_soft_link_it_would_not_follow(tmp_path):
    """h5py's visititems skips soft links: a truth dataset reached through one was left out of the
    FITS file (or written under its target's name) without a word."""
    import h5py
    src = simulate(np.full((8, 8), 5.0), (3, 1, 0), seed=1, out=str(tmp_path / "r.h5"), progress=False)
    with h5py.File(src, "a") as fh:
        fh["extra/cr"] = np.zeros((8, 8), np.float32)
        fh["truth/cosmic_rays"] = h5py.SoftLink("/extra/cr")
    out = tmp_path / "r.fits"
    with pytest.raises(RampFileError, match=r"r\.h5: truth/cosmic_rays is a soft link: a ramp file to convert"):
        write_uncal_from_hdf5(src, out)
    assert not out.exists()
    write_uncal_from_hdf5(simulate(np.full((8, 8), 5.0), (3, 1, 0), seed=1, out=str(tmp_path / "ok.h5"),
                                   progress=False), tmp_path / "ok.fits")          # a file of ours converts
    assert (tmp_path / "ok.fits").exists()


def test_conversion_refuses_a_ramp_file_without_its_completion_marker(tmp_path):
    # every chunk stored (the storage check passes), COMPLETE false: a writer stopped before the marker
    import h5py
    src = simulate(np.full((8, 8), 5.0), (3, 1, 0), seed=1, out=str(tmp_path / "r.h5"), progress=False)
    with h5py.File(src, "a") as fh:
        fh.attrs["COMPLETE"] = False
    out = tmp_path / "r.fits"
    with pytest.raises(RampFileError, match=r"r\.h5: incomplete file \(no completion marker\)"):
        write_uncal_from_hdf5(src, out)
    assert not out.exists()
