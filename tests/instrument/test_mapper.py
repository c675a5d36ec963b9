"""SlicerMapper: optical model on the detector and flux-conserving cube projection.

Tolerances
----------
* Reference traces: the reference's ``trace_xy_pix`` points all lie on
  rectangle edges (fieldpos nodes −1, 0, +1), where every piecewise-linear
  scheme reduces to the same 1-D interpolation: 1e-9 px (measured ~1e-12,
  the rounding of mm → px).  Inside the rectangles bilinear and the
  reference's triangle split differ by up to ~0.06 px (README §3.5.2: the two
  diagonals differ by ≤ 0.10 px): asserted ≤ 0.1 px.
* Flux: every cell's weights are renormalised in float64 from the stored
  weights, so image sums equal cube sums to float64 rounding of ~1e6 terms:
  1e-12 relative (the brief asks ≥ 1e-4, ideally 1e-6).
* OpenCL vs NumPy: same formulas and operation order except FMA contraction
  and summation order (deposit: phases vs bincount): weights atol 1e-12,
  images 1e-12 of the image maximum.  Repeated OpenCL runs are bit-identical
  (no atomics: items of one launch never share a pixel).
* Inverse map: Newton to 1e-9 px; round trip asserted at 1e-6 px.
* Box model: centroid of a single-cell image = box centre to 1e-4 px (the
  window is symmetric to a pixel) and = forward map at the cell centre to
  1e-3 px (map curvature inside a 1 px cell is ~1e-5 px); second
  moments = box²/12 + σ² + 1/12 (pixelisation) to 1 % (4σ truncation and
  Sheppard's correction are ~1e-3 effects).
"""

import numpy as np
import pytest

from conftest import missing_reference
from slicersim.backends import projection as cp
from slicersim.instrument.mapper import SlicerMapper, detector_rate_image

BACKENDS = ["numpy", pytest.param("opencl", marks=pytest.mark.needs_opencl)]

def cbe_grid():
    """The built-in CBE wavelength grid (510 bins, ~1 px each on the default layout)."""
    from slicersim.io.config import builtin_config_dir
    from slicersim.io.curves import read_curve
    from slicersim.instrument.spectrograph import wavelength_grid_from_dispersion
    lam, cols = read_curve(f"{builtin_config_dir()}/dispersion_prism.ecsv")
    return wavelength_grid_from_dispersion(lam, next(iter(cols.values())), (4000, 17000), 1.3, 2.3)


_LBDA, _EDGES = cbe_grid()
LBDA, EDGES = _LBDA[200:240], _EDGES[200:241]     # 40 real bins: realistic cells, fast tables


@pytest.fixture(scope="module")
def mapper():
    return SlicerMapper.default()


@pytest.fixture(scope="module")
def spot_mapper():
    """1.2-px spots applied in full: a cell's light is smooth on the pixel grid (centroids and
    the box model are then exact to ~1e-4 px)."""
    from conftest import wide_spot_mapper
    return wide_spot_mapper()


@pytest.fixture(scope="module")
def ref(refdir):
    if not (refdir / "detector" / "sn_z1.00_cbe_detector.npz").is_file():
        missing_reference("reference detector products (../shared/reference/detector)")
    return refdir, dict(np.load(refdir / "detector" / "sn_z1.00_cbe_detector.npz"))


# --------------------------------------------------------------------------- reference optical model
@pytest.mark.parametrize("interpolation", ["bilinear", "triangles"])
def test_reference_traces(ref, interpolation):
    path, d = ref
    m = SlicerMapper.from_table(path / "config" / "mapping_spotdata.csv", interpolation=interpolation,
                                face_diagonal=d["mapper_face_diagonal"] if interpolation == "triangles" else None)
    assert np.array_equal(m.fieldpos_nodes, d["mapper_fieldpos_nodes"])
    np.testing.assert_allclose(m.lbda_nodes, d["mapper_lbda_nodes_AA"], rtol=1e-14)
    s = m.slice_ids[:, None, None]
    px, py = m.forward(s, d["trace_fieldpos"][None, :, None], d["trace_lbda_AA"][None, None, :])
    err = np.hypot(px - d["trace_xy_pix"][..., 0], py - d["trace_xy_pix"][..., 1])
    assert err.max() < 1e-9, err.max()


