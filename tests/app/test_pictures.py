"""Pictures (slicersim.app.pictures, re-exported by app.plotting) and the footprints/plot CLI.

Every figure is drawn with Agg and checked against arrays computed independently: the
image data, the curves, the number of slice outlines."""
import errno
import os
import subprocess
import sys

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from matplotlib.patches import Polygon  # noqa: E402
from scipy.special import j1  # noqa: E402

from slicersim.app import plotting  # noqa: E402
from slicersim.app.cli import main  # noqa: E402
from slicersim.assembly import build_simulation  # noqa: E402
from slicersim.errors import ParameterError  # noqa: E402
from slicersim.instrument.footprints import detector_label_image, field_footprints  # noqa: E402
from slicersim.instrument.mapper import SlicerMapper  # noqa: E402
from slicersim.io.footprint_files import read_label_image, read_outlines  # noqa: E402
from slicersim.io.atomic import temporary_path  # noqa: E402
from slicersim.targets import Lazuli3DFlat, LazuliGalaxy, LazuliSupernova  # noqa: E402


@pytest.fixture(scope="module")
def target():
    return LazuliSupernova(redshift=0.5)


@pytest.fixture(scope="module")
def small_fields():
    """Both fields' footprints on 30 bins of the CBE grid (fast)."""
    mapper = SlicerMapper.default(table_cache=None)
    edges = build_simulation("cbe", "narrow").spectrograph.lbda_edges[300:331]
    return mapper, edges, [field_footprints(mapper, f, edges, 116) for f in ("narrow", "wide")]


@pytest.fixture(autouse=True)
def close_figures():
    yield
    plt.close("all")


def _colorbar_labels_readable(fig):
    """Every colour bar has 2-8 tick labels and none overlaps another."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    canvas = FigureCanvasAgg(fig)                          # also after save_figure closed it
    canvas.draw()
    renderer = canvas.get_renderer()
    bars = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert bars
    for ax in bars:
        labels = [t for t in ax.get_yticklabels() if t.get_visible() and t.get_text()]
        assert 2 <= len(labels) <= 8, [t.get_text() for t in labels]
        boxes = sorted((t.get_window_extent(renderer) for t in labels), key=lambda b: b.y0)
        assert all(a.y1 <= b.y0 for a, b in zip(boxes, boxes[1:])), [t.get_text() for t in labels]


def _dead_pid():
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def _by_gid(items, gid):
    found = [a for a in items if a.get_gid() == gid]
    assert len(found) == 1, (gid, [a.get_gid() for a in items])
    return found[0]


# --------------------------------------------------------------------------- both fields
def test_show_fields_draws_both_fields_scene_and_cube(target):
    assert plotting.show_fields is plotting.__dict__["show_fields"]          # exported by plotting
    fig = plotting.show_fields(target, lbda_range=(5000, 8000))
    wide = LazuliSupernova(redshift=0.5, field="wide").simulation           # built independently
    images = [im for ax in fig.axes for im in ax.get_images()]
    lines = [ln for ax in fig.axes for ln in ax.get_lines()]
    assert len(images) == 4
    for field, sim in (("narrow", target.simulation), ("wide", wide)):
        sel = (sim.lbda >= 5000) & (sim.lbda <= 8000)
        scene = sim.get_projected_scene()
        signal = sim.get_cube()[0]
        assert np.allclose(_by_gid(images, f"{field}:scene").get_array(), scene[sel].sum(axis=0), rtol=1e-12)
        assert np.allclose(_by_gid(images, f"{field}:cube").get_array(), signal[sel].sum(axis=0), rtol=1e-12)
        iy, ix = sim.aperture
        assert np.allclose(_by_gid(lines, f"{field}:cube").get_ydata(), signal[:, iy, ix].sum(axis=1), rtol=1e-12)
        assert np.allclose(_by_gid(lines, f"{field}:scene").get_ydata(), scene[:, iy, ix].sum(axis=1), rtol=1e-12)
        s = sim.spectrograph.spatial_scale                                  # square cells, 58 × 116
        assert np.allclose(_by_gid(images, f"{field}:cube").get_extent(), (-58 * s, 58 * s, -29 * s, 29 * s))
    assert target.field == "narrow"                                        # the target itself is untouched


@pytest.mark.slow
def test_show_fields_from_a_simulation_and_a_noisy_cube(target, tmp_path):
    sim = build_simulation("cbe", "wide", pointsource=target.pointsource)
    fig = plotting.show_fields(sim, seed=7, savefile=tmp_path / "fields.png")
    assert (tmp_path / "fields.png").stat().st_size > 10_000
    images = [im for ax in fig.axes for im in ax.get_images()]
    narrow = build_simulation("cbe", "narrow", pointsource=target.pointsource)
    noisy = narrow.get_cube(seed=7)[2]
    assert np.allclose(_by_gid(images, "narrow:cube").get_array(), noisy.sum(axis=0), rtol=1e-12)
    assert np.allclose(_by_gid(images, "narrow:scene").get_array(),
                       narrow.get_projected_scene().sum(axis=0), rtol=1e-12)
    _colorbar_labels_readable(fig)                                       # asinh ticks crowd around 0
    with pytest.raises(ParameterError, match="selects no bin"):
        plotting.show_fields(target, lbda_range=(100, 200))
    with pytest.raises(ParameterError, match="Target or a Simulation"):
        plotting.show_fields("narrow")


def test_round_galaxy_is_drawn_round():
    """Review 10 #2: square cells of spatial_scale, 116 × 58 of them: x spans twice y."""
    galaxy = LazuliGalaxy(0.5, axis_ratio=1.0)
    fig = plotting.show_fields({"narrow": galaxy})
    im = _by_gid([im for ax in fig.axes for im in ax.get_images()], "narrow:scene")
    s, (ny, nx) = galaxy.simulation.spectrograph.spatial_scale, galaxy.simulation.spectrograph.shape
    assert (ny, nx, s) == (58, 116, 0.04)
    x0, x1, y0, y1 = im.get_extent()
    assert np.allclose((x1 - x0, y1 - y0), (nx * s, ny * s))               # 4.64″ × 2.32″
    img = np.asarray(im.get_array(), float)
    img = img - img.min()
    x = x0 + (np.arange(nx) + 0.5) * (x1 - x0) / nx
    y = y0 + (np.arange(ny) + 0.5) * (y1 - y0) / ny
    xx, yy = np.meshgrid(x, y)
    w = np.where(np.hypot(xx, yy) < 1.0, img, 0.0)                        # moments within 1″ (in the field)
    vx = (w * xx**2).sum() / w.sum()
    vy = (w * yy**2).sum() / w.sum()
    assert np.sqrt(vx / vy) == pytest.approx(1.0, abs=0.03)                # round on the plot (was 0.5)


