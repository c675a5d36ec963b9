"""Rectification (slicersim.reduction.rectify) and the transposed projection it uses.

Tolerances
----------
* gather (Pᵀ) OpenCL vs NumPy, and the adjoint identity ⟨P v, y⟩ = ⟨v, Pᵀ y⟩: same
  formulas, different summation order: 1e-12 relative (measured ~1e-16).
* Noiseless LSQ recovery: the cube comes back to κ(P)·ε; on the grids used here κ₁(PᵀWP) ≤
  ~7e4 (2-px bins, 58 or 29 columns), measured errors 1e-15 … 1e-13 of the peak; asserted
  1e-10 of the peak (the acceptance goal).
* Pulls: width measured over all cells and realisations; its Monte Carlo error is the
  realisation-to-realisation scatter of the mean squared pull (neighbouring cells are
  correlated, so cells are not independent draws) — asserted |width − 1| < 0.05 and within
  5 of those errors.
* Flux: Σ cube = Σ model image (lsq) and Σ cube = Σ image over the footprint (drizzle) to
  1e-12 relative (float64 sums of ~1e5 terms).
"""
import numpy as np
import pytest
from conftest import SMALL_EDGES, small_raw_ramps
from conftest import have_opencl, small_slicer_mapper, wide_spot_mapper

from slicersim.backends import projection as cp
from slicersim.backends.projection_transpose import gather, matrix_entries
from slicersim.errors import ParameterError
from slicersim.instrument.mapper import SlicerMapper
from slicersim.io.config import builtin_config_dir
from slicersim.io.curves import read_curve
from slicersim.instrument.spectrograph import wavelength_grid_from_dispersion
from slicersim.reduction.rectify import rectify
from slicersim.reduction.spectra import extract_spectrum
from slicersim.reduction.rectify import noise_information
from test_gls_extraction import EDGES as EDGES_GLS, NCOL as NCOL_GLS, noisy_scene
from slicersim.reduction.spectra import propagate_variance


def _cbe_grid():
    lam, cols = read_curve(f"{builtin_config_dir()}/dispersion_prism.ecsv")
    return wavelength_grid_from_dispersion(lam, next(iter(cols.values())), (4000, 17000), 1.3, 2.3)


_, _EDGES = _cbe_grid()                      # 510 bins of ~1 px on the default layout
BLUE = _EDGES[200:213:2]                     # 6 bins of 2 px (blue: spot σ ~ 1 px)
RED = _EDGES[480:493:2]                      # 6 bins of 2 px (red: spot σ ~ 1.4 px, the worst κ)


@pytest.fixture(scope="module")
def mapper():
    return SlicerMapper.default(table_cache=None)


@pytest.fixture(scope="module")
def small():
    """The small test layout (conftest.small_slicer_mapper)."""
    return small_slicer_mapper()


SMALL = np.linspace(9050.0, 9950.0, 13)     # 12 bins of 5 px on the small layout


def _centres(edges):
    return 0.5 * (edges[1:] + edges[:-1])