def test_reference_bilinear_close_to_triangles(ref):
    path, d = ref
    table = path / "config" / "mapping_spotdata.csv"
    bil = SlicerMapper.from_table(table)
    tri = SlicerMapper.from_table(table, interpolation="triangles", face_diagonal=d["mapper_face_diagonal"])
    rng = np.random.default_rng(5)
    s, phi, lam = rng.integers(1, 117, 50000), rng.uniform(-1, 1, 50000), rng.uniform(3500, 17002, 50000)
    dist = np.hypot(*(np.array(bil.forward(s, phi, lam)) - np.array(tri.forward(s, phi, lam))))
    assert 0.01 < dist.max() <= 0.1                        # interior: different, but within 0.1 px
    on_edge = np.hypot(*(np.array(bil.forward(s, 0.5, lam)) - np.array(tri.forward(s, 0.5, lam))))
    assert on_edge.max() < 1e-9


def test_reference_table_projection_conserves_flux(ref):
    path, d = ref
    m = SlicerMapper.from_table(path / "config" / "mapping_spotdata.csv")
    lbda = d["lbda_AA"][100:140]
    edges = np.concatenate([[1.5 * lbda[0] - 0.5 * lbda[1]], 0.5 * (lbda[1:] + lbda[:-1]),
                            [1.5 * lbda[-1] - 0.5 * lbda[-2]]])
    cube = np.random.default_rng(2).uniform(0, 1, (lbda.size, 58, 116))
    img = m.project_cube(cube, lbda, edges, slices="wide")
    assert img.sum() == pytest.approx(cube.sum(), rel=1e-12)
    rows = np.flatnonzero(img.sum(axis=1))
    assert rows.min() > 100 and rows.max() < 2048          # the reference's wide field: bottom half


# --------------------------------------------------------------------------- default layout
def test_default_layout(mapper):
    assert mapper.slice_ids.tolist() == list(range(1, 117))
    lam = np.linspace(3990, 17010, 200)
    phi = np.linspace(-1, 1, 9)
    grid = mapper.forward_grid(mapper.slice_ids, phi, lam)            # (116, 2, λ, φ)
    px, py = grid[:, 0], grid[:, 1]
    assert py[:58].min() > 2048 + 200 and py[58:].max() < 2048 - 200   # narrow top, wide bottom
    assert px.min() > 200 and px.max() < 4096 - 200
    assert np.all(np.diff(py, axis=1) < 0)                             # dispersion towards -y
    assert np.all(np.diff(px, axis=2) < 0)                             # fieldpos -1 -> +1 towards -x
    length = px[:, :, 0] - px[:, :, -1]
    assert 0.9 * 116 - 1 < length.min() and length.max() < 116 + 1
    bins = -np.diff(mapper.forward(1, 0.0, [4000.0, 17000.0])[1])[0]
    # the spot table's dispersion (px from 4000 to 17000 Å) against the CBE grid built from the
    # independent dispersion law (dispersion_prism.ecsv × 1.3 × 2.3/2): ~1 px per bin, to 1 %
    assert bins == pytest.approx(_LBDA.size - 1, rel=0.01)
    sx, sy = mapper.spot_rms(mapper.slice_ids[:, None], 0.0, np.array([4000.0, 17000.0]))
    # the optics' aberration, 2.0–5.3 µm, growing with λ, within the budget the CBE cubes carry
    assert 0.19 < sx.min() and sy.max() < 0.531 and np.all(sx[:, 1] > sx[:, 0])
    assert max(sx.max(), sy.max()) <= mapper.cube_blur_px[0] == pytest.approx(0.5 * np.sqrt(2.3**2 - 4))
    pitch = np.diff(mapper.forward(np.arange(1, 30), 0.0, 10000.0)[0])
    assert np.all((pitch > -125) & (pitch < -115))