@pytest.mark.slow
def test_show_fields_of_a_flat():
    """Review 10 #21: no aperture spectrum for a lamp, readable colour bars, a true title."""
    flat = Lazuli3DFlat.from_qth()
    fig = plotting.show_fields(flat)
    texts = [fig.get_suptitle()] + [t.get_text() for ax in fig.axes
                                          for t in (ax.yaxis.label, ax.title)]
    assert not any("aperture" in t for t in texts)
    title = fig.get_suptitle()
    assert "Lazuli3DFlat" in title and "narrow and wide" in title and "both" not in title
    # at (16, 8, 0) the wide field's red end saturates (as the detector does): NaN cells, said in the title
    assert any("cells saturated" in t for t in texts if t.startswith("wide"))
    assert not any("cells saturated" in t for t in texts if t.startswith("narrow"))
    lines = [ln for ax in fig.axes for ln in ax.get_lines()]
    for field, sim in (("narrow", flat.simulation), ("wide", None)):
        if sim is None:
            continue
        cube = sim.get_cube()[0]
        assert np.allclose(_by_gid(lines, f"{field}:cube").get_ydata(), cube.mean(axis=(1, 2)), rtol=1e-12)
    _colorbar_labels_readable(fig)
    one = plotting.show_fields({"wide": flat.simulation})
    assert "wide field" in one.get_suptitle() and "narrow" not in one.get_suptitle()


