"""Detector footprints of the slices (slicersim.instrument.footprints) and their files.

The reference for "which pixels receive light" is the projection itself: a uniform cube
(and one-slice cubes) projected with SlicerMapper.project_cube on a 40-bin piece of the
CBE grid.  Footprints must give exactly its lit pixels (the windows are the projection's).
"""
import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from matplotlib.path import Path as MplPath

from slicersim.errors import ParameterError
from slicersim.instrument import footprints as fpm
from slicersim.instrument.footprints import (NO_SLICE, detector_label_image, field_footprints, mask_outlines,
                                             polygon_area, save_footprints)
from slicersim.instrument.mapper import SlicerMapper
from slicersim.io.footprint_files import read_label_image, read_outlines


def cbe_grid():
    from slicersim.instrument.spectrograph import wavelength_grid_from_dispersion
    from slicersim.io.config import builtin_config_dir
    from slicersim.io.curves import read_curve
    lam, cols = read_curve(f"{builtin_config_dir()}/dispersion_prism.ecsv")
    return wavelength_grid_from_dispersion(lam, next(iter(cols.values())), (4000, 17000), 1.3, 2.3)


_LBDA, _EDGES = cbe_grid()
LBDA, EDGES = _LBDA[200:240], _EDGES[200:241]
NCOL = 116


@pytest.fixture(scope="module")
def mapper():
    """1.2-px spots applied in full (slices overlap in their tails): the default layout's spots
    add no blur to the cubes' own, so its slices do not overlap at all."""
    from conftest import wide_spot_mapper
    return wide_spot_mapper(table_cache=None)


@pytest.fixture(scope="module")
def fields(mapper):
    return {f: field_footprints(mapper, f, EDGES, NCOL) for f in ("narrow", "wide")}


def _inside(outlines, rows, cols):
    """Even-odd point-in-polygon of pixel centres."""
    pts = np.stack([cols + 0.5, rows + 0.5], axis=1)
    inside = np.zeros(rows.size, bool)
    for xy in outlines:
        inside ^= MplPath(xy).contains_points(pts)
    return inside


# --------------------------------------------------------------------------- against the projection
@pytest.mark.parametrize("field", ["narrow", "wide"])
def test_masks_are_the_lit_pixels_of_projected_cubes(mapper, fields, field):
    fp = fields[field]
    cube = np.ones((LBDA.size, 58, NCOL))
    lit = mapper.project_cube(cube, LBDA, EDGES, field) > 0
    assert lit.sum() == 354904                                   # the measured count: non-trivial
    assert np.array_equal(fp.union_mask(), lit)
    for row in (0, 1, 27, 28, 29, 56, 57):                       # slices 58, 57, 30, 29, 28, 2, 1 (+58)
        one = np.zeros_like(cube)
        one[:, row] = 1.0
        sid = fp.slice_ids[-1 - row]
        img = mapper.project_cube(one, LBDA, EDGES, field)
        assert np.array_equal(fp.mask(sid), img > 0), sid
        assert fp[sid].npix == int((img > 0).sum())


def test_detector_edge_clips_footprints_and_lbda_range(mapper):
    """Shift the layout up by 420 px: the narrow top tier's blue end leaves the detector."""
    values = mapper.values.copy()
    values[..., 1] += 420.0
    moved = SlicerMapper(mapper.slice_ids, mapper.fieldpos_nodes, mapper.lbda_nodes, values, table_cache=None)
    fp = field_footprints(moved, "narrow", _EDGES[:201], NCOL)
    lit = moved.project_cube(np.ones((200, 58, NCOL)), _LBDA[:200], _EDGES[:201], "narrow") > 0
    assert np.array_equal(fp.union_mask(), lit)
    top = fp[1]                                                 # tier 1 (slices 1-29) is at the top
    assert top.bbox[1] == 4096 and top.lbda_range[0] > _EDGES[0] + 100
    assert fp[30].lbda_range == (_EDGES[0], _EDGES[200])         # tier 2 stays on the detector
    lo = top.lbda_range[0]
    assert np.all(moved.forward(1, 0.0, lo + 20)[1] < 4096 + 8)  # first kept bin is near the edge