def test_inverse_round_trip(mapper):
    rng = np.random.default_rng(11)
    n = 3000
    s, phi, lam = rng.integers(1, 117, n), rng.uniform(-1, 1, n), rng.uniform(4000, 17000, n)
    px, py = mapper.forward(s, phi, lam)
    s2, phi2, lam2 = mapper.inverse(px, py)
    assert np.array_equal(s2, s)
    np.testing.assert_allclose(phi2, phi, atol=1e-9)
    np.testing.assert_allclose(lam2, lam, rtol=1e-9)
    bx, by = mapper.forward(s2, phi2, lam2)
    assert np.hypot(bx - px, by - py).max() < 1e-6
    # pixel centres of a trace, with the slice given
    pcx, pcy = np.floor(px[:50]) + 0.5, np.floor(py[:50]) + 0.5
    s3, phi3, lam3 = mapper.inverse(pcx, pcy, slice_id=s[:50])
    ok = s3 > 0                                   # pixel centres beyond a slice end are off the trace
    assert ok.mean() > 0.9
    bx, by = mapper.forward(s3[ok], phi3[ok], lam3[ok])
    assert np.hypot(bx - pcx[ok], by - pcy[ok]).max() < 1e-6
    # off every trace: corner, between two tiers
    s4, phi4, _ = mapper.inverse([5.0, 2048.0], [5.0, 3072.0])
    assert s4.tolist() == [0, 0] and np.isnan(phi4).all()


# --------------------------------------------------------------------------- projection physics
@pytest.mark.parametrize("backend", BACKENDS)
def test_flux_conservation_total_and_per_slice(mapper, backend):
    rng = np.random.default_rng(3)
    narrow = rng.uniform(0, 2, (EDGES.size - 1, 58, 116))
    wide = rng.uniform(0, 2, (EDGES.size - 1, 58, 116))
    img = mapper.project_fields(LBDA, EDGES, narrow=narrow, wide=wide, backend=backend)
    assert img.sum() == pytest.approx(narrow.sum() + wide.sum(), rel=1e-12)
    assert img[:2048].sum() == pytest.approx(wide.sum(), rel=1e-12)     # fields on their halves
    for row in (0, 28, 29, 57):                                         # slices 58, 30, 29, 1
        one = np.zeros_like(narrow)
        one[:, row] = narrow[:, row]
        img1 = mapper.project_cube(one, LBDA, EDGES, "narrow", backend=backend)
        assert img1.sum() == pytest.approx(narrow[:, row].sum(), rel=1e-12)
        yy, xx = np.nonzero(img1)                                       # row r <-> slice 58 - r
        w = img1[yy, xx] / img1.sum()
        px, py = mapper.forward(58 - row, 0.0, LBDA.mean())
        assert abs((w * xx).sum() + 0.5 - px) < 3 and abs((w * yy).sum() + 0.5 - py) < 3