# --------------------------------------------------------------------------- PSF
def test_show_psf_profiles_curves_are_the_airy_and_gaussian_models(target):
    lbdas = (6000.0, 12000.0)
    fig = plotting.show_psf_profiles(target, lbda=lbdas, rmax=0.3, npoints=301)
    lines = [ln for ax in fig.axes for ln in ax.get_lines()]
    assert len(lines) == 5 * len(lbdas) + 2 * 2                            # 5 curves per λ, 2 cell marks per panel
    tel, sim = target.simulation.telescope, target.simulation
    assert tel.obscuration == 0.0
    for lam in lbdas:
        r = _by_gid(lines, f"airy:{lam:g}").get_xdata()
        v = np.pi * tel.diameter_ext * np.radians(r / 3600) / (lam * 1e-10)
        with np.errstate(invalid="ignore", divide="ignore"):
            airy = np.where(v > 0, (2 * j1(v) / v) ** 2, 1.0)
        assert np.allclose(_by_gid(lines, f"airy:{lam:g}").get_ydata(), airy, rtol=1e-9, atol=1e-15)
        sig_t = tel.psf_sigma_ref * lam / 1e4                               # Airy-equivalent σ [arcsec]
        sig_y = np.hypot(sig_t, tel.guiding_sigma)
        sig_x = np.sqrt(sig_y**2 + (sim.instrumental_sigma * sim.spectrograph.spatial_scale) ** 2)
        assert np.allclose(_by_gid(lines, f"gauss_y:{lam:g}").get_ydata(), np.exp(-0.5 * (r / sig_y) ** 2))
        assert np.allclose(_by_gid(lines, f"gauss_x:{lam:g}").get_ydata(), np.exp(-0.5 * (r / sig_x) ** 2))
        ee = _by_gid(lines, f"ee_airy:{lam:g}")
        first_dark = 1.22 * lam * 1e-10 / tel.diameter_ext * 206264.806
        assert np.interp(first_dark, ee.get_xdata(), ee.get_ydata()) == pytest.approx(0.8378, abs=2e-3)
    for bad in ((), (-5.0,), (np.nan,)):
        with pytest.raises(ParameterError, match="lbda"):
            plotting.show_psf_profiles(target, lbda=bad)
    for bad in ((1e9,), (5000.0, 3000.0)):                                 # review 10 #17
        with pytest.raises(ParameterError, match="instrument's range"):
            plotting.show_psf_profiles(target, lbda=bad)


# --------------------------------------------------------------------------- slice map
def test_show_slice_map_outlines_every_slice(small_fields):
    mapper, edges, fields = small_fields
    fig = plotting.show_slice_map(footprints=fields)
    ax = fig.axes[0]
    outlines = [p for p in ax.patches if isinstance(p, Polygon) and str(p.get_gid()).startswith("slice ")]
    assert len(outlines) == 116
    texts = [t for t in ax.texts if str(t.get_gid()).startswith("label ")]
    assert sorted(int(t.get_text()) for t in texts) == list(range(1, 117))
    for f in fields:
        for s in f:
            xy = _by_gid(outlines, f"slice {s.slice_id}").get_xy()
            assert np.array_equal(xy[:-1], s.contour) and np.array_equal(xy[-1], s.contour[0])
    background = _by_gid(ax.get_images(), "background").get_array()
    label = detector_label_image(*fields)
    assert np.array_equal(background.mask, label == -1)
    assert np.array_equal(background.data, label)

    narrow = plotting.show_slice_map(mapper, "narrow", lbda_edges=edges, ncol=116, labels=False,
                                     region=(2200, 3900, 200, 3900))
    ax = narrow.axes[0]
    assert len([p for p in ax.patches if isinstance(p, Polygon)]) == 58 and not ax.texts
    assert ax.get_xlim() == (200, 3900) and ax.get_ylim() == (2200, 3900)


@pytest.mark.slow
def test_show_slice_map_over_a_detector_image(small_fields):
    mapper, edges, fields = small_fields
    rng = np.random.default_rng(1)
    image = rng.uniform(0.0, 1.0, mapper.detector_shape)
    image[:10] = 0.0
    fig = plotting.show_slice_map(footprints=fields[1], image=image)
    shown = _by_gid(fig.axes[0].get_images(), "background").get_array()
    assert np.array_equal(np.isnan(shown), image <= 0)
    assert np.array_equal(shown[10:], image[10:])
    with pytest.raises(ParameterError, match="detector shape"):
        plotting.show_slice_map(footprints=fields, image=image[:100])
    with pytest.raises(ParameterError, match="fields must be"):
        plotting.show_slice_map(mapper, fields="middle", lbda_edges=edges)
    for region in ((0, 99999, 0, 10), (-5, 100, 0, 10), (0, 100, 4000, 4097)):   # review 10 #17
        with pytest.raises(ParameterError, match="within|detector"):
            plotting.show_slice_map(footprints=fields, region=region)