def _truth(rng, edges, ncol):
    """Smooth continuum × random structure, plus a point-like bright cell: peak ~ 5."""
    cube = rng.uniform(0.5, 1.5, (edges.size - 1, 58, ncol))
    cube[:, 20, ncol // 3] += 3.0
    return cube


# --------------------------------------------------------------------------- transpose projection
def _random_tables(rng, grid, oversample, shape, dtype, vw):
    H, W = shape
    n = int(np.prod(grid))
    ax, ay = rng.uniform(-3, W + 1, n), rng.uniform(-3, H + 1, n)
    box = np.stack([ax, ax + rng.uniform(0, 2, n), rng.uniform(0, 1.5, n),
                    ay, ay + rng.uniform(0, 2, n), rng.uniform(0, 1.5, n)], axis=1)
    return cp.build_tables(box, grid, oversample, detector_shape=shape, weights_dtype=dtype, vw=vw, block=3,
                           backend="numpy")


@pytest.mark.parametrize("oversample,vw,dtype", [((1, 1), 4, np.float64), ((1, 1), 16, np.float32),
                                                  ((2, 3), 8, np.float32), ((1, 1), 1, np.float64)])
def test_gather_is_the_transpose(oversample, vw, dtype):
    rng = np.random.default_rng(sum(oversample) + vw)
    ne, nq = oversample
    shape = (67, 53)
    t = _random_tables(rng, (3, 9 * ne, 13 * nq), oversample, shape, dtype, vw)
    v, img = rng.uniform(-1, 1, (3, 9, 13)), rng.uniform(-1, 1, shape)
    dep = cp.deposit(v, t, backend="numpy")
    backends = ["numpy"] + (["opencl"] if have_opencl() else [])
    for be in backends:
        g = gather(img, t, backend=be)
        assert (v * g).sum() == pytest.approx((dep * img).sum(), rel=1e-12, abs=1e-12)
    pix, cell, w = matrix_entries(t, 0, t.ncell)                     # explicit P: P v = deposit(v)
    Pv = np.bincount(pix, weights=w * v.ravel()[cell], minlength=img.size).reshape(shape)
    assert np.abs(Pv - dep).max() < 1e-12 * np.abs(dep).max()
    if oversample == (1, 1):                                          # squared weights: (P∘P)ᵀ y
        expect = np.bincount(cell, weights=w * w * img.ravel()[pix], minlength=v.size).reshape(v.shape)
        assert np.abs(gather(img, t, power=2, backend="numpy") - expect).max() < 1e-13
    else:
        with pytest.raises(ValueError, match="oversample"):
            gather(img, t, power=2)


@pytest.mark.needs_opencl
def test_gather_opencl_matches_numpy_twin(mapper):
    t = mapper.projection_tables([3, 4, 31], 58, BLUE)
    img = np.random.default_rng(4).uniform(0, 1, mapper.detector_shape)
    for power in (1, 2):
        a, b = gather(img, t, power, backend="opencl"), gather(img, t, power, backend="numpy")
        assert np.abs(a - b).max() < 1e-12 * np.abs(b).max()
        assert np.array_equal(a, gather(img, t, power, backend="opencl"))       # bit-identical reruns


# --------------------------------------------------------------------------- exact LSQ
@pytest.mark.slow
@pytest.mark.parametrize("edges,ncol,spots", [(BLUE, 58, "default"), (RED, 58, "default"), (RED, 58, "wide")])
def test_noiseless_lsq_returns_the_truth_both_fields(mapper, edges, ncol, spots):
    """Default layout (no projection blur beyond the cube's: slices share no pixel) and 1.2-px
    spots applied in full (slices share tail pixels, left out of the fit)."""
    if spots == "wide":
        mapper = wide_spot_mapper(table_cache=None)
    rng = np.random.default_rng(1)
    lbda = _centres(edges)
    narrow, wide = _truth(rng, edges, ncol), _truth(rng, edges, ncol)
    img = mapper.project_fields(lbda, edges, narrow=narrow, wide=wide)
    out = rectify(img, mapper=mapper, field="both", lbda=lbda, lbda_edges=edges, ncol=ncol)
    for name, truth in (("narrow", narrow), ("wide", wide)):
        p = out[name]
        assert p.flux.shape == truth.shape and p.variance is None and p.field == name
        err = np.abs(p.flux - truth).max() / truth.max()
        print(f"{name}: max |cube − truth| / peak = {err:.2e}, κ₁(PᵀP) ≤ {p.diagnostics['cond1_normal_max']:.3g}")
        assert err < 1e-10, (name, err)
        d = p.diagnostics
        assert d["gradient_rel"][0] < 1e-12 and d["chi2"][0] < 1e-20
        if spots == "wide":                                  # slices do share tail pixels
            assert d["pixels_shared"] > 0 and 0 < d["excluded_flux_max"] < 1
        model = mapper.project_cube(p.flux, lbda, edges, name)
        assert p.flux.sum() == pytest.approx(model.sum(), rel=1e-12)          # flux-conserving
        assert p.wcs["slice_of_row"][0] == (58 if name == "narrow" else 116)
        np.testing.assert_array_equal(p.lbda_edges, edges)


@pytest.mark.slow
def test_noiseless_lsq_weighted_with_bad_pixels_numpy(small):
    """Weights, unusable pixels (NaN rate, infinite variance) and the NumPy backend."""
    rng = np.random.default_rng(2)
    edges, ncol, mapper = SMALL, 24, small
    lbda = _centres(edges)
    narrow = _truth(rng, edges, ncol)
    img = mapper.project_fields(lbda, edges, narrow=narrow)
    var = 0.01 + 0.02 * img
    rows, cols = np.nonzero(img > 0.05 * img.max())
    pick = rng.choice(rows.size, 200, replace=False)
    img[rows[pick], cols[pick]] = np.nan
    var[rows[pick], cols[pick]] = np.inf
    p = rectify(img, var, mapper=mapper, field="narrow", lbda=lbda, lbda_edges=edges, ncol=ncol, backend="numpy")
    assert np.abs(p.flux - narrow).max() < 1e-10 * narrow.max()
    assert np.all(np.isfinite(p.variance)) and np.all(p.variance > 0)
    with pytest.raises(ParameterError, match="variance=\\+inf"):
        rectify(img, mapper=mapper, field="narrow", lbda=lbda, lbda_edges=edges, ncol=ncol)


@pytest.mark.slow
def test_oversampled_projection_and_stack(small):
    """Sub-cells (oversample) enter P as their sum; a stack gives each image's own answer."""
    rng = np.random.default_rng(5)
    edges, ncol, mapper = SMALL, 16, small
    lbda = _centres(edges)
    a, b = _truth(rng, edges, ncol), _truth(rng, edges, ncol)
    imgs = np.stack([mapper.project_fields(lbda, edges, wide=c, oversample=(2, 3)) for c in (a, b)])
    kw = dict(mapper=mapper, field="wide", lbda=lbda, lbda_edges=edges, ncol=ncol, oversample=(2, 3))
    p = rectify(imgs, **kw)
    assert p.flux.shape == (2,) + a.shape
    assert np.abs(p.flux[0] - a).max() < 1e-10 * a.max() and np.abs(p.flux[1] - b).max() < 1e-10 * b.max()
    np.testing.assert_allclose(rectify(imgs[1], **kw).flux, p.flux[1], rtol=0, atol=1e-13 * b.max())
    with pytest.raises(ParameterError, match="oversample"):
        rectify(imgs[0], np.ones(imgs[0].shape), method="drizzle", **kw)


def test_native_grid_is_refused_by_lsq(mapper):
    """116 columns of ~0.9 px across a ~105 px slice: more cells than pixels, P singular."""
    edges = _EDGES[200:206]
    img = mapper.project_fields(_centres(edges), edges, narrow=np.ones((5, 58, 116)))
    with pytest.raises(ParameterError, match="singular|condition"):
        rectify(img, mapper=mapper, field="narrow", lbda_edges=edges, ncol=116)


# --------------------------------------------------------------------------- noise
def _pull_width(pulls):
    """Width sqrt(<pull²>) and its Monte Carlo error from the scatter between realisations."""
    per = (pulls ** 2).reshape(pulls.shape[0], -1).mean(axis=1)
    mean = per.mean()
    return np.sqrt(mean), 0.5 * per.std(ddof=1) / np.sqrt(per.size) / np.sqrt(mean)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["lsq", "drizzle"])