def test_delta_cube_lands_on_forward_map(spot_mapper):
    """One cell, one bin of the real grid (one slice projected): position and spread."""
    mapper = spot_mapper
    lbda, edges = _LBDA, _EDGES
    i, k, s = 300, 40, 38
    cube = np.zeros((lbda.size, 1, 116))
    cube[i, 0, k] = 1.0
    img = mapper.project_cube(cube, lbda, edges, [s])
    assert img.sum() == pytest.approx(1.0, rel=1e-12)
    phi_c, lam_c = -1 + 2 * (k + 0.5) / 116, 0.5 * (edges[i] + edges[i + 1])
    px, py = mapper.forward(s, phi_c, lam_c)
    yy, xx = np.nonzero(img)
    w = img[yy, xx]
    cx, cy = (w * (xx + 0.5)).sum(), (w * (yy + 0.5)).sum()
    ax, bx, sx, ay, by, sy = mapper.cell_boxes([s], 116, edges)[i * 116 + k]
    assert abs(cx - 0.5 * (ax + bx)) < 1e-4 and abs(cy - 0.5 * (ay + by)) < 1e-4
    assert abs(cx - px) < 1e-3 and abs(cy - py) < 1e-3
    rmsx, rmsy = mapper.spot_rms(s, phi_c, lam_c)
    assert sx == pytest.approx(rmsx, rel=1e-3) and sy == pytest.approx(rmsy, rel=1e-3)   # shear tiny
    var_x = (w * (xx + 0.5 - cx) ** 2).sum() - 1 / 12
    var_y = (w * (yy + 0.5 - cy) ** 2).sum() - 1 / 12
    assert var_x == pytest.approx((bx - ax) ** 2 / 12 + sx**2, rel=0.01)
    assert var_y == pytest.approx((by - ay) ** 2 / 12 + sy**2, rel=0.01)
    assert 0.9 < by - ay < 1.1 and 0.8 < bx - ax < 1.0      # a bin ~1 px tall, a column ~0.9 px wide
    assert xx.min() >= np.floor(ax - 4 * sx) and xx.max() <= np.floor(bx + 4 * sx)   # ±4σ window
    assert yy.min() >= np.floor(ay - 4 * sy) and yy.max() <= np.floor(by + 4 * sy)


@pytest.mark.slow
def test_box_model_matches_oversampled_cells(spot_mapper):
    mapper = spot_mapper
    """One box per cell vs 3×3 sub-cells on real 1-px bins: the box model needs no sub-sampling."""
    lbda, edges = _LBDA, _EDGES
    slices = [1, 29, 30, 87, 88, 116]
    for lo in (0, 480):                                   # blue (strongest curvature) and red ends
        lam, e = lbda[lo:lo + 25], edges[lo:lo + 26]
        cube = np.random.default_rng(lo).uniform(0.5, 1.5, (25, len(slices), 116))
        img1 = mapper.project_cube(cube, lam, e, slices)
        img3 = mapper.project_cube(cube, lam, e, slices, oversample=(3, 3))
        assert img3.sum() == pytest.approx(cube.sum(), rel=1e-12)
        assert np.abs(img3 - img1).max() < 5e-3 * img1.max()     # measured 1.5e-3


def test_exact_area_overlap_without_blur():
    box = np.array([[2.25, 3.75, 0.0, 10.5, 10.5, 0.0]])            # x: box, no blur; y: a point
    t = cp.build_tables(box, (1, 1, 1), detector_shape=(32, 32), weights_dtype=np.float64, backend="numpy")
    img = cp.deposit(np.ones((1, 1, 1)), t, backend="numpy")
    np.testing.assert_array_equal(np.nonzero(img), ([10, 10], [2, 3]))
    np.testing.assert_allclose(img[10, 2:4], [0.5, 0.5], rtol=0, atol=1e-15)


