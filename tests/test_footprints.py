"""Detector footprints of the slices (slicersim.instrument.footprints) and their files.

The reference for "which pixels receive light" is the projection itself: a uniform cube
(and one-slice cubes) projected with SlicerMapper.project_cube on a 40-bin piece of the
CBE grid.  Footprints must give exactly its lit pixels (the windows are the projection's).
"""
import json

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
    return SlicerMapper.default(table_cache=None)


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
    assert lit.sum() == 337336                                   # the measured count: non-trivial
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