def test_mapper_show_slices_is_the_slice_map_of_its_fields(small_fields):
    """SlicerMapper.show_slices (slicersim 1.4.2's show_slices): the detector with the outlines of the
    fields asked for, on the grid of the spectrograph given; axes in detector pixels."""
    from types import SimpleNamespace
    mapper, edges, fields = small_fields
    fig = mapper.show_slices("narrow", spectrograph=SimpleNamespace(lbda_edges=edges, shape=(58, 116)),
                             region=(2200, 3900, 200, 3900))
    ax = fig.axes[0]
    outlines = [p for p in ax.patches if isinstance(p, Polygon) and str(p.get_gid()).startswith("slice ")]
    assert sorted(int(p.get_gid().split()[1]) for p in outlines) == list(range(1, 59))
    seven = next(fp for fp in fields[0] if fp.slice_id == 7)
    assert np.array_equal(_by_gid(outlines, "slice 7").get_xy()[:-1], seven.contour)
    assert ax.get_xlabel() == "detector column x [px]" and ax.get_ylabel() == "detector row y [px]"
    assert fig.axes[1].get_ylabel() == "slice id (label image)"
    image = np.ones(mapper.detector_shape)
    fig = mapper.show_slices(("narrow", "wide"), spectrograph=SimpleNamespace(lbda_edges=edges, shape=(58, 116)),
                             image=image, labels=False)
    assert fig.axes[1].get_ylabel() == "detector image [e-/s/px]"
    with pytest.raises(ParameterError, match="fields"):
        mapper.show_slices("middle")
    with pytest.raises(ParameterError, match="region"):
        mapper.show_slices("narrow", spectrograph=SimpleNamespace(lbda_edges=edges, shape=(58, 116)),
                           region=(0, 99999, 0, 10))