def test_projection_tables_refuse_bad_arguments_naming_them():
    """Bad arguments of the projection backend are ParameterErrors naming the argument (they were bare
    ValueError / TypeError)."""
    from slicersim.backends.projection_transpose import gather, matrix_entries
    from slicersim.errors import ParameterError
    box = np.array([[2.25, 3.75, 0.0, 10.5, 10.5, 0.0]])
    t = cp.build_tables(box, (1, 1, 1), detector_shape=(32, 32), weights_dtype=np.float64, backend="numpy")
    cases = [(lambda: cp.build_tables(box[:, :5], (1, 1, 1), detector_shape=(32, 32), backend="numpy"), "box"),
             (lambda: cp.build_tables(box[:, [1, 0, 2, 3, 4, 5]], (1, 1, 1), detector_shape=(32, 32),
                                      backend="numpy"), "box"),
             (lambda: cp.build_tables(box, (1, 1, 1), detector_shape=(32, 32), weights_dtype=np.int16,
                                      backend="numpy"), "weights_dtype"),
             (lambda: cp.deposit(np.ones((2, 1, 1)), t, backend="numpy"), "value must have shape"),
             (lambda: cp.deposit(np.ones((1, 1, 1)), t, out=np.zeros((3, 3)), backend="numpy"), "out must be"),
             (lambda: gather(np.zeros((31, 32)), t, backend="numpy"), "image must be a real array of shape"),
             (lambda: gather(np.zeros((32, 32)), t, power=3, backend="numpy"), "unknown power 3"),
             (lambda: matrix_entries(t, 0, 5), r"last \(sub-cell\) must be an integer in \[0, 1\], got 5")]
    for call, message in cases:
        with pytest.raises(ParameterError, match=message):
            call()


@pytest.mark.parametrize("backend", ["numpy", "opencl"])
def test_gather_of_the_tables_band_equals_gather_of_the_detector(backend):
    """gather(band=True) takes only the rows the tables reach (the forward fit's white light works on a
    field's band, 37 % of the Lazuli detector for the narrow field): the same cube values bit for bit,
    and a band of the wrong height is refused naming the rows."""
    from slicersim.backends.projection_transpose import gather
    from slicersim.errors import ParameterError
    box = np.array([[2.25, 3.75, 0.0, 10.5, 10.5, 0.8], [5.0, 9.0, 0.5, 20.0, 22.0, 0.6]])
    t = cp.build_tables(box, (1, 2, 1), detector_shape=(32, 32), weights_dtype=np.float64, backend="numpy")
    r0, r1 = t.row_range
    assert 0 < r0 < r1 < 32
    img = np.random.default_rng(2).normal(size=(32, 32))
    full = gather(img, t, backend=backend)
    np.testing.assert_array_equal(gather(img[r0:r1], t, backend=backend, band=True), full)
    with pytest.raises(ParameterError, match=f"rows {r0}:{r1}"):
        gather(img, t, backend=backend, band=True)


def test_blurred_box_weights_against_quadrature():
    from scipy.integrate import quad
    from scipy.special import erf
    a, b, s, c0, n = 3.3, 4.45, 0.7, 0, 9
    w = cp.box_weights_numpy([a], [b], [s], [c0], [n], n)[0]
    dens = lambda x: 0.5 * (erf((x - a) / (np.sqrt(2) * s)) - erf((x - b) / (np.sqrt(2) * s))) / (b - a)
    exact = [quad(dens, c, c + 1, epsabs=1e-14)[0] for c in range(c0, c0 + n)]
    np.testing.assert_allclose(w, exact, rtol=0, atol=1e-11)


def test_detector_rate_image(mapper):
    narrow = np.full((EDGES.size - 1, 58, 116), 0.01)
    img = detector_rate_image(mapper, LBDA, EDGES, narrow=narrow, dark=2.8e-3, thermal_dark=1e-3,
                              roic_glow=3e-3, tframe=2.83)
    floor = 2.8e-3 + 1e-3 + 3e-3 / 2.83
    assert img[5, 5] == pytest.approx(floor, rel=1e-12)             # unpainted pixels: dark only
    assert img.sum() == pytest.approx(narrow.sum() + floor * img.size, rel=1e-12)
    with pytest.raises(ValueError, match="tframe"):
        detector_rate_image(mapper, LBDA, EDGES, narrow=narrow, roic_glow=3e-3)


