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