# --------------------------------------------------------------------------- CLI
def test_cli_footprints_writes_label_image_and_outlines(tmp_path, capsys):
    out = tmp_path / "fp"
    assert main(["footprints", "--field", "wide", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "wide: 58 slices" in text and "footprints_labels.fits" in text
    image, header = read_label_image(out / "footprints_labels.fits")
    desc = read_outlines(out / "footprints_outlines.json")
    assert header["FIELDS"] == "wide" and header["NBINS"] == 510
    assert set(np.unique(image)) == {-1, *range(59, 117)} and image[2048:].max() == -1
    slices = desc["fields"][0]["slices"]
    assert [s["slice_id"] for s in slices] == list(range(59, 117))
    # every shared pixel is in two masks and carries one label; the default layout's slices share
    # none (its spots add no blur to the cubes', whose images stay within their traces)
    assert sum(s["npix"] for s in slices) - int((image != -1).sum()) == header["NSHARED"] == 0
    r0, r1, c0, c1 = slices[0]["bbox"]
    rows, cols = np.nonzero(image == 59)
    assert rows.min() >= r0 and rows.max() < r1 and cols.min() >= c0 and cols.max() < c1
    # existing outputs: one line, exit 2, nothing changed
    before = (out / "footprints_labels.fits").stat().st_mtime_ns
    assert main(["footprints", "--field", "wide", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("slicersim: error: output file exists")
    assert (out / "footprints_labels.fits").stat().st_mtime_ns == before


@pytest.mark.parametrize("args, match", [
    (["plot", "psf", "--out", "x.txt"], "must end with"),
    (["plot", "slice-map", "--out", "m.png", "--region", "10", "5", "0", "100"], "--region"),
    (["plot", "fields", "--out", "f.png", "--lbda-range", "8000", "5000"], "LO < HI"),
    (["footprints", "--out", "fp", "--truncate", "-1"], "--truncate"),
    (["footprints", "--out", "fp", "--spot-table", "missing.csv"], "--spot-table: missing.csv: No such file"),
    (["footprints", "--out", "missing/fp"], "parent directory"),
    (["plot", "psf", "--out", "p.png", "--lbda", "1e9"], "instrument's range"),            # review 10 #17
    (["plot", "slice-map", "--out", "m.png", "--region", "0", "99999", "0", "10"], "--region"),
    (["plot", "fields", "--out", "f.png", "--lbda-range", "3000", "8000"], "instrument's range"),
])
def test_cli_user_errors_are_one_line(tmp_path, monkeypatch, capsys, args, match):
    monkeypatch.chdir(tmp_path)
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and match in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_cli_plot_psf_and_slice_map(tmp_path, capsys):
    assert main(["plot", "psf", "--lbda", "8000", "--out", str(tmp_path / "psf.png")]) == 0
    assert (tmp_path / "psf.png").stat().st_size > 10_000
    assert main(["plot", "slice-map", "--field", "narrow", "--region", "3300", "3900", "3400", "3900",
                 "--out", str(tmp_path / "map.png")]) == 0
    assert (tmp_path / "map.png").stat().st_size > 10_000
    assert "wrote" in capsys.readouterr().out


# --------------------------------------------------------------------------- atomic outputs (review 10)
def _write_fails_on_second_file(monkeypatch, directory):
    """os.write raises ENOSPC from the second file written under ``directory`` on (a full disk)."""
    real, files = os.write, []

    def write(fd, data):
        path = os.readlink(f"/proc/self/fd/{fd}")
        if path.startswith(str(directory)):
            if path not in files:
                files.append(path)
            if len(files) > 1:
                raise OSError(errno.ENOSPC, "No space left on device")
        return real(fd, data)
    monkeypatch.setattr(os, "write", write)


def test_cli_footprints_figure_in_new_out_and_full_disk(tmp_path, monkeypatch, capsys):
    """#8: --figure may point into the --out directory to be created; #5: a full disk leaves
    neither file (nor the directory it created)."""
    out = tmp_path / "new"
    args = ["footprints", "--field", "narrow", "--out", str(out), "--figure", str(out / "map.png")]
    with monkeypatch.context() as m:
        _write_fails_on_second_file(m, tmp_path)
        assert main(args[:-2]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "No space left" in err
    assert list(tmp_path.iterdir()) == []
    assert main(args) == 0
    assert sorted(p.name for p in out.iterdir()) == ["footprints_labels.fits", "footprints_outlines.json", "map.png"]
    assert (out / "map.png").stat().st_size > 10_000 and "wrote" in capsys.readouterr().out


def test_cli_figures_are_written_atomically(tmp_path, monkeypatch, capsys):
    """#7: a failing savefig (full disk) leaves no partial figure and keeps an existing one;
    a temporary left by a killed writer is removed by the next write."""
    good = tmp_path / "p.png"
    assert main(["plot", "psf", "--lbda", "8000", "--out", str(good)]) == 0
    before = good.read_bytes()
    capsys.readouterr()

    def partial_savefig(self, fname, *args, **kwargs):
        fh = open(fname, "wb") if isinstance(fname, (str, os.PathLike)) else fname
        fh.write(b"\x89PNG partial")
        if fh is not fname:
            fh.close()
        raise OSError(errno.ENOSPC, "No space left on device")
    with monkeypatch.context() as m:
        m.setattr(matplotlib.figure.Figure, "savefig", partial_savefig)
        assert main(["plot", "psf", "--lbda", "8000", "--out", str(good), "--overwrite"]) == 2
        assert main(["plot", "psf", "--lbda", "8000", "--out", str(tmp_path / "q.png")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 2 and err.count("No space left") == 2
    assert good.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["p.png"]
    stale = temporary_path(tmp_path / "q.png").replace(f"-{os.getpid()}-", f"-{_dead_pid()}-")
    open(stale, "wb").write(b"\x89PNG killed")
    assert main(["plot", "psf", "--lbda", "8000", "--out", str(tmp_path / "q.png")]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.png", "q.png"]


def test_picture_arguments_are_parameter_errors_naming_them(target):
    from slicersim.app.pictures import check_region
    with pytest.raises(ParameterError, match=r"region\[1\] \(row1\) \[px\] must be an integer"):
        check_region((0, 10.5, 0, 10), (4096, 4096))
    with pytest.raises(ParameterError, match=r"region must be \(row0, row1, col0, col1\)"):
        check_region("0 10 0 10", (4096, 4096))
    with pytest.raises(ParameterError, match="npoints must be an integer"):
        plotting.show_psf_profiles(target, lbda=8000.0, npoints=2.5)
    with pytest.raises(ParameterError, match=r"lbda \[AA\] must be an array of real numbers"):
        plotting.show_psf_profiles(target, lbda="red")
    with pytest.raises(ParameterError, match="target_or_sim must be a Target or a Simulation"):
        plotting.plot_spectrum("sn")
    plt.close("all")


def test_read_outlines_names_a_file_that_is_not_outlines_json(tmp_path):
    from slicersim.errors import DatasetError
    bad = tmp_path / "fp_outlines.json"
    bad.write_bytes(b"\x89PNG\r\n")
    with pytest.raises(DatasetError, match="fp_outlines.json: not a footprint outlines JSON file"):
        read_outlines(bad)