def test_bad_input(mapper):
    cube = np.ones((EDGES.size - 1, 58, 116))
    with pytest.raises(ValueError, match="shape"):
        mapper.project_cube(cube[:, :57], LBDA, EDGES)
    with pytest.raises(ValueError, match="bracket"):
        mapper.project_cube(cube, LBDA[::-1], EDGES)
    bad = cube.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        mapper.project_cube(bad, LBDA, EDGES)
    with pytest.raises(ValueError, match="unknown slice"):
        mapper.forward(117, 0.0, 5000.0)
    with pytest.raises(ValueError, match="exactly once"):
        SlicerMapper.from_table(np.array([[1, -1, 0.4, 0, 0, 1, 1], [1, 1, 0.4, 0, 0, 1, 1],
                                          [1, -1, 0.5, 0, 0, 1, 1]]))


def test_a_spot_table_that_is_not_a_regular_file_is_refused_before_opening(tmp_path):
    import os
    import threading

    from slicersim.errors import ConfigError
    fifo = tmp_path / "spots.txt"
    os.mkfifo(fifo)
    caught = []

    def read():
        try:
            SlicerMapper.from_table(str(fifo))
        except ConfigError as exc:
            caught.append(str(exc))
    thread = threading.Thread(target=read, daemon=True)
    thread.start()
    thread.join(30)
    assert not thread.is_alive(), "blocked on a FIFO"
    assert caught == [f"spot table: {fifo} is not a regular file"]


# --------------------------------------------------------------------------- kernels vs NumPy twins
def _random_boxes(rng, n, shape):
    """Odd-sized random boxes, some unblurred, some points, some across or beyond the detector edge."""
    H, W = shape
    ax = rng.uniform(-6, W + 3, n)
    ay = rng.uniform(-6, H + 3, n)
    box = np.stack([ax, ax + rng.uniform(0, 1.6, n), rng.uniform(0, 2.2, n),
                    ay, ay + rng.uniform(0, 3.1, n), rng.uniform(0, 1.7, n)], axis=1)
    box[::7, 2] = 0.0
    box[::5, 5] = 0.0
    box[::11, 1] = box[::11, 0]
    return box


@pytest.mark.needs_opencl
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_tables_opencl_vs_numpy(dtype):
    rng = np.random.default_rng(7)
    grid, shape = (3, 14, 11), (61, 75)
    box = _random_boxes(rng, np.prod(grid), shape)
    kw = dict(detector_shape=shape, weights_dtype=dtype, block=3)
    tn = cp.build_tables(box, grid, backend="numpy", **kw)
    to = cp.build_tables(box, grid, backend="opencl", **kw).host()
    assert np.array_equal(tn.meta, to.meta) and np.array_equal(tn.offset, to.offset)
    atol = 1e-12 if dtype == np.float64 else 1e-7                  # float32: one ulp of a weight ≤ 1
    np.testing.assert_allclose(to.pool, tn.pool, rtol=0, atol=atol)
    np.testing.assert_allclose(to.scale, tn.scale, rtol=1e-12 if dtype == np.float64 else 1e-6)
    sums_x = [tn.pool[o:o + nx].astype(float).sum() for o, nx in zip(tn.offset, tn.meta[:, 2])]
    assert np.all(np.array(sums_x) > 0.99)                         # ±4σ windows hold ≥ 99 % before renormalising