def test_variance_pulls(small, method):
    rng = np.random.default_rng(7)
    mapper, edges, ncol, nreal = small, SMALL, 24, 40
    lbda = _centres(edges)
    truth = _truth(rng, edges, ncol)
    model = mapper.project_fields(lbda, edges, narrow=truth)
    var = 0.05 + 0.1 * model                                  # read-noise floor + shot noise [(e-/s)²]
    noisy = model + np.sqrt(var) * rng.standard_normal((nreal,) + model.shape)
    kw = dict(mapper=mapper, field="narrow", lbda=lbda, lbda_edges=edges, ncol=ncol, method=method)
    p = rectify(noisy, var, **kw)
    centre = truth if method == "lsq" else rectify(model, var, **kw).flux     # drizzle is biased: its mean
    pulls = (p.flux - centre) / np.sqrt(p.variance)
    width, err = _pull_width(pulls)
    print(f"{method}: pull width {width:.4f} ± {err:.4f}, mean {pulls.mean():+.4f}")
    assert abs(width - 1) < 0.05 and abs(width - 1) < 5 * err + 1e-3, (width, err)
    bias = pulls.mean(axis=0)                                 # per cell, over the realisations
    assert abs(bias.mean()) < 5 / np.sqrt(nreal * 10)         # ≥ 10 independent cells' worth
    if method == "lsq":                                       # the variance is the real noise amplification
        assert p.variance.max() / p.variance.min() > 10
        chi2, dof = p.diagnostics["chi2"], p.diagnostics["dof"]  # χ² of the fit: dof ± √(2 dof)
        assert abs(chi2.mean() / dof - 1) < 5 * np.sqrt(2 / dof / nreal)


