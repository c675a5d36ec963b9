"""The per-pixel part of a ramp file's dark (slicersim.reduction.dark): the bad pixels' extra dark as
the rates see it.  The reduction that subtracts it: tests/reduction/test_closed_loop.py
(test_the_files_warm_pixels_are_dark_subtracted_pixel_by_pixel)."""
import h5py
import numpy as np
import pytest

from slicersim.physics.ipc import ipc_kernel
from slicersim.reduction.dark import extra_dark


def test_the_files_map_seen_through_ipc(tmp_path):
    """The recorded map, NaN as 0, coupled to the neighbours by the IPC kernel (charge conserved away from
    the edges); None for a file without a map, for a map of another shape, for a file that is not
    HDF5 and for ramps given in memory."""
    m = np.zeros((6, 8), np.float32)
    m[3, 4], m[0, 0] = 2.0, np.nan
    path = tmp_path / "raw.h5"
    with h5py.File(path, "w") as fh:
        fh["truth/bad_pixels/extra_dark"] = m
    plain = extra_dark(str(path), (6, 8))
    assert plain[3, 4] == 2.0 and plain[0, 0] == 0.0 and plain.sum() == 2.0
    k = ipc_kernel(0.016, 0.002)
    seen = extra_dark(path, (6, 8), k)
    np.testing.assert_allclose(seen[2:5, 3:6], 2.0 * k)
    assert abs(seen.sum() - 2.0) < 1e-12
    assert extra_dark(str(path), (8, 6)) is None
    empty = tmp_path / "empty.h5"
    with h5py.File(empty, "w") as fh:
        fh["SCI"] = np.zeros((1, 2, 6, 8))
    assert extra_dark(str(empty), (6, 8)) is None
    fits = tmp_path / "uncal.fits"
    fits.write_bytes(b"SIMPLE  =                    T" + b" " * 2849)
    assert extra_dark(str(fits), (6, 8)) is None
    assert extra_dark((np.zeros((1, 2, 6, 8)), None, None, {}), (6, 8)) is None


def test_a_damaged_map_is_one_ramp_file_error(tmp_path):
    """A map that is not one (a group, strings, a compound or complex type, bool) or whose values no
    detector has (negative, above 1e6 e-/s) is refused as the file's damage (RampFileError naming the
    dataset): a group or strings were an AttributeError / ValueError traceback, and a negative or
    1e30 e-/s map was subtracted (the spectrum's flux came out −3e30 with no error)."""
    from slicersim.errors import RampFileError
    m = np.zeros((6, 8), np.float32)
    m[3, 4] = 2.0
    cases = {"group": None, "strings": np.full((6, 8), b"x"), "complex": m.astype(np.complex64),
             "bool": m > 0, "compound": np.zeros((6, 8), dtype=[("a", "f4"), ("b", "f4")]),
             "negative": -m, "huge": m * 1e30}
    for name, data in cases.items():
        path = tmp_path / f"{name}.h5"
        with h5py.File(path, "w") as fh:
            if data is None:
                fh.create_group("truth/bad_pixels/extra_dark")
            else:
                fh["truth/bad_pixels/extra_dark"] = data
        with pytest.raises(RampFileError, match="truth/bad_pixels/extra_dark"):
            extra_dark(str(path), (6, 8))
    ok = tmp_path / "int.h5"                                   # integers are rates too
    with h5py.File(ok, "w") as fh:
        fh["truth/bad_pixels/extra_dark"] = m.astype(np.int32)
    assert extra_dark(str(ok), (6, 8)).sum() == 2.0


def test_a_corrupt_map_is_a_checksum_error_not_no_map(tmp_path):
    """A flipped byte of the map (Fletcher-32 checksums, as the simulator writes it) was swallowed with
    the OSError of a file that is not HDF5: no map, the warm pixels left in the rates with no word;
    now "checksum mismatch in dataset truth/bad_pixels/extra_dark"."""
    from slicersim.errors import RampFileError
    path = tmp_path / "raw.h5"
    with h5py.File(path, "w") as fh:
        fh.create_dataset("truth/bad_pixels/extra_dark", data=np.ones((6, 8), np.float32), chunks=(3, 8),
                          fletcher32=True)
    assert extra_dark(str(path), (6, 8)).sum() == 48.0
    with h5py.File(path, "r") as fh:
        offset = fh["truth/bad_pixels/extra_dark"].id.get_chunk_info(0).byte_offset + 3
    with open(path, "r+b") as fh:
        fh.seek(offset)
        byte = fh.read(1)
        fh.seek(offset)
        fh.write(bytes([byte[0] ^ 0x10]))
    with pytest.raises(RampFileError, match="checksum mismatch in dataset truth/bad_pixels/extra_dark"):
        extra_dark(str(path), (6, 8))


