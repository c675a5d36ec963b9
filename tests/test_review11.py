"""Review of issue 11 (raw ramps → rates → cubes → spectra): adversarial findings, one test each."""
import subprocess
import sys

import h5py
import numpy as np
import pytest

from slicersim.products.ramps import simulate

EDGES = np.arange(9050.0, 9951.0, 75.0)     # 12 bins on the small test layout
NCOL = 24


@pytest.fixture(scope="module")
def small_raw(tmp_path_factory):
    """Raw ramps of a point source in the narrow field of the small test layout (660 × 600)."""
    from conftest import small_slicer_mapper

    from slicersim.physics.psf import gaussian_psf_cells
    mapper = small_slicer_mapper()
    lbda = 0.5 * (EDGES[1:] + EDGES[:-1])
    sig = np.linspace(1.2, 1.8, lbda.size)
    iy, ix = np.indices((58, NCOL)).reshape(2, -1)
    psf = gaussian_psf_cells(sig, 0.8 * sig, (58, NCOL), (0.7, -1.4), (iy, ix)).reshape(lbda.size, 58, NCOL)
    image = mapper.project_fields(lbda, EDGES, narrow=400.0 * psf)
    path = tmp_path_factory.mktemp("small") / "raw.h5"
    simulate(image, (4, 2, 0), seed=2, out=path, ron=5.0, dark=0.0, roic_glow=0.0, progress=False)
    return path, mapper


def test_fit_ramps_reads_compressed_ramps_in_a_fresh_process(tmp_path):
    """Known item (a): fit_ramps called directly (no check_ramp_file first) on lz4/zstd ramps
    failed in a fresh process with h5py's 'can't open directory (/usr/local/lib/plugin)'."""
    for comp in ("lz4", "zstd"):
        path = simulate(np.full((8, 16), 5.0), (4, 2, 0), seed=1, progress=False, out=tmp_path / f"{comp}.h5",
                        compression=comp)
        code = ("import sys; from slicersim.reduction.ramp_fit import fit_ramps; "
                "print(fit_ramps(sys.argv[1], progress=False).rate.shape)")
        proc = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True)
        assert proc.returncode == 0 and "(8, 16)" in proc.stdout, proc.stderr[-500:]


def test_reduce_exposure_writes_the_truth_rate(small_raw, tmp_path):
    """Known item (b): reduce_exposure(out=..., fit_options={"with_truth": True}) dropped the truth
    (only reduce_file added it afterwards)."""
    from slicersim.reduction.pipeline import reduce_exposure
    path, mapper = small_raw
    out = tmp_path / "red.h5"
    res = reduce_exposure(path, mapper=mapper, lbda_edges=EDGES, ncol=NCOL, rectify_method="drizzle",
                          fit_options={"with_truth": True, "progress": False}, out=out)
    with h5py.File(out, "r") as fh:
        assert np.array_equal(fh["rates/TRUTH_RATE"][...], res["rates"].truth_rate)
    out2 = tmp_path / "red2.h5"
    reduce_exposure(path, mapper=mapper, lbda_edges=EDGES, ncol=NCOL, rectify_method="drizzle",
                    fit_options={"progress": False}, out=out2)
    with h5py.File(out2, "r") as fh:
        assert "TRUTH_RATE" not in fh["rates"]


def test_truncated_fits_ramps_are_named_in_one_line(tmp_path, capsys):
    """A level-1b FITS cut inside an extension gave 'mmap length is greater than file size' (no file
    name) after an astropy WARNING line."""
    from slicersim.app.cli import main
    from slicersim.errors import RampFileError
    from slicersim.reduction.ramp_fit import fit_ramps
    path = simulate(np.full((16, 32), 5.0), (4, 2, 0), seed=1, progress=False, out=tmp_path / "raw.fits")
    cut = tmp_path / "cut.fits"
    with open(path, "rb") as fh:
        cut.write_bytes(fh.read()[:10000])                  # SCI's data start at byte 8640
    with pytest.raises(RampFileError, match="cut.fits: truncated file: extension SCI ends at byte"):
        fit_ramps(cut, progress=False)
    capsys.readouterr()
    assert main(["reduce", str(cut), "--out", str(tmp_path / "r.h5"), "--quiet"]) == 2
    captured = capsys.readouterr()
    err = (captured.err + captured.out).strip().splitlines()
    assert len(err) == 1 and "truncated file" in err[0], err
    assert not (tmp_path / "r.h5").exists()


@pytest.fixture(scope="module")
def small_cubes(small_raw):
    """(drizzle cube, lsq cube, PSF fractions) of the small layout's point source."""
    from slicersim.physics.psf import gaussian_psf_cells
    from slicersim.reduction.pipeline import rate_variance
    from slicersim.reduction.ramp_fit import fit_ramps
    from slicersim.reduction.rectify import rectify
    path, mapper = small_raw
    rates = fit_ramps(path, progress=False)
    var = rate_variance(rates)
    rate = np.where(np.isfinite(var), rates.rate, 0.0)
    cubes = [rectify(rate, var, mapper=mapper, lbda_edges=EDGES, ncol=NCOL, method=m) for m in ("drizzle", "lsq")]
    lbda = 0.5 * (EDGES[1:] + EDGES[:-1])
    sig = np.linspace(1.2, 1.8, lbda.size)
    iy, ix = np.indices((58, NCOL)).reshape(2, -1)
    psf = gaussian_psf_cells(sig, 0.8 * sig, (58, NCOL), (0.7, -1.4), (iy, ix)).reshape(lbda.size, 58, NCOL)
    return cubes[0], cubes[1], psf