@pytest.mark.slow
def test_variance_pulls_lazuli_layout(mapper):
    """A few realisations on the real layout (red end: the worst conditioning)."""
    rng = np.random.default_rng(8)
    edges, nreal = RED, 8
    lbda = _centres(edges)
    truth = _truth(rng, edges, 58)
    model = mapper.project_fields(lbda, edges, narrow=truth)
    var = 0.05 + 0.1 * model
    rows = np.flatnonzero(model.any(axis=1))                  # noise where the field is (saves time)
    noisy = np.repeat(model[None], nreal, axis=0)
    noisy[:, rows] += np.sqrt(var[rows]) * rng.standard_normal((nreal, rows.size, model.shape[1]))
    p = rectify(noisy, var, mapper=mapper, field="narrow", lbda=lbda, lbda_edges=edges, ncol=58)
    width, err = _pull_width((p.flux - truth) / np.sqrt(p.variance))
    print(f"Lazuli layout, lsq: pull width {width:.4f} ± {err:.4f}")
    assert abs(width - 1) < 0.05 and abs(width - 1) < 5 * err + 2e-3, (width, err)


# --------------------------------------------------------------------------- drizzle
def test_drizzle_conserves_flux_and_constants(mapper):
    edges, ncol = BLUE, 58
    lbda = _centres(edges)
    rng = np.random.default_rng(3)
    truth = _truth(rng, edges, ncol)
    img = mapper.project_fields(lbda, edges, narrow=truth, wide=np.full_like(truth, 2.5))
    out = rectify(img, mapper=mapper, field="both", lbda=lbda, lbda_edges=edges, ncol=ncol, method="drizzle")
    d = out["narrow"].diagnostics
    assert d["flux_cube"][0] == pytest.approx(d["flux_image"][0], rel=1e-12)
    assert d["flux_image"][0] == pytest.approx(img[2048:].sum(), rel=1e-12)    # narrow: top half
    assert np.abs(out["wide"].flux - 2.5).max() < 1e-12                       # constants come back
    err_drizzle = np.abs(out["narrow"].flux - truth).max() / truth.max()
    assert err_drizzle > 0.01               # biased (smoothed) where lsq is exact to 1e-15 on this grid


# --------------------------------------------------------------------------- bad input
def test_bad_input_is_refused_before_any_work(mapper, monkeypatch):
    calls = []
    monkeypatch.setattr(mapper, "projection_tables", lambda *a, **k: calls.append(a))
    lbda, edges = _centres(BLUE), BLUE
    good = np.zeros(mapper.detector_shape)
    cases = [
        (dict(rate_image=np.zeros((4096, 4095))), "rate_image must have shape"),
        (dict(field="medium"), "unknown field 'medium'"),
        (dict(lbda=lbda[:-1]), "inconsistent λ grid: 5 bin centres for 7 edges"),
        (dict(lbda=lbda + 500), "inconsistent λ grid: every centre"),
        (dict(lbda=None, lbda_edges=edges[::-1]), "inconsistent λ grid: lbda_edges must increase"),
        (dict(lbda=None, lbda_edges=np.array([3000.0, 3500.0])), "inconsistent λ grid: .* leaves the traces"),
        (dict(lbda=None, lbda_edges=None), "λ grid is missing"),
        (dict(variance=np.ones((10, 10))), "variance must have shape"),
        (dict(variance=np.full(mapper.detector_shape, -1.0)), "variance must be ≥ 0"),
        (dict(method="psf"), "unknown method"),
        (dict(ncol=0), "ncol must be an integer ≥ 1"),
    ]
    for change, message in cases:
        kw = dict(rate_image=good, variance=None, mapper=mapper, field="narrow", lbda=lbda, lbda_edges=edges,
                  ncol=58)
        kw.update(change)
        with pytest.raises(ParameterError, match=message):
            rectify(kw.pop("rate_image"), kw.pop("variance"), **kw)
    assert calls == []                                        # nothing built or launched
    other = SlicerMapper(mapper.slice_ids[:58], mapper.fieldpos_nodes, mapper.lbda_nodes, mapper.values[:58],
                         table_cache=None)
    with pytest.raises(ParameterError, match="no wide field"):
        rectify(good, mapper=other, field="both", lbda=lbda, lbda_edges=edges, ncol=58)


