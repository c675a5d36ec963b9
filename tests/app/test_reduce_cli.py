"""`slicersim reduce`: raw ramp file → rates file, and one-line errors that write nothing."""
import json
import os
import re
import stat

import h5py
import numpy as np
import pytest
from conftest import flip_chunk_byte, small_raw_ramps

from slicersim.app.cli import main
from slicersim.errors import ParameterError
from slicersim.products.ramps import simulate


@pytest.fixture(scope="module")
def raw(tmp_path_factory):
    rate = np.full((16, 32), 20.0)
    rate[4:8, 10:20] = 300.0
    path = tmp_path_factory.mktemp("raw") / "raw.h5"
    return simulate(rate, (12, 4, 0), seed=5, progress=False, out=path, ron=5.0), rate


def test_reduce_writes_rates_close_to_the_truth(raw, tmp_path, capsys):
    path, rate = raw
    out = tmp_path / "rates.h5"
    assert main(["reduce", str(path), "--out", str(out), "--with-truth", "--quiet"]) == 0
    assert "rates 16×32" in capsys.readouterr().out
    with h5py.File(out, "r") as fh:
        fitted, var, truth = fh["RATE"][...], fh["VAR"][...], fh["TRUTH_RATE"][...]
    assert fitted.shape[-2:] == rate.shape and np.allclose(truth, rate)
    pulls = (fitted - truth) / np.sqrt(var)
    assert abs(pulls.mean()) < 4 / np.sqrt(pulls.size) + 0.1 and 0.7 < pulls.std() < 1.3


@pytest.mark.parametrize("case", ["missing", "exists", "threshold", "not_a_ramp", "weighting"])
def test_reduce_bad_input_is_one_line_and_writes_nothing(raw, tmp_path, capsys, case):
    path, _ = raw
    out = tmp_path / "rates.h5"
    argv = ["reduce", str(path), "--out", str(out), "--quiet"]
    if case == "missing":
        argv[1] = str(tmp_path / "nope.h5")
    elif case == "exists":
        out.write_bytes(b"keep me")
    elif case == "threshold":
        argv += ["--jump-threshold", "-3"]
    elif case == "not_a_ramp":
        bad = tmp_path / "bad.h5"
        with h5py.File(bad, "w") as fh:
            fh["x"] = np.zeros(3)
        argv[1] = str(bad)
    if case == "weighting":
        with pytest.raises(SystemExit):
            main(argv + ["--weighting", "best"])
        return
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("slicersim: error:"), err
    if case == "exists":
        assert out.read_bytes() == b"keep me"
    else:
        assert not out.exists()


# --------------------------------------------------------------------------- --spectra
EDGES = "9050,9950,75"                      # 12 bins on the small test layout
NCOL = 24


@pytest.fixture(scope="module")
def small_raw(tmp_path_factory):
    """Raw ramps of :func:`conftest.small_point_source`."""
    return small_raw_ramps(tmp_path_factory.mktemp("small") / "raw.h5", (8, 4, 0))


@pytest.fixture
def small_layout(small_raw, monkeypatch):
    """The CLI's default layout is the small test one (the full detector's tables take minutes)."""
    from slicersim.reduction import rectify
    monkeypatch.setattr(rectify, "_default_mapper", lambda: small_raw[1])
    return small_raw