@pytest.mark.parametrize("method", ["optimal", "gls"])
def test_a_psf_that_is_not_fractions_is_refused(small_cubes, method, tmp_path, small_raw, monkeypatch, capsys):
    """A peak-normalised PSF (Σ ≫ 1) gave 'optimal' and 'gls' fluxes 1/Σ of the truth (0.0 ± 0.0
    for a 1e6× PSF) without a word; the docstring says Σ over the field ≤ 1."""
    from slicersim.app.cli import main
    from slicersim.errors import ParameterError
    from slicersim.reduction import rectify
    from slicersim.reduction.spectra import extract_spectrum
    drizzle, lsq, psf = small_cubes
    cube = lsq if method == "gls" else drizzle
    assert np.all(np.abs(extract_spectrum(cube, method=method, psf=psf).flux - 400.0) < 80.0)
    with pytest.raises(ParameterError, match="Σ over the field ≤ 1"):
        extract_spectrum(cube, method=method, psf=psf / psf.max(axis=(1, 2), keepdims=True))
    np.save(tmp_path / "peak.npy", psf / psf.max())
    monkeypatch.setattr(rectify, "_default_mapper", lambda: small_raw[1])
    assert main(["reduce", str(small_raw[0]), "--out", str(tmp_path / "r.h5"), "--spectra", "--quiet",
                 "--lbda-edges", "9050,9950,75", "--ncol", str(NCOL), "--psf", str(tmp_path / "peak.npy")]) == 2
    assert "Σ over the field ≤ 1" in capsys.readouterr().err and not (tmp_path / "r.h5").exists()


@pytest.mark.parametrize("kwargs, message", [({"nchunks": 0}, r"nchunks \(λ chunks of the PSF fit\) must be an integer ≥ 1"),
                                             ({"nchunks": -3}, r"nchunks \(λ chunks of the PSF fit\) must be an integer ≥ 1"),
                                             ({"nchunks": 2.5}, r"nchunks \(λ chunks of the PSF fit\) must be an integer ≥ 1"),
                                             ({"background": "no"}, "background must be True or False")])
@pytest.mark.parametrize("method", ["optimal", "aperture", "gls"])
def test_extraction_options_of_the_wrong_kind_are_refused(small_cubes, method, kwargs, message):
    """nchunks=0 was taken as 1 chunk (σ constant in λ: fluxes 8 % higher), background="no" as True."""
    from slicersim.errors import ParameterError
    from slicersim.reduction.spectra import extract_spectrum
    with pytest.raises(ParameterError, match=message):
        extract_spectrum(small_cubes[1], method=method, **kwargs)


@pytest.mark.parametrize("value", [0, -1, "3", True])
def test_fit_ramps_saturation_must_be_positive(value):
    """saturation=0, -1, "3" or True flagged every group SATURATED: an all-NaN rate image, no error."""
    from slicersim.errors import ParameterError
    from slicersim.reduction.ramp_fit import fit_ramps
    sci = np.full((1, 4, 4, 8), 1000, np.uint16) + np.arange(4, dtype=np.uint16)[None, :, None, None] * 10
    attrs = {"NFRAMES": 1, "GROUPGAP": 0, "TFRAME": 1.0, "GAIN": 1.0, "READNOISE": 5.0}
    assert np.allclose(fit_ramps((sci, None, None, attrs), progress=False).rate, 10.0)
    with pytest.raises(ParameterError, match="saturation must be a number of DN > 0"):
        fit_ramps((sci, None, None, attrs), saturation=value, progress=False)
    with pytest.raises(Exception, match="SATURATION = 0.0 DN must be > 0"):
        fit_ramps((sci, None, None, dict(attrs, SATURATION=0.0)), progress=False)


@pytest.mark.parametrize("case, message", [
    ("empty stack", "empty stack"), ("complex", "real numbers"), ("huge rate", "finite values beyond"),
    ("huge variance", "variance has values outside"), ("tiny variance", "variance has values outside")])
@pytest.mark.parametrize("method", ["drizzle", "lsq"])
def test_rectify_absurd_images_are_refused_in_one_clear_line(small_raw, method, case, message):
    """An empty stack raised numpy's 'need at least one array to stack'; complex images lost their
    imaginary part silently; rates beyond 1e300 or variances of 1e300 / 1e-320 raised 'image must be
    finite where the tables reach (replace NaN pixels first)' about finite inputs."""
    from slicersim.errors import ParameterError
    from slicersim.reduction.rectify import rectify
    mapper = small_raw[1]
    rate, var = np.ones((660, 600)), np.ones((660, 600))
    if case == "empty stack":
        rate = np.zeros((0, 660, 600))
    elif case == "complex":
        rate = rate + 1j
    elif case == "huge rate":
        rate[3, 3] = 1e300
    elif case == "huge variance":
        var[:] = 1e300
    else:
        var[:] = 1e-320
    with pytest.raises(ParameterError, match=message):
        rectify(rate, var, mapper=mapper, lbda_edges=EDGES, ncol=NCOL, method=method)