EDGES = SMALL_EDGES                          # 12 bins on the small test layout


NCOL = 24


@pytest.fixture(scope="module")
def small_raw(tmp_path_factory):
    """Raw ramps of a point source in the narrow field of the small test layout (660 × 600)."""
    return small_raw_ramps(tmp_path_factory.mktemp("small") / "raw.h5")[:2]


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


@pytest.fixture(scope="module")
def layout():
    small, psf, _, _, img, var, noisy = noisy_scene()
    cp = rectify(noisy, var, mapper=small, field="narrow", lbda_edges=EDGES_GLS, ncol=NCOL_GLS)
    return small, cp, var, psf, img, noisy


@pytest.mark.parametrize("bad", ["transposed", "padded", "flat", "scalar"])
def test_noise_information_needs_the_detector_shaped_variance(layout, bad):
    _, cp, var, *_ = layout
    v = {"transposed": var.T.copy(), "padded": np.pad(var, 5), "flat": var.ravel(), "scalar": 1.0}[bad]
    with pytest.raises(ParameterError, match="rectified from"):
        noise_information(cp.inverse_covariance, v)


@pytest.mark.parametrize("bad", ["text", "complex"])
def test_noise_information_refuses_non_real_variances(layout, bad):
    _, cp, var, *_ = layout
    with pytest.raises(ParameterError, match="variance must be"):
        noise_information(cp.inverse_covariance, "abc" if bad == "text" else var + 1j)


@pytest.mark.parametrize("info", [None, "cube"])
def test_noise_information_needs_an_inverse_covariance(layout, info):
    _, cp, var, *_ = layout
    with pytest.raises(ParameterError, match="InverseCovariance"):
        noise_information(cp if info == "cube" else None, var)


def test_noise_information_of_another_cube_is_refused(layout):
    small, cp, var, psf, img, noisy = layout
    wide = rectify(noisy, var, mapper=small, field="wide", lbda_edges=EDGES_GLS, ncol=NCOL_GLS)
    shifted = rectify(noisy, var, mapper=small, field="narrow", lbda_edges=EDGES_GLS + 3.0, ncol=NCOL_GLS)
    assert wide.flux.shape == shifted.flux.shape == cp.flux.shape            # the old shape check passed them
    for other in (wide, shifted):
        with pytest.raises(ParameterError, match="not for this cube"):
            extract_spectrum(cp, psf=psf, method="gls",
                             noise_information=noise_information(other.inverse_covariance, var))
    for junk in (np.zeros(cp.flux.shape), cp.inverse_covariance):             # an array; N itself (not a B)
        with pytest.raises(ParameterError, match="noise_information"):
            extract_spectrum(cp, psf=psf, method="gls", noise_information=junk)
    opt = extract_spectrum(cp, psf=psf, method="optimal")
    with pytest.raises(ParameterError, match="not for this cube"):
        propagate_variance(opt, cp, noise_information=noise_information(wide.inverse_covariance, var))
    with pytest.raises(ParameterError, match="rate_variance"):
        propagate_variance(opt, cp, var, mapper=small, noise_information=noise_information(cp.inverse_covariance, var))