@pytest.mark.needs_opencl
@pytest.mark.parametrize("oversample,vw", [((1, 1), 8), ((2, 3), 4), ((3, 1), 1)])
def test_deposit_opencl_vs_numpy(oversample, vw):
    rng = np.random.default_rng(8)
    ne, nq = oversample
    grid, shape = (3, 9 * ne, 13 * nq), (67, 53)
    box = _random_boxes(rng, np.prod(grid), shape)
    t = cp.build_tables(box, grid, oversample, detector_shape=shape, weights_dtype=np.float64, vw=vw,
                        block=2, backend="numpy")
    value = rng.normal(size=(3, 9, 13))
    value[1, 4] = 0.0
    img_n = cp.deposit(value, t, backend="numpy")
    img_o = cp.deposit(value, t, backend="opencl")
    np.testing.assert_allclose(img_o, img_n, rtol=0, atol=1e-12 * np.abs(img_n).max())
    again = cp.deposit(value, t, backend="opencl")
    assert np.array_equal(again, img_o)                            # deterministic, bit for bit
    inside = (box[:, 1] + 4 * box[:, 2] < shape[1] - 1) & (box[:, 0] - 4 * box[:, 2] > 0) \
        & (box[:, 4] + 4 * box[:, 5] < shape[0] - 1) & (box[:, 3] - 4 * box[:, 5] > 0)
    assert 0 < inside.sum() < inside.size                          # some cells lose flux off the edge
    only_inside = np.where(inside.reshape(grid)[:, ::ne, ::nq], value, 0.0)   # parents fully inside
    only_inside *= inside.reshape(3, 9, ne, 13, nq).all(axis=(2, 4))
    for backend in ("numpy", "opencl"):
        assert cp.deposit(only_inside, t, backend=backend).sum() == pytest.approx(only_inside.sum(), rel=1e-12)
    out = np.ones(shape)
    cp.deposit(value, t, out=out, backend="opencl")                # accumulates into `out`
    np.testing.assert_allclose(out - 1.0, img_o, rtol=0, atol=1e-12 * np.abs(img_n).max())


@pytest.mark.needs_opencl
def test_project_cube_opencl_vs_numpy():
    """Whole path (tables + deposit) with each backend, on a few slices of the real grid."""
    lbda, edges = _LBDA, _EDGES
    slices = [31, 89]
    cube = np.random.default_rng(9).uniform(0, 1, (lbda.size, len(slices), 116))
    img_n = SlicerMapper.default().project_cube(cube, lbda, edges, slices, backend="numpy")
    img_o = SlicerMapper.default().project_cube(cube, lbda, edges, slices, backend="opencl")
    assert img_n.sum() == pytest.approx(cube.sum(), rel=1e-12)
    np.testing.assert_allclose(img_o, img_n, rtol=0, atol=1e-12 * img_n.max())


@pytest.mark.parametrize("i", [5, 150, 300, 505])
def test_projection_does_not_blur_the_cube_twice(i):
    """The cubes' LSF and spatial blur already hold the optics' aberration (σ_ab = √(dr² − 4)/2 =
    0.568 px for the CBE dr = 2.3), and the default table's spots (≤ 0.53 px) lie within it: its
    projection of one cell of one bin is exactly that of a layout without spots (only the cell
    box and the pixels), while the table's spots applied in full (cube_blur_px=0, the double
    count this guards against) widen the line along the dispersion."""
    from slicersim.instrument.mapper import aberration_sigma_px
    lbda, edges = _LBDA, _EDGES
    k, s = 58, 38
    cube = np.zeros((lbda.size, 1, 116))
    cube[i, 0, k] = 1.0
    single = SlicerMapper.default(table_cache=None)
    assert single.cube_blur_px[1] == pytest.approx(aberration_sigma_px(2.3)) == pytest.approx(0.5679, abs=1e-4)
    nospot = SlicerMapper.default(table_cache=None, cube_blur_px=10.0)
    twice = SlicerMapper.default(table_cache=None, cube_blur_px=0.0)

    def rms_along_dispersion(img):
        yy, xx = np.nonzero(img)
        w = img[yy, xx] / img.sum()
        cy = (w * yy).sum()
        return float(np.sqrt((w * (yy - cy) ** 2).sum()))
    img = single.project_cube(cube, lbda, edges, [s])
    np.testing.assert_array_equal(img, nospot.project_cube(cube, lbda, edges, [s]))
    wider = rms_along_dispersion(twice.project_cube(cube, lbda, edges, [s])) - rms_along_dispersion(img)
    assert wider > 0.02, wider