# --------------------------------------------------------------------------- overlaps and labels
def test_overlaps_are_reported_and_labels_resolve_them(fields):
    for fp in fields.values():
        count = np.zeros(fp.detector_shape, np.int16)
        for s in fp:
            r0, r1, c0, c1 = s.bbox
            count[r0:r1, c0:c1] += s.mask
        pairs = fp.overlaps()
        assert 0 < len(pairs) < 58 and all(b - a == 1 for a, b, _ in pairs)   # only neighbours share
        assert count.max() == 2                                                 # never three slices
        assert sum(n for *_, n in pairs) == int((count == 2).sum())
        label = fp.label_image()
        assert np.array_equal(label != NO_SLICE, count > 0)
        per_label = np.bincount(label[label != NO_SLICE])
        for s in fp:
            r0, r1, c0, c1 = s.bbox
            mine, one = label[r0:r1, c0:c1] == s.slice_id, count[r0:r1, c0:c1] == 1
            assert mine.sum() == per_label[s.slice_id]          # nothing outside its box
            assert not np.any(mine & ~s.mask)                   # a label only where the slice sends light
            assert np.all(mine[s.core])                         # its geometric image is always its own
            assert np.all(mine[s.mask & one])
        for a, b, n in pairs:                                   # shared pixels split between the two
            shared = fp.mask(a) & fp.mask(b)
            got = label[shared]
            assert set(np.unique(got)) <= {a, b} and got.size == n
    both = detector_label_image(fields["narrow"], fields["wide"])
    assert np.array_equal(both[2048:], fields["narrow"].label_image()[2048:])
    assert np.array_equal(both[:2048], fields["wide"].label_image()[:2048])
    assert set(np.unique(both)) == {NO_SLICE, *range(1, 117)}


# --------------------------------------------------------------------------- outlines
def test_contours_enclose_their_masks_exactly(fields):
    for fp in fields.values():
        for s in fp:
            r0, r1, c0, c1 = s.bbox
            rows, cols = np.mgrid[r0 - 1:r1 + 1, c0 - 1:c1 + 1]
            rows, cols = rows.ravel(), cols.ravel()
            inside = _inside(s.outlines, rows, cols)
            truth = np.zeros((r1 - r0 + 2, c1 - c0 + 2), bool)
            truth[1:-1, 1:-1] = s.mask
            assert np.array_equal(inside, truth.ravel()), s.slice_id
            assert len(s.outlines) == 1 and polygon_area(s.contour) == s.npix   # one piece, no hole
            seg = np.diff(s.contour, axis=0, append=s.contour[:1])
            assert np.all((seg[:, 0] == 0) ^ (seg[:, 1] == 0))                 # along pixel edges, corners only


def test_mask_outlines_holes_and_corner_touching_pixels():
    m = np.zeros((7, 8), bool)
    m[1:6, 1:6] = True
    m[3, 3] = False                                              # a hole
    m[6, 6] = True                                               # touches the square at a corner only
    loops = mask_outlines(m, origin=(10, 20))
    areas = [polygon_area(xy) for xy in loops]
    assert areas == [25.0, 1.0, -1.0]                            # outer CCW, the corner pixel, the hole CW
    assert sorted(map(tuple, loops[0].tolist())) == [(21, 11), (21, 16), (26, 11), (26, 16)]
    assert sorted(map(tuple, loops[2].tolist())) == [(23, 13), (23, 14), (24, 13), (24, 14)]
    rows, cols = np.mgrid[0:7, 0:8]
    inside = _inside(loops, rows.ravel() + 10, cols.ravel() + 20)
    assert np.array_equal(inside, m.ravel())
    assert mask_outlines(np.zeros((3, 3), bool)) == []


# --------------------------------------------------------------------------- traces
def test_trace_follows_the_forward_map_inside_the_core(mapper, fields):
    fp = fields["wide"]
    s = fp[70]
    lbda, x, y = s.trace()
    assert np.allclose(lbda, 0.5 * (EDGES[1:] + EDGES[:-1]))
    px, py = mapper.forward(70, 0.0, lbda)
    assert np.array_equal(x, px) and np.array_equal(y, py)
    assert np.all(np.diff(y) < 0)                                # dispersion towards −y
    r0, _, c0, _ = s.bbox
    assert np.all(s.core[np.floor(y).astype(int) - r0, np.floor(x).astype(int) - c0])
    assert s.lbda_range == (EDGES[0], EDGES[-1])