@pytest.mark.slow
def test_the_extra_dark_is_seen_through_the_files_ipc_when_the_rates_are_not_deconvolved(tmp_path):
    """dark="auto" with ipc=False (CLI --no-ipc): the rates are not deconvolved, but their warm pixels'
    dark charge went through IPC all the same, so the map subtracted is the one seen through the file's
    kernel, as with the deconvolution.  It was the raw map: warm pixels over-subtracted by ~6 % of
    their extra dark and their neighbours left with theirs (median residuals −0.040 ± 0.006 and
    +0.024 ± 0.004 e-/s on a small-layout ramp)."""
    from conftest import SMALL_NCOL, small_point_source
    from slicersim.physics.ipc import apply_ipc
    from slicersim.products.ramps import simulate
    from slicersim.reduction.ipc_correction import ipc_kernel_of
    from slicersim.reduction.pipeline import reduce_exposure
    mapper, edges, psf, image = small_point_source()
    raw = tmp_path / "raw.h5"
    simulate(image, (4, 2, 0), seed=12, out=str(raw), ron=5.0, dark=0.01, roic_glow=0.0,
             effects="bad_pixels,ipc", progress=False)
    with h5py.File(raw) as fh:
        extra = np.nan_to_num(fh["truth/bad_pixels/extra_dark"][...].astype(float))
        kernel = ipc_kernel_of(dict(fh.attrs))
    assert kernel is not None and (extra > 0.5).sum() >= 5
    kw = dict(mapper=mapper, lbda_edges=edges, ncol=SMALL_NCOL, psf=psf, weights="data")
    for ipc in (None, False):
        r = reduce_exposure(str(raw), ipc=ipc, **kw)
        assert r["dark_kind"] == "file DARK_RATE + bad pixels' extra dark"
        np.testing.assert_allclose(r["dark_rate"], float(r["rates"].attrs["DARK_RATE"]) + apply_ipc(extra, kernel),
                                   rtol=1e-12, atol=1e-12, err_msg=f"ipc={ipc}")


def test_no_finite_bin_is_not_blamed_on_the_warm_pixels_dark():
    """With dark="auto" the dark subtracted is an image whose warm and hot pixels reach 100 e-/s: a
    spectrum without a finite bin was blamed on "the dark rate subtracted (100 e-/s per pixel) ...: check
    --dark" (its maximum) although a typical pixel had 0.01 e-/s; the typical pixel's dark is what
    could exceed the signal everywhere."""
    from types import SimpleNamespace
    from slicersim.errors import ReductionError
    from slicersim.reduction.pipeline import check_spectrum_has_signal
    empty = SimpleNamespace(flux=np.full(4, np.nan))
    dark = np.full((50, 40), 0.01)
    dark[::7, ::5] = 100.0
    with pytest.raises(ReductionError, match=r"\(0\.01 e-/s per pixel\)"):
        check_spectrum_has_signal(empty, "narrow", dark)
    with pytest.raises(ReductionError, match=r"\(1e\+06 e-/s per pixel\)"):
        check_spectrum_has_signal(empty, "narrow", np.full((50, 40), 1e6))


def test_rows_read_only_those_rows_and_couple_within_each_range(tmp_path):
    """A ramp file of some rows (``rows=``): the map of those rows, IPC within each range, 0 elsewhere;
    the rows of a range away from its edges are the whole map's."""
    m = np.zeros((20, 8), np.float32)
    m[4, 3], m[12, 5], m[8, 1] = 2.0, 3.0, 7.0            # row 8 is not read
    path = tmp_path / "raw.h5"
    with h5py.File(path, "w") as fh:
        fh["truth/bad_pixels/extra_dark"] = m
    k = ipc_kernel(0.016, 0.002)
    whole = extra_dark(path, (20, 8), k)
    part = extra_dark(path, (20, 8), k, rows=((0, 7), (10, 16)))
    np.testing.assert_array_equal(part[1:6], whole[1:6])
    np.testing.assert_array_equal(part[11:15], whole[11:15])
    assert (part[7:10] == 0).all() and (part[16:] == 0).all()
    assert abs(part.sum() - 5.0) < 1e-12