def test_sandwich_is_the_naive_variance_when_the_weights_are_the_inverse_variance(layout):
    _, cp, var, psf, *_ = layout
    B = noise_information(cp.inverse_covariance, var)
    naive = extract_spectrum(cp, psf=psf, method="gls")
    sw = extract_spectrum(cp, psf=psf, method="gls", noise_information=B)
    np.testing.assert_allclose(sw.variance, naive.variance, rtol=1e-10)
    opt = extract_spectrum(cp, psf=psf, method="optimal")
    np.testing.assert_allclose(propagate_variance(opt, cp, noise_information=B), propagate_variance(opt, cp),
                               rtol=1e-10)


@pytest.mark.slow
def test_propagated_variance_sandwich_matches_monte_carlo(layout):
    """Optimal extraction from a cube rectified with wrong weights (core variance 0.6×): the
    propagated N⁻¹ under-reports, the sandwich N⁻¹BN⁻¹ matches 400 realisations."""
    small, _, var, psf, img, _ = layout
    used = np.where(img > 0.3 * img.max(), 0.6 * var, var)
    n = 400
    stack = img[None] + np.random.default_rng(17).standard_normal((n,) + img.shape) * np.sqrt(var)[None]
    cw = rectify(stack, used, mapper=small, field="narrow", lbda_edges=EDGES_GLS, ncol=NCOL_GLS)
    opt = extract_spectrum(cw, psf=psf, method="optimal")
    naive = propagate_variance(opt, cw)
    sw = propagate_variance(opt, cw, noise_information=noise_information(cw.inverse_covariance, var))
    emp = opt.flux.var(axis=0, ddof=1)
    err = np.sqrt(2 / (n - 1))
    r_sw, r_naive = emp / sw, emp / naive
    print(f"empirical / sandwich {np.round(r_sw, 3)}; empirical / naive {np.round(r_naive, 3)} (± {err:.3f})")
    assert np.all(np.abs(r_sw - 1) < 4 * err) and abs(r_sw.mean() - 1) < 4 * err / np.sqrt(r_sw.size)
    assert r_naive.mean() > 1 + 4 * err / np.sqrt(r_naive.size)


def test_a_few_unsolvable_slices_are_nan_with_a_warning_not_a_failed_exposure(mapper, monkeypatch):
    """A campaign target with cosmic rays failed whole ("slice 32: … condition 1.1e+14 > 1e+14") though its
    forward-fit spectrum does not use the cube: one or a few unsolvable slices now leave their cells NaN with a
    warning; more than a tenth of the slices (the grid asked for, not damage) is still refused."""
    from slicersim.reduction import rectify as module
    edges = _EDGES[200:206]
    img = mapper.project_fields(_centres(edges), edges, narrow=np.ones((5, 58, 116)))
    real = module._solve_slice

    def one_bad(P, w, rhs, data, want_variance, max_bytes, sid, A, excluded=0.0):
        if sid == 32:
            raise module._UnsolvedSlice("slice 32: the normal matrix PᵀWP has condition 1.1e+14 > 1e+14: test")
        return real(P, w, rhs, data, want_variance, max_bytes, sid, A, excluded)
    monkeypatch.setattr(module, "_solve_slice", one_bad)
    with pytest.warns(RuntimeWarning, match=r"1 of 58 slices not rectified, their cells NaN: slice 32"):
        p = rectify(img, mapper=mapper, field="narrow", lbda_edges=edges, ncol=29)
    bad = ~np.isfinite(p.flux).all(axis=(0, 2))          # the cube rows that are all NaN
    assert bad.sum() == 1 and np.isfinite(p.flux[:, ~bad]).all()

    def all_bad(P, w, rhs, data, want_variance, max_bytes, sid, A, excluded=0.0):
        raise module._UnsolvedSlice(f"slice {sid}: singular — test")
    monkeypatch.setattr(module, "_solve_slice", all_bad)
    with pytest.raises(ParameterError, match=r"singular — test \(58 of 58 slices\)"):
        rectify(img, mapper=mapper, field="narrow", lbda_edges=edges, ncol=29)