# --------------------------------------------------------------------------- cost and cache
def test_computed_from_geometry_without_projection_and_cached(mapper, monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("footprints must not project a cube")
    monkeypatch.setattr(mapper, "project_cube", refuse)
    monkeypatch.setattr(mapper, "projection_tables", refuse)
    a = field_footprints(mapper, "narrow", EDGES[:11], NCOL, truncate=3.0)
    assert field_footprints(mapper, "narrow", EDGES[:11], NCOL, truncate=3.0) is a
    b = field_footprints(mapper, "narrow", EDGES[:11], NCOL, truncate=4.0)
    assert b is not a and b[1].npix > a[1].npix                  # wider windows, more pixels
    assert len(fpm._CACHE[mapper]) <= fpm._CACHE_PER_MAPPER


def test_spectrograph_gives_the_grid(mapper):
    class Spec:
        lbda_edges, shape = EDGES, (58, NCOL)
    assert field_footprints(mapper, "narrow", spectrograph=Spec()) is field_footprints(mapper, "narrow", EDGES, NCOL)
    with pytest.raises(ParameterError, match="spectrograph must be"):
        field_footprints(mapper, "narrow", spectrograph=object())


def test_spectrograph_may_be_a_simulation_or_a_target(mapper):
    """Review 10 #15: the docstring's "a Simulation's spectrograph" — a Simulation (or a
    Target) is accepted and gives the same (cached) footprints as its spectrograph."""
    from slicersim.assembly import build_simulation
    from slicersim.targets import LazuliSupernova
    sim = build_simulation("cbe", "wide")
    sim.spectrograph.update(spectral_range=(9000.0, 9300.0))               # a few bins: fast
    ref = field_footprints(mapper, "wide", spectrograph=sim.spectrograph)
    assert ref.lbda_edges.size < 30 and ref.ncol == 116
    assert field_footprints(mapper, "wide", spectrograph=sim) is ref
    target = LazuliSupernova(0.5, field="wide")
    target.simulation.spectrograph.update(spectral_range=(9000.0, 9300.0))
    assert field_footprints(mapper, "wide", spectrograph=target) is ref


@pytest.mark.parametrize("kwargs, match", [
    (dict(field="middle"), "field must be"),
    (dict(lbda_edges=None), "cube grid"),
    (dict(lbda_edges=EDGES[::-1]), "increasing"),
    (dict(ncol=0), "ncol"),
    (dict(ncol=2.5), "ncol"),
    (dict(truncate=-1.0), "truncate"),
    (dict(slices=[1, 999]), "unknown slice"),
    (dict(oversample=(0, 1)), "oversample"),
])
def test_bad_input(mapper, kwargs, match):
    args = dict(field="narrow", lbda_edges=EDGES, ncol=NCOL) | kwargs
    with pytest.raises(ParameterError, match=match):
        field_footprints(mapper, **args)
    with pytest.raises(ParameterError, match="SlicerMapper"):
        field_footprints(object(), "narrow", EDGES, NCOL)


# --------------------------------------------------------------------------- files
def test_save_and_read_back(fields, tmp_path):
    narrow, wide = fields["narrow"], fields["wide"]
    fits_path, json_path = save_footprints(tmp_path, narrow, wide, name="lazuli")
    image, header = read_label_image(fits_path)
    assert image.dtype == np.int16 and np.array_equal(image, detector_label_image(narrow, wide))
    assert header["FIELDS"] == "narrow,wide" and header["NOSLICE"] == -1 and header["NBINS"] == 40
    assert header["NSHARED"] == sum(n for f in (narrow, wide) for *_, n in f.overlaps())
    desc = read_outlines(json_path)
    assert desc["format"] == "slicersim-footprints" and [f["field"] for f in desc["fields"]] == ["narrow", "wide"]
    slices = {s["slice_id"]: s for f in desc["fields"] for s in f["slices"]}
    assert sorted(slices) == list(range(1, 117))
    s7 = slices[7]
    assert np.array_equal(np.asarray(s7["outlines"][0]), narrow[7].contour)
    assert s7["npix"] == narrow[7].npix and s7["bbox"] == list(narrow[7].bbox)
    assert np.allclose(s7["trace"]["y"], narrow[7].trace_y, atol=1e-4)
    with pytest.raises(ParameterError, match="exists"):
        save_footprints(tmp_path, narrow, name="lazuli")
    save_footprints(tmp_path, narrow, name="lazuli", overwrite=True)
    assert read_label_image(fits_path)[0][:2048].max() == NO_SLICE       # only the narrow field now
    assert json.loads(open(json_path, encoding="utf-8").read())["fields"][0]["field"] == "narrow"
    with pytest.raises(ParameterError, match="does not exist"):
        save_footprints(tmp_path / "missing", narrow)


# --------------------------------------------------------------------------- published together (review 10 #5, #6)
REPO = Path(__file__).resolve().parents[2]
CHILD = r"""
import os, sys, time
ctl, out, field, mode = sys.argv[1:5]
import numpy as np
from slicersim.instrument.footprints import field_footprints, save_footprints
from slicersim.instrument.mapper import SlicerMapper
m = SlicerMapper.default(table_cache=None)
values = m.values.copy()
values[..., 0] -= 3540.0
values[..., 1] -= 3480.0
small = SlicerMapper(m.slice_ids, m.fieldpos_nodes, m.lbda_nodes, values, detector_shape=(64, 288), table_cache=None)
fp = field_footprints(small, field, np.linspace(9000, 9100, 4), 116, slices=[1, 2])
def flag(name):
    open(os.path.join(ctl, name), "w").close()
def replace_then(pause, only_first=True):
    real, calls = os.replace, []
    def replace(src, dst):
        real(src, dst)
        calls.append(dst)
        if str(dst).startswith(out) and (len(calls) == 1 or not only_first):
            flag("published-one")
            time.sleep(pause)
    os.replace = replace
if mode == "hang-second-fsync":           # killed -9 while the second file is written
    real, calls = os.fsync, []
    def fsync(fd):
        calls.append(fd)
        if len(calls) == 2:
            flag("hanging")
            time.sleep(60)
        real(fd)
    os.fsync = fsync
elif mode == "hang-after-first-rename":   # killed -9 between the renames
    replace_then(60)
elif mode == "slow-renames":              # race: a long pause between the renames
    replace_then(0.5)
flag(f"ready-{field}")
while mode in ("slow-renames", "late") and not os.path.exists(os.path.join(ctl, "go")):
    time.sleep(0.005)
if mode == "late":
    time.sleep(0.15)
save_footprints(out, fp, overwrite=True)
"""


def _start(tmp_path, field, mode):
    ctl = tmp_path / "ctl"
    ctl.mkdir(exist_ok=True)
    (tmp_path / "out").mkdir(exist_ok=True)
    return subprocess.Popen([sys.executable, "-c", CHILD, str(ctl), str(tmp_path / "out"), field, mode],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


@pytest.fixture(scope="module")
def killed(tmp_path_factory, tiny):
    """Two writers killed -9 (started together): one while writing its second file, one
    between its two renames (over a pair of the wide field).  {mode: its directory}."""
    dirs = {mode: tmp_path_factory.mktemp(mode) for mode in ("hang-second-fsync", "hang-after-first-rename")}
    (dirs["hang-after-first-rename"] / "out").mkdir()
    save_footprints(dirs["hang-after-first-rename"] / "out", tiny["wide"])
    procs = {mode: _start(d, "narrow", mode) for mode, d in dirs.items()}
    try:
        _wait_for(dirs["hang-second-fsync"] / "ctl" / "hanging", list(procs.values()))
        _wait_for(dirs["hang-after-first-rename"] / "ctl" / "published-one", list(procs.values()))
    finally:
        for p in procs.values():
            _kill(p)
    return {mode: d / "out" for mode, d in dirs.items()}


def _wait_for(path, procs, timeout=60):
    t0 = time.monotonic()
    while not path.exists():
        if time.monotonic() - t0 > timeout or any(p.poll() is not None for p in procs):
            for p in procs:
                p.kill()
            raise AssertionError(f"{path.name} never appeared: {[p.communicate()[0] for p in procs]}")
        time.sleep(0.01)


def _kill(proc):
    proc.send_signal(signal.SIGKILL)
    proc.wait()                                       # reaped: its pid is dead, not a zombie


def _fields_of_pair(out):
    """(FIELDS of the label image, fields of the outlines) of the pair in ``out``."""
    header = read_label_image(out / "footprints_labels.fits")[1]
    desc = read_outlines(out / "footprints_outlines.json")
    return header["FIELDS"], ",".join(f["field"] for f in desc["fields"])


def tiny_footprints(field, mapper):
    """Slices 1-2 on 3 bins, labelled ``field``, on a 64 × 288 px detector (small files; as CHILD's)."""
    values = mapper.values.copy()
    values[..., 0] -= 3540.0                                   # x, y [px]
    values[..., 1] -= 3480.0
    small = SlicerMapper(mapper.slice_ids, mapper.fieldpos_nodes, mapper.lbda_nodes, values,
                         detector_shape=(64, 288), table_cache=None)
    return field_footprints(small, field, np.linspace(9000, 9100, 4), NCOL, slices=[1, 2])


@pytest.fixture(scope="module")
def tiny(mapper):
    return {f: tiny_footprints(f, mapper) for f in ("narrow", "wide")}


def test_full_disk_or_failed_rename_leaves_neither_file(tiny, tmp_path, monkeypatch):
    real_write, real_replace, files = os.write, os.replace, []

    def write(fd, data):                               # the disk fills up during the second file
        path = os.readlink(f"/proc/self/fd/{fd}")
        if path.startswith(str(tmp_path)) and path not in files:
            files.append(path)
        if path.startswith(str(tmp_path)) and len(files) > 1:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, data)
    with monkeypatch.context() as m:
        m.setattr(os, "write", write)
        with pytest.raises(OSError, match="No space left"):
            save_footprints(tmp_path, tiny["narrow"])
    assert len(files) == 2 and list(tmp_path.iterdir()) == []     # no file, no temporary

    def replace(src, dst):                             # the second rename fails
        if files and str(dst).startswith(str(tmp_path)):
            raise OSError(errno.EIO, "Input/output error")
        files.append(dst)
        return real_replace(src, dst)
    files.clear()
    with monkeypatch.context() as m:
        m.setattr(os, "replace", replace)
        with pytest.raises(OSError, match="Input/output"):
            save_footprints(tmp_path, tiny["wide"], overwrite=True)
    assert [p.name for p in tmp_path.iterdir() if not p.name.endswith(".lock")] == []
    save_footprints(tmp_path, tiny["wide"])
    assert _fields_of_pair(tmp_path) == ("wide", "wide") and len(list(tmp_path.iterdir())) == 2


@pytest.mark.slow
def test_killed_writer_leaves_no_file_and_its_temporaries_are_removed(tiny, killed):
    out = killed["hang-second-fsync"]
    names = [p.name for p in out.iterdir()]
    assert names and all(".tmp-" in n for n in names), names       # temporaries only, no final file
    save_footprints(out, tiny["wide"])                             # no --overwrite needed
    assert sorted(p.name for p in out.iterdir()) == ["footprints_labels.fits", "footprints_outlines.json"]


def test_writer_killed_between_renames_is_completed_by_the_next(tiny, killed):
    out = killed["hang-after-first-rename"]
    with pytest.raises(ParameterError, match="exists"):
        save_footprints(out, tiny["wide"])                         # finishes the killed set first
    assert _fields_of_pair(out) == ("narrow", "narrow")
    assert sorted(p.name for p in out.iterdir()) == ["footprints_labels.fits", "footprints_outlines.json"]


@pytest.mark.slow
def test_concurrent_writers_never_leave_a_mixed_pair(tmp_path):
    """The narrow writer pauses 0.5 s between its two renames; the wide writer starts 0.15 s
    later: without a lock the pair ends up half narrow, half wide."""
    procs = [_start(tmp_path, "narrow", "slow-renames"), _start(tmp_path, "wide", "late")]
    try:
        for field in ("narrow", "wide"):
            _wait_for(tmp_path / "ctl" / f"ready-{field}", procs)
        (tmp_path / "ctl" / "go").touch()
        for p in procs:
            assert p.wait(timeout=60) == 0, p.communicate()[0]
    finally:
        for p in procs:
            if p.poll() is None:
                _kill(p)
    labels, outlines = _fields_of_pair(tmp_path / "out")
    assert labels == outlines
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["footprints_labels.fits",
                                                                    "footprints_outlines.json"]


def test_a_window_wider_than_any_spot_is_refused(mapper):
    """truncate=1e300 made every projection window the whole detector: `footprints` ran for ever."""
    from slicersim.errors import ParameterError
    from slicersim.reduction.rectify_checks import RectifyOptions
    with pytest.raises(ParameterError, match=r"truncate must be in \[0, 100\] \[spot rms\], got 1e\+300"):
        field_footprints(mapper, "narrow", EDGES[:11], NCOL, truncate=1e300)
    with pytest.raises(ParameterError, match=r"truncate \[spot rms\] must be in \(0, 100\], got 1e\+300"):
        RectifyOptions(truncate=1e300)