def _one_line_error(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("slicersim: error:"), err
    return err[0]


@pytest.mark.slow
def test_reduce_spectra_writes_rates_cubes_and_spectra(small_layout, tmp_path, capsys):
    path, _, _ = small_layout
    out = tmp_path / "red.h5"
    argv = ["reduce", str(path), "--out", str(out), "--spectra", "--lbda-edges", EDGES, "--ncol", str(NCOL),
            "--with-truth", "--quiet"]
    assert main(argv) == 0
    line = capsys.readouterr().out
    assert "narrow cube 12×58×24, spectrum (gls)" in line
    with h5py.File(out, "r") as fh:
        assert {"rates", "cubes", "spectra"} <= set(fh) and list(fh["cubes"]) == ["narrow"]
        assert fh["rates/TRUTH_RATE"].shape == fh["rates/RATE"].shape == (660, 600)
        flux, var = fh["spectra/narrow/FLUX"][...], fh["spectra/narrow/VAR"][...]
    assert np.all(np.abs(flux - 400.0) < 5 * np.sqrt(var)), (flux - 400.0) / np.sqrt(var)
    assert main(argv) == 2 and "exists" in _one_line_error(capsys)        # --overwrite needed
    # rates only: unchanged behaviour, no cube
    assert main(["reduce", str(path), "--out", str(tmp_path / "rates.h5"), "--quiet"]) == 0
    with h5py.File(tmp_path / "rates.h5", "r") as fh:
        assert "RATE" in fh and "cubes" not in fh


def test_reduce_spectra_options_from_files(small_layout, tmp_path, capsys):
    """λ edges from a text file, a given PSF (.npy), position, aperture, drizzle + optimal,
    no background, both fields (--no-propagate, which drizzle has no use for, refused)."""
    path, _, psf = small_layout
    edges = tmp_path / "edges.txt"
    edges.write_text("# λ edges [Å]\n" + "\n".join(f"{v:.1f}" for v in np.arange(9050.0, 9951.0, 75.0)))
    np.save(tmp_path / "psf.npy", psf)
    out = tmp_path / "red.h5"
    assert main(["reduce", str(path), "--out", str(out), "--spectra", "--field", "both", "--lbda-edges", str(edges),
                 "--ncol", str(NCOL), "--rectify", "drizzle", "--extraction", "optimal", "--psf",
                 str(tmp_path / "psf.npy"), "--position", "0.7,-1.4", "--aperture", "2.5", "--no-background",
                 "--quiet"]) == 0
    # --no-propagate concerns lsq cubes only: with drizzle it would do nothing, so it is refused
    assert main(["reduce", str(path), "--out", str(tmp_path / "np.h5"), "--spectra", "--rectify", "drizzle",
                 "--no-propagate", "--quiet"]) == 2
    assert "propagate applies" in capsys.readouterr().err and not (tmp_path / "np.h5").exists()
    with h5py.File(out, "r") as fh:
        assert sorted(fh["cubes"]) == ["narrow", "wide"] and fh["cubes/narrow/FLUX"].attrs["METHOD"] == "drizzle"
        info = json.loads(fh.attrs["SPECTRUM_NARROW"])
        flux = fh["spectra/narrow/FLUX"][...]
    assert info["method"] == "optimal" and info["aperture_sigma"] == 2.5 and info["position"] == [0.7, -1.4]
    assert np.all(flux > 0)


@pytest.mark.parametrize("extra, message", [
    (["--field", "wide"], "--field applies only with --spectra"),
    (["--spectra", "--lbda-edges", "9000,9000,10"], "START < STOP"),
    (["--spectra", "--lbda-edges", "9000,9950"], "START,STOP,STEP"),
    (["--spectra", "--lbda-edges", "9050,9950,7"], "multiple of STEP"),
    (["--spectra", "--lbda-edges", "0,1e12,1e-3"], "bins (at most"),
    (["--spectra", "--lbda-edges", "5000,6000,50"], "leaves the traces"),
    (["--spectra", "--ncol", "0"], "--ncol must be an integer in [1, 1024]"),
    (["--spectra", "--ncol", "100000"], "--ncol must be an integer in [1, 1024]"),
    (["--spectra", "--aperture", "-1"], "aperture"),
    (["--spectra", "--aperture", "nan"], "aperture"),
    (["--spectra", "--aperture", "7"], "--aperture [PSF σ] must be in (0, 6)"),
    (["--spectra", "--position", "1"], "--position must be X,Y"),
    (["--spectra", "--position", "nan,1"], "finite"),
    (["--spectra", "--psf", "nope.npy"], "--psf must be 'fit' or an existing .npy"),
    (["--spectra", "--psf", "BADPSF"], "psf has shape (2, 3, 4)"),
    (["--spectra", "--extraction", "gls", "--rectify", "drizzle"], "needs an lsq cube"),
    (["--workers", "2"], "--workers applies only to a campaign dataset"),
    (["--retry-failed"], "--retry-failed applies only to a campaign dataset"),
    (["--gain", "0"], "--gain [DN/e-] must be > 0"),
    (["--read-noise", "-1"], "--ron (read noise per frame) [electron] must be in [0, 10000], got -1"),
    (["--ron", "nan"], "--ron (read noise per frame) [electron] must be finite and in [0, 10000], got nan"),
    (["--jump-threshold", "-1"], "--jump-threshold [σ] (0: no jump detection) must be ≥ 0"),
    (["--show", "-1"], "--show must be an integer ≥ 0"),
    (["--out-is-dir"], "is a directory"),
    (["--spectra", "--position", "1e300,0"], "lies outside the field"),
    (["--spectra", "--position", "0,29.5"], "|y| ≤ 29"),
    (["--dark", "none"], "--dark applies only with --spectra"),
    (["--weights", "data"], "--weights applies only with --spectra"),
    (["--spectra", "--dark", "-1"], "--dark (dark rates) must be finite, ≥ 0 and ≤ 1e+06 e-/s, got -1"),
    (["--spectra", "--dark", "nope.npy"], "--dark must be 'auto', 'none', a rate"),
    (["--spectra", "--dark", "BADPSF"], "--dark: a dark image must have the detector's shape"),
])
def test_reduce_spectra_bad_options_are_one_line_and_write_nothing(small_layout, tmp_path, capsys, extra, message):
    path, _, _ = small_layout
    out = tmp_path / "red.h5"
    if "BADPSF" in extra:
        np.save(tmp_path / "bad.npy", np.ones((2, 3, 4)))
        extra = [str(tmp_path / "bad.npy") if v == "BADPSF" else v for v in extra]
    if extra == ["--out-is-dir"]:
        out.mkdir()
        extra = []
    assert main(["reduce", str(path), "--out", str(out), "--quiet", "--ncol", "24", *extra]
                if "--spectra" in extra and "--ncol" not in extra else
                ["reduce", str(path), "--out", str(out), "--quiet", *extra]) == 2
    assert message in _one_line_error(capsys)
    assert not out.exists() or out.is_dir()


def test_spectra_of_a_detector_that_is_not_the_mappers_is_refused_before_the_fit(raw, tmp_path, capsys):
    path, _ = raw                                            # 16 × 32 pixels; the layout is 4096 × 4096
    assert main(["reduce", str(path), "--out", str(tmp_path / "r.h5"), "--spectra", "--quiet"]) == 2
    assert "cubes and spectra need the full detector" in _one_line_error(capsys)


def test_bad_extraction_choice_is_a_usage_error(raw, tmp_path, capsys):
    path, _ = raw
    with pytest.raises(SystemExit) as exc:
        main(["reduce", str(path), "--out", str(tmp_path / "r.h5"), "--spectra", "--extraction", "psf"])
    assert exc.value.code == 2 and "invalid choice" in _one_line_error(capsys)


# --------------------------------------------------------------------------- bad input files
def _h5_copy(src, dst, edit):
    import shutil
    shutil.copy(src, dst)
    with h5py.File(dst, "r+") as fh:
        edit(fh)
    return dst


def test_files_of_other_layouts_and_inconsistent_keywords_are_named(raw, tmp_path, capsys):
    from astropy.io import fits
    path, rate = raw
    rates = tmp_path / "rates.h5"
    assert main(["reduce", str(path), "--out", str(rates), "--quiet"]) == 0
    reduced = tmp_path / "reduced.h5"
    with h5py.File(reduced, "w") as fh:
        fh["rates/RATE"], fh["spectra/narrow/FLUX"] = np.zeros((2, 2)), np.zeros(3)
    spectrum = tmp_path / "spectrum.h5"
    with h5py.File(spectrum, "w") as fh:
        fh["lbda"] = np.zeros(3)
        fh.attrs["product"] = "spectrum"
    notruth = _h5_copy(path, tmp_path / "notruth.h5", lambda fh: fh.__delitem__("truth/rate"))
    ngroups = _h5_copy(path, tmp_path / "ngroups.h5", lambda fh: fh.attrs.__setitem__("NGROUPS", 13))
    tgroup = _h5_copy(path, tmp_path / "tgroup.h5", lambda fh: fh.attrs.__setitem__("TGROUP", 9.0))
    effinttm = _h5_copy(path, tmp_path / "effinttm.h5", lambda fh: fh.attrs.__setitem__("EFFINTTM", 1.0))

    def float_sci(fh):
        sci = fh["SCI"][...]
        del fh["SCI"]
        fh["SCI"] = sci.astype(np.float64)
    floats = _h5_copy(path, tmp_path / "floats.h5", float_sci)
    uncal = simulate(rate, (6, 2, 1), seed=1, progress=False, out=tmp_path / "uncal.fits", ron=5.0)
    fits_bad = {}
    for name, key, val in (("frmdivsr", "FRMDIVSR", 3), ("effexptm", "EFFEXPTM", 1.0),
                           ("copy", "HIERARCH SLICERSIM NFRAMES", 4)):
        bad = tmp_path / f"{name}.fits"
        with fits.open(uncal) as hdul:
            hdul[0].header[key] = val
            hdul.writeto(bad, checksum=True)          # keywords changed by a tool that keeps CHECKSUM right
        fits_bad[name] = bad
    cases = [(rates, [], "is a rates file (from `slicersim reduce`), not a raw ramp file"),
             (reduced, [], "is a reduced exposure"),
             (spectrum, [], "is a campaign spectrum product"),
             (notruth, ["--with-truth"], "the truth is asked for (--with-truth) but the file has no truth/rate"),
             (ngroups, [], "inconsistent readout keywords: NGROUPS = 13 but SCI has 12"),
             (tgroup, [], "inconsistent readout keywords: TGROUP = 9.0 s"),
             (effinttm, [], "inconsistent readout keywords: EFFINTTM = 1.0 but (NGROUPS − 1)·TGROUP = 124.52"),
             (floats, [], "SCI has type float64"),
             (fits_bad["frmdivsr"], [], "FRMDIVSR = 3 but NFRAMES = 2"),
             (fits_bad["effexptm"], [], "EFFEXPTM = 1.0 but TFRAME·(NGROUPS·NFRAMES"),
             (fits_bad["copy"], [], "NFRAMES = 2 but SLICERSIM NFRAMES = 4"),
             (tmp_path, [], "not a slicersim campaign dataset")]
    for source, extra, message in cases:
        out = tmp_path / "out.h5" if source != tmp_path else tmp_path / "outdir"
        assert main(["reduce", str(source), "--out", str(out), "--quiet", *extra]) == 2, source
        assert message in _one_line_error(capsys), source
        assert not out.exists()
    assert main(["reduce", str(uncal), "--out", str(tmp_path / "ok.h5"), "--quiet"]) == 0   # the FITS itself is fine


@pytest.mark.slow
def test_compressed_ramps_need_their_filter(tmp_path, monkeypatch):
    """lz4 ramps (the campaigns' compression) reduce in a fresh process (the filter is registered);
    without the filter the error names it."""
    import subprocess
    import sys
    from pathlib import Path

    from slicersim.errors import RampFileError
    from slicersim.reduction.checks import check_ramp_file
    path = simulate(np.full((16, 32), 5.0), (4, 2, 0), seed=1, progress=False, out=tmp_path / "lz4.h5",
                    compression="lz4")
    proc = subprocess.run([str(Path(sys.executable).parent / "slicersim"), "reduce", str(path), "--out",
                           str(tmp_path / "r.h5"), "--quiet"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    monkeypatch.setattr(h5py.h5z, "filter_avail", lambda code: False)
    with pytest.raises(RampFileError, match="cannot decode .install the 'hdf5plugin' package"):
        check_ramp_file(path)


def test_out_that_is_the_raw_file_is_refused_even_with_overwrite(raw, tmp_path, capsys):
    """Adversarial finding: `--out RAW --overwrite` replaced the raw ramps by the rates."""
    import shutil

    from slicersim.reduction.campaign import reduce_file
    path = str(shutil.copy(raw[0], tmp_path / "raw.h5"))
    before = (tmp_path / "raw.h5").read_bytes()
    for out in (path, str(tmp_path / "." / "raw.h5")):
        assert main(["reduce", str(path), "--out", out, "--overwrite", "--quiet"]) == 2
        assert "the ramps would be lost" in _one_line_error(capsys)
    with pytest.raises(ParameterError, match="the ramps would be lost"):
        reduce_file(path, path, overwrite=True)
    assert (tmp_path / "raw.h5").read_bytes() == before


@pytest.mark.parametrize("call, message", [
    (lambda f: f(None), "raw must be a path"),
    (lambda f: f(3.5, "x.h5"), "raw must be a path"),
    (lambda f: f("raw.h5", out=["x.h5"]), "out must be a path"),
    (lambda f: f("raw.h5", fit_options=[("gain", 1)]), "fit_options must be a dict"),
    (lambda f: f("raw.h5", fit_options={"gain": True}), "gain"),
    (lambda f: f("raw.h5", fit_options={"jump_threshold": float("inf")}), "jump_threshold"),
    (lambda f: f("raw.h5", fit_options={"with_truth": "yes"}), "with_truth must be True or False"),
    (lambda f: f("raw.h5", spectra=True, ncol=2.5), "ncol"),
    (lambda f: f("raw.h5", spectra=True, ncol=True), "ncol"),
    (lambda f: f("raw.h5", spectra=True, field="all"), "field"),
    (lambda f: f("raw.h5", spectra=True, lbda_edges="9000-9500"), "lbda_edges must be numbers"),
    (lambda f: f("raw.h5", spectra=True, lbda_edges=[[9000, 9500]]), "1-D"),
    (lambda f: f("raw.h5", spectra=True, psf="gauss"), "psf must be 'fit'"),
    (lambda f: f("raw.h5", spectra=True, psf=np.full((12, 58, 58), np.nan)), "finite"),
    (lambda f: f("raw.h5", spectra=True, background="no"), "background must be True or False"),
    (lambda f: f("raw.h5", spectra=True, position=(1, 2, 3)), "position must be"),
    (lambda f: f("raw.h5", spectra=True, wavelength=3), "unknown reduction option 'wavelength'"),
])
def test_reduce_file_wrong_types(call, message):
    from slicersim.reduction.campaign import reduce_file
    with pytest.raises((ParameterError, TypeError), match=message):
        call(reduce_file)


@pytest.mark.slow
def test_reduce_spectra_defaults_on_a_full_detector_ramp(tmp_path, capsys):
    """`slicersim ramp --redshift 0.5` then `slicersim reduce RAW --out RED --spectra` with every default:
    the forward extraction in the recorded field, the band flux within 4 σ of the input, units on every
    dataset, valid JSON; `--field both` extracts the field with the source and warns (one line) for the
    other (review: it failed on every single-source ramp); `--extraction gls` is refused with the reason.
    The cube is made only when asked (`--cubes`; issue 30: it was ~30 % of the CPU time and the forward
    spectrum does not use it): the spectrum is the same bit for bit with and without it."""
    from slicersim.targets import LazuliSupernova
    raw, red, both = tmp_path / "raw.h5", tmp_path / "red.h5", tmp_path / "both.h5"
    assert main(["ramp", "--redshift", "0.5", "--seed", "3", "--out", str(raw)]) == 0
    assert main(["reduce", str(raw), "--out", str(red), "--spectra", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "narrow spectrum (forward)" in out and "cube" not in out
    with_cube = tmp_path / "cube.h5"
    assert main(["reduce", str(raw), "--out", str(with_cube), "--spectra", "--cubes", "--quiet"]) == 0
    assert "narrow cube 255×58×58, spectrum (forward)" in capsys.readouterr().out
    with h5py.File(red, "r") as a, h5py.File(with_cube, "r") as b:
        assert "cubes" not in a and "RECTIFY_VAR" not in a["rates"] and a.attrs["PRODUCTS"] == "rates,spectra"
        assert b["cubes/narrow/FLUX"].shape == (255, 58, 58) and b.attrs["RECTIFY_METHOD"] == "lsq"
        assert np.array_equal(a["spectra/narrow/FLUX"][...], b["spectra/narrow/FLUX"][...], equal_nan=True)
    sn = LazuliSupernova(0.5)
    _, rate, _ = sn.get_spectrum(unit="rate")
    ne = sn.simulation.spectrograph.lbda_edges
    with h5py.File(red, "r") as fh:
        sp = fh["spectra/narrow"]
        edges, flux, cov = sp["LBDA_EDGES"][...], sp["FLUX"][...], sp["COVARIANCE"][...]
        info = json.loads(fh.attrs["SPECTRUM_NARROW"])                 # strict JSON: no NaN
        units = {}
        fh.visititems(lambda n, o: units.setdefault(n, o.attrs.get("BUNIT")) if isinstance(o, h5py.Dataset)
                      else None)
        assert json.loads(fh.attrs["RAW_CONFIG"])["field"] == "narrow"
    assert info["method"] == "forward" and info["converged"] and info["warnings"] == []
    assert all(u for u in units.values()), [n for n, u in units.items() if not u]
    centre = 0.5 * (edges[1:] + edges[:-1]) / 1.5
    band = (centre >= 4000) & (centre <= 6800)
    from slicersim.reduction.forward_extraction import aggregate_bins
    truth = (aggregate_bins(ne, edges) @ (rate / sn.simulation.detector.gain))[band].sum()
    ratio, sigma = flux[band].sum() / truth, np.sqrt(cov[np.ix_(band, band)].sum()) / truth
    print(f"band flux / input {ratio:.4f} ± {sigma:.4f}")
    assert abs(ratio - 1) < 4 * sigma
    with pytest.warns(RuntimeWarning, match="no point source in the wide field"):
        assert main(["reduce", str(raw), "--out", str(both), "--spectra", "--field", "both", "--quiet"]) == 0
    assert "narrow spectrum (forward), wide no spectrum (no source)" in capsys.readouterr().out
    with h5py.File(both, "r") as fh:
        assert "spectra/narrow" in fh and "spectra/wide" not in fh
    assert main(["reduce", str(raw), "--out", str(tmp_path / "gls.h5"), "--spectra", "--extraction", "gls"]) == 2
    assert "biased by the coarse cells" in capsys.readouterr().err


def test_cli_warnings_are_one_line():
    """Warnings from a command print as `slicersim: warning: ...` (review: the Python format showed a
    source file and a code line); pytest's own warning capture is left alone."""
    import warnings

    from slicersim.app import cli
    text = cli._format_warning(RuntimeWarning("no instrument configuration:\n the spectrum ..."), RuntimeWarning,
                               "campaign.py", 122)
    assert text == "slicersim: warning: no instrument configuration: the spectrum ...\n"
    assert cli.main(["info"]) == 0 and warnings.formatwarning is not cli._format_warning     # restored


@pytest.mark.parametrize("text, expected", [
    ("ncol must be an integer in [1, 1024], got 0", "--ncol must be an integer in [1, 1024], got 0"),
    ("unknown rectify_method 'lsqr' (did you mean 'lsq'?)", "unknown --rectify 'lsqr' (did you mean 'lsq'?)"),
    ("aperture [PSF σ] must be in (0, 6), got 7.0", "--aperture [PSF σ] must be in (0, 6), got 7.0"),
    ("propagate applies to 'optimal' or 'aperture' extraction", "--no-propagate applies to 'optimal' or 'aperture' "
     "extraction"),
    ("no point source in the wide field; give position= (CLI --position) to extract there anyway, or field= "
     "(CLI --field) for the other field", "no point source in the wide field; give --position to extract there "
     "anyway, or --field for the other field"),
    ("the file records none (its CONFIG keyword); give config= (CLI: --config cbe|eol|PATH)",
     "the file records none (its CONFIG keyword); give --config"),
    ("a partial band (allow_partial=True in Python, --allow-partial on the command line)",
     "a partial band (--allow-partial)"),
    ("partial: pass allow_partial=True", "partial: pass --allow-partial"),
    ("unknown fit_ramps option 'jump'", "unknown fit_ramps option 'jump'"),      # no keyword named: unchanged
    ("dark rates must be finite, ≥ 0 and ≤ 1e+06 e-/s", "dark rates must be finite, ≥ 0 and ≤ 1e+06 e-/s"),
])
def test_errors_name_the_command_line_flags(text, expected):
    """Issue 24: an error of the reduction reaching the CLI names the flag to change (--allow-partial, not
    allow_partial=True; --rectify, not rectify_method)."""
    from slicersim.app.reduce_cli import cli_message
    assert cli_message(text) == expected


def test_a_reduction_error_reaching_the_cli_is_reworded_with_its_class(tmp_path):
    """The flag wording keeps the error's class (ReductionError stays a ReductionError, a SlicersimError)."""
    from slicersim.app.reduce_cli import _FlagNames
    from slicersim.errors import ReductionError
    with pytest.raises(ReductionError, match=r"^no source; give --position$"):
        with _FlagNames():
            raise ReductionError("no source; give position= (CLI --position)")
    with pytest.raises(KeyError):                                     # not ours: untouched
        with _FlagNames():
            raise KeyError("position=")


def test_out_fifo_link_and_directory_are_refused_and_untouched(raw, tmp_path, capsys):
    """Adversarial findings: `--overwrite` replaced a FIFO (and, as root, /dev/null); `--out newdir/` wrote a
    file named newdir.  A link to a FIFO is refused too; nothing is written."""
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    link = tmp_path / "link.h5"
    link.symlink_to(fifo)
    for out, message in ((fifo, "FIFO"), (link, "FIFO .* symbolic link"), (f"{tmp_path / 'newdir'}/", "names a directory"),
                         (tmp_path, "is a directory")):
        assert main(["reduce", str(raw[0]), "--out", str(out), "--overwrite", "--quiet"]) == 2
        line = _one_line_error(capsys)
        assert "--out" in line and re.search(message, line), line
    assert sorted(os.listdir(tmp_path)) == ["link.h5", "pipe"]
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode) and os.path.islink(link)


# --------------------------------------------------------------------------- inputs we did not write
def test_external_truth_is_refused_and_its_bytes_never_copied(raw, tmp_path, capsys):
    path, rate = raw
    secret = tmp_path / "secret.bin"
    secret.write_bytes(np.full(rate.shape, 12345.0, np.float32).tobytes())

    def external(fh):
        del fh["truth/rate"]
        fh.create_dataset("truth/rate", rate.shape, dtype="f4", external=[(str(secret), 0, rate.size * 4)])
    bad = _h5_copy(path, tmp_path / "external.h5", external)
    out = tmp_path / "out.h5"
    assert main(["reduce", str(bad), "--out", str(out), "--with-truth", "--quiet"]) == 2
    assert "dataset truth/rate has external storage" in _one_line_error(capsys) and not out.exists()
    link = _h5_copy(path, tmp_path / "link.h5", lambda fh: (fh.__delitem__("truth/rate"),
                                                            fh.__setitem__("truth/rate", h5py.ExternalLink(str(bad), "SCI"))))
    assert main(["reduce", str(link), "--out", str(out), "--with-truth", "--quiet"]) == 2
    assert "truth/rate is an external link" in _one_line_error(capsys) and not out.exists()


@pytest.mark.parametrize("key, value, message", [
    ("GAIN", 1e-300, "keyword GAIN = 1e-300 is outside the physical range"),
    ("READNOISE", 1e300, "keyword READNOISE = 1e+300 is outside the physical range"),
    ("DARK", float("nan"), "keyword DARK = nan is not finite"),
    ("EFFECTS", "{not json", "keyword EFFECTS = '{not json' is not the JSON object"),
    ("NFRAMES", 10**9, "NFRAMES"),
])
def test_raw_keywords_out_of_their_physical_range_are_named(raw, tmp_path, capsys, key, value, message):
    path, _ = raw
    bad = _h5_copy(path, tmp_path / "bad.h5", lambda fh: fh.attrs.__setitem__(key, value))
    out = tmp_path / "out.h5"
    assert main(["reduce", str(bad), "--out", str(out), "--quiet"]) == 2
    assert message in _one_line_error(capsys) and not out.exists()


def test_nan_linearity_truth_is_refused(raw, tmp_path, capsys):
    path, rate = raw
    coeffs = np.zeros((3,) + rate.shape)
    coeffs[1] = 1.0
    coeffs[1, 5, 5] = np.nan
    bad = _h5_copy(path, tmp_path / "bad.h5",
                   lambda fh: fh.create_dataset("truth/nonlinearity/inverse_coefficients", data=coeffs))
    out = tmp_path / "out.h5"
    assert main(["reduce", str(bad), "--out", str(out), "--quiet"]) == 2
    assert "truth/nonlinearity/inverse_coefficients has non-finite values" in _one_line_error(capsys)
    assert not out.exists()


def test_ramp_inputs_that_are_not_regular_files_are_refused(tmp_path, capsys):
    import os
    import threading
    fifo = tmp_path / "fifo.h5"
    os.mkfifo(fifo)
    codes = []
    thread = threading.Thread(target=lambda: codes.append(main(["reduce", str(fifo), "--out",
                                                                str(tmp_path / "o.h5"), "--quiet"])), daemon=True)
    thread.start()
    thread.join(60)
    assert not thread.is_alive() and codes == [2]
    assert "fifo.h5" in _one_line_error(capsys)
    assert main(["reduce", "/dev/zero", "--out", str(tmp_path / "o.h5"), "--quiet"]) == 2
    assert "/dev/zero" in _one_line_error(capsys)
    from slicersim.errors import RampFileError
    from slicersim.reduction.checks import check_ramp_file
    with pytest.raises(RampFileError, match="fifo.h5 is not a regular file"):
        check_ramp_file(fifo)


def test_a_flipped_data_byte_fails_with_a_checksum_error(raw, tmp_path, capsys):
    """Acceptance (issue 26): one flipped byte of SCI makes reduce fail (exit 2) naming the checksum."""
    import shutil
    path, _ = raw
    bad = tmp_path / "flipped.h5"
    shutil.copy(path, bad)
    flip_chunk_byte(bad, "SCI", offset=3, mask=0x10)
    out = tmp_path / "out.h5"
    assert main(["reduce", str(bad), "--out", str(out), "--quiet"]) == 2
    error = _one_line_error(capsys)
    assert "checksum mismatch in dataset SCI" in error and "flipped.h5" in error and not out.exists()


def test_a_flipped_gain_bit_fails_with_the_same_checksum_line(raw, tmp_path, capsys):
    """Issue 33: one flipped bit in GAIN gave exit 0 and every rate × 0.667; it is now exit 2, one line, as a
    flipped data byte."""
    import shutil
    path, _ = raw
    bad = tmp_path / "gain.h5"
    shutil.copy(path, bad)
    import h5py
    with h5py.File(path, "r") as fh:
        gain = float(fh.attrs["GAIN"])
    data = bytearray(bad.read_bytes())
    where = data.find(np.float64(gain).tobytes())
    data[where + 6] ^= 0x01
    bad.write_bytes(bytes(data))
    out = tmp_path / "out.h5"
    assert main(["reduce", str(bad), "--out", str(out), "--quiet"]) == 2
    error = _one_line_error(capsys)
    assert "checksum mismatch in the metadata" in error and "gain.h5" in error and not out.exists()


def test_weights_with_drizzle_are_refused(tmp_path, capsys):
    """--weights is an option of the LSQ rectification: with --rectify drizzle it did nothing, silently
    (the CLI refuses options that do not apply)."""
    from slicersim.app.cli import main
    from slicersim.reduction.checks import check_spectra_options
    with pytest.raises(ParameterError, match="drizzle"):
        check_spectra_options(weights="data", rectify_method="drizzle")
    assert check_spectra_options(weights="data", rectify_method="lsq")["weights"] == "data"
    raw = tmp_path / "raw.h5"
    raw.write_bytes(b"")                                   # refused before any data are read
    assert main(["reduce", str(raw), "--out", str(tmp_path / "o.h5"), "--quiet", "--spectra", "--rectify", "drizzle",
                 "--weights", "model"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "drizzle" in err[0] and err[0].startswith("slicersim: error:")


def test_absurd_read_noise_is_refused_naming_the_flag(raw, tmp_path, capsys):
    """`reduce --ron 1e300` overflowed the variance (exit 3, internal error): the flag's physical
    range is the raw keyword's, [0, 1e4] electron per frame."""
    path, _ = raw
    for value in ("1e300", "-1", "nan"):
        assert main(["reduce", str(path), "--out", str(tmp_path / "r.h5"), "--ron", value, "--quiet"]) == 2
        assert "--ron" in _one_line_error(capsys)
    assert not (tmp_path / "r.h5").exists()


def _flip_fits_byte(src, dst, extname, at=1000):
    import shutil

    from astropy.io import fits
    shutil.copy(src, dst)
    with fits.open(dst) as hdul:
        offset = hdul.fileinfo(hdul.index_of(extname))["datLoc"] + at
    with open(dst, "r+b") as fh:
        fh.seek(offset)
        byte = fh.read(1)
        fh.seek(offset)
        fh.write(bytes([byte[0] ^ 0x10]))
    return dst


def test_a_flipped_byte_of_a_level1b_ramp_is_a_checksum_error(tmp_path, capsys):
    """The FITS writer streams DATASUM/CHECKSUM; reduce verifies the DATASUM of every extension (SCI and
    the truth): a flipped byte was reduced without complaint (one more jump found)."""
    good = simulate(np.full((16, 32), 20.0), (6, 2, 0), seed=3, progress=False, out=tmp_path / "u.fits", truth=True)
    assert main(["reduce", str(good), "--out", str(tmp_path / "ok.h5"), "--quiet", "--with-truth"]) == 0
    capsys.readouterr()
    for ext in ("SCI", "TRUTH_RATE"):
        bad = _flip_fits_byte(good, tmp_path / f"flip_{ext}.fits", ext)
        assert main(["reduce", str(bad), "--out", str(tmp_path / "r.h5"), "--quiet", "--with-truth"]) == 2
        line = _one_line_error(capsys)
        assert f"checksum mismatch in extension {ext}" in line and f"flip_{ext}.fits" in line, line
    assert not (tmp_path / "r.h5").exists()


def test_a_flipped_byte_of_the_truth_names_the_checksum(raw, tmp_path, capsys):
    """A flipped byte of truth/rate said only "filter returned failure during read" (no file, no dataset)."""
    path, _ = raw
    bad = tmp_path / "flip_truth.h5"
    import shutil
    shutil.copy(path, bad)
    with h5py.File(bad, "r") as fh:
        dset = fh["truth/rate"]
        offset = (dset.id.get_chunk_info(0).byte_offset if dset.chunks else dset.id.get_offset()) + 3
    with open(bad, "r+b") as fh:
        fh.seek(offset)
        byte = fh.read(1)
        fh.seek(offset)
        fh.write(bytes([byte[0] ^ 0x10]))
    assert main(["reduce", str(bad), "--out", str(tmp_path / "r.h5"), "--quiet", "--with-truth"]) == 2
    line = _one_line_error(capsys)
    assert "checksum mismatch in dataset truth/rate" in line and "flip_truth.h5" in line, line


def test_a_fifo_as_the_raw_input_is_named_as_not_a_regular_file(tmp_path, capsys):
    fifo = tmp_path / "raw.h5"
    os.mkfifo(fifo)
    assert main(["reduce", str(fifo), "--out", str(tmp_path / "r.h5"), "--quiet"]) == 2
    assert "is not a regular file" in _one_line_error(capsys)


def test_a_campaign_spec_given_as_raw_says_what_reduce_takes(raw, tmp_path, capsys):
    spec = tmp_path / "spec.toml"
    spec.write_text("[population]\nn = 2\n")
    assert main(["reduce", str(spec), "--out", str(tmp_path / "red"), "--workers", "2"]) == 2
    err = _one_line_error(capsys)
    for needle in (f"{spec} is a TOML file, not a ramp file", "takes a ramp file or a campaign dataset directory",
                   f"'slicersim campaign run {spec} --out DIR'"):
        assert needle in err, (needle, err)
    from slicersim.errors import DatasetError
    from slicersim.reduction.campaign import reduce_dataset
    with pytest.raises(DatasetError, match=r"spec.toml is a file, not a dataset directory"):
        reduce_dataset(spec, tmp_path / "red")
    assert not (tmp_path / "red").exists()


@pytest.mark.parametrize("flag", ["--lbda-edges", "--psf", "--dark"])
def test_option_files_that_are_not_regular_files_are_named_so(raw, tmp_path, capsys, flag):
    import os
    import threading
    fifo = tmp_path / "edges.npy"
    os.mkfifo(fifo)
    codes = []
    argv = ["reduce", str(raw[0]), "--out", str(tmp_path / "o.h5"), "--quiet", "--spectra", flag, str(fifo)]
    thread = threading.Thread(target=lambda: codes.append(main(argv)), daemon=True)
    thread.start()
    thread.join(60)
    assert not thread.is_alive() and codes == [2]
    assert f"{flag}: {fifo} is not a regular file" in _one_line_error(capsys)


def test_a_negative_position_is_a_value_not_a_flag(monkeypatch):
    """`--position -29.4,0` was taken for a flag ("expected one argument")."""
    from slicersim.app.cli import build_parser
    from slicersim.app.reduce_cli import _parse_position
    args = build_parser().parse_args(["reduce", "raw.h5", "--out", "r.h5", "--spectra", "--position", "-29.4,0"])
    assert _parse_position(args.position) == (-29.4, 0.0)
    args = build_parser().parse_args(["reduce", "raw.h5", "--out", "r.h5", "--spectra", "--position", "-1e1,-2"])
    assert _parse_position(args.position) == (-10.0, -2.0)


def test_a_dark_that_removes_all_signal_is_an_error_not_an_all_nan_spectrum():
    """`reduce --spectra --dark 1e6` (the largest accepted) gave exit 0 with all 255 F_λ bins NaN."""
    from types import SimpleNamespace

    from slicersim.errors import ReductionError
    from slicersim.reduction.pipeline import check_spectrum_has_signal
    empty = SimpleNamespace(flux=np.full(255, np.nan))
    with pytest.raises(ReductionError, match=r"narrow field's spectrum has no finite bin: the dark rate subtracted "
                                             r"\(1e\+06 e-/s per pixel\) exceeds the signal everywhere: check --dark"):
        check_spectrum_has_signal(empty, "narrow", 1e6)
    with pytest.raises(ReductionError, match="every pixel of the source is flagged"):
        check_spectrum_has_signal(empty, "wide", 0.0)
    check_spectrum_has_signal(SimpleNamespace(flux=np.r_[np.nan, 1.0]), "narrow", 1e6)     # one finite bin: kept


@pytest.mark.slow
def test_reduce_spectra_with_a_dark_above_the_signal_exits_2(small_layout, tmp_path, capsys):
    path, _, _ = small_layout
    out = tmp_path / "red.h5"
    code = main(["reduce", str(path), "--out", str(out), "--spectra", "--lbda-edges", EDGES, "--ncol", str(NCOL),
                 "--dark", "1e6", "--quiet"])
    assert code == 2 and not out.exists()
    error = _one_line_error(capsys)
    assert "no finite bin" in error or "no point source" in error, error


def test_a_files_reference_pixel_problem_is_not_blamed_on_the_flag():
    """The file's reference-pixel problem read "--no-refpix: nx = 50 is not divisible ..." (the message began
    with the keyword the CLI maps to the flag): it now names the file's correction and the flag as the way out."""
    from slicersim.app.reduce_cli import cli_message
    from slicersim.errors import EffectsError
    from slicersim.reduction.refpix import refpix_correct
    for shape, words in (((1, 2, 40, 50), "its width nx = 50 is not divisible"),
                         ((1, 2, 6, 64), "a border of 4 reference pixels is impossible for its 6×64 detector")):
        with pytest.raises(EffectsError) as err:
            refpix_correct(np.zeros(shape))
        text = cli_message(str(err.value))
        assert text.startswith("reference-pixel correction of this file: ") and words in text
        assert text.endswith("(the file's EFFECTS ask for the correction; --no-refpix, skips it)"), text


@pytest.mark.slow
@pytest.mark.parametrize("damage", ["group", "strings", "negative"])
def test_reduce_spectra_with_a_damaged_extra_dark_is_one_line(small_layout, tmp_path, capsys, damage):
    """--dark auto reads the file's truth/bad_pixels/extra_dark: a damaged one (a group, strings, negative
    rates) is one line naming it and writes nothing (a group or strings were an AttributeError /
    ValueError traceback, negative rates were subtracted silently)."""
    path, _, _ = small_layout
    with h5py.File(path) as fh:
        shape = fh["SCI"].shape[2:]
    data = {"group": None, "strings": np.full(shape, b"x"), "negative": np.full(shape, -1.0, np.float32)}[damage]
    bad = _h5_copy(path, tmp_path / "bad.h5", lambda fh: fh.create_group("truth/bad_pixels/extra_dark")
                   if data is None else fh.create_dataset("truth/bad_pixels/extra_dark", data=data))
    out = tmp_path / "red.h5"
    code = main(["reduce", str(bad), "--out", str(out), "--spectra", "--lbda-edges", EDGES, "--ncol", str(NCOL),
                 "--quiet"])
    assert code == 2 and not out.exists()
    assert "truth/bad_pixels/extra_dark" in _one_line_error(capsys)
