"""GLS extraction from an LSQ cube with its inverse covariance (slicersim.reduction.gls_extraction) and
rectify's inverse-covariance hook (InverseCovariance), on the small test layout.

Tolerances
----------
* Noiseless, given PSF: the LSQ cube is the truth to κ(P)·ε and GLS is linear and exactly
  unbiased for F P + B: 1e-12 relative (measured ~1e-15).  Fitted Gaussian PSF: 1e-6 (the
  fit's convergence on noiseless data, measured ~1e-8).
* GLS on the cube vs the same GLS on the detector pixels: equal in exact arithmetic (N x̂ = PᵀW d);
  the cube's LSQ solve (one step of refinement) leaves ~κ·ε: 1e-10 relative on flux (in units
  of its σ) and variance.
* The inverse covariance kept, rebuilt lazily and rebuilt from the rate variance: the same
  floating-point operations, asserted identical.
"""
import numpy as np
import pytest
from conftest import SMALL_EDGES, small_raw_ramps
import scipy.sparse as sp
from conftest import small_slicer_mapper

from slicersim.errors import ParameterError
from slicersim.physics.psf import gaussian_psf_cells
from slicersim.reduction.rectify import inverse_covariance, rectify
from slicersim.reduction.spectra import extract_spectrum, propagate_variance

EDGES = np.linspace(9050.0, 9950.0, 11)      # 10 bins of 6 px on the small layout
NCOL = 24


def _scene():
    lbda = 0.5 * (EDGES[1:] + EDGES[:-1])
    ny, nx = 58, NCOL
    sig = 1.1 + 0.5 * (lbda - lbda[0]) / (lbda[-1] - lbda[0])
    iy, ix = np.indices((ny, nx)).reshape(2, -1)
    psf = gaussian_psf_cells(sig, 0.9 * sig, (ny, nx), (-0.6, 3.4), (iy, ix)).reshape(-1, ny, nx)
    F = 30.0 * (1 + 0.2 * np.cos(lbda / 150.0))
    B = 0.03 - 0.001 * np.arange(lbda.size)
    return lbda, F[:, None, None] * psf + B[:, None, None], psf, F, B


def noisy_scene():
    """The small layout, :func:`_scene` projected (img), its pixel variance and one noisy draw."""
    small = small_slicer_mapper()
    lbda, cube, psf, F, B = _scene()
    img = small.project_fields(lbda, EDGES, narrow=cube)
    var = np.where(img > 0, 2e-3 + 0.01 * img, 2e-3)
    noisy = img + np.random.default_rng(5).standard_normal(img.shape) * np.sqrt(var)
    return small, psf, F, B, img, var, noisy


@pytest.fixture(scope="module")
def setup():
    small, psf, F, B, img, var, noisy = noisy_scene()
    cp = rectify(np.stack([img, noisy]), var, mapper=small, field="narrow", lbda_edges=EDGES, ncol=NCOL,
                 keep_information=True)
    return small, cp, var, psf, F, B, noisy, img


def test_noiseless_gls_returns_the_truth(setup):
    small, cp, var, psf, F, B, *_ = setup
    g = extract_spectrum(cp, psf=psf, method="gls")
    err, errb = np.abs(g.flux[0] / F - 1).max(), np.abs(g.background[0] / B - 1).max()
    print(f"GLS noiseless: max |F̂/F − 1| = {err:.1e}, |B̂/B − 1| = {errb:.1e}, fit χ² {g.diagnostics['chi2'][0]:.1e}")
    assert err < 1e-12 and errb < 1e-10
    assert g.method == "gls" and g.cell_weights is None and g.variance.shape == F.shape
    assert np.allclose(np.diag(g.diagnostics["covariance"]), g.variance, rtol=0, atol=0)
    single = type(cp)(**{**cp.__dict__, "flux": cp.flux[0]})          # one cube, not a stack
    fit = extract_spectrum(single, psf="fit", method="gls")
    print(f"fitted PSF: max |F̂/F − 1| = {np.abs(fit.flux / F - 1).max():.1e}")
    assert np.abs(fit.flux / F - 1).max() < 1e-6 and np.allclose(fit.position, (-0.6, 3.4), atol=1e-5)
    assert np.array_equal(propagate_variance(fit, single), fit.variance)   # already exact


def test_gls_needs_the_inverse_covariance(setup):
    small, cp, var, psf, F, B, noisy, img = setup
    dz = rectify(noisy, var, mapper=small, lbda_edges=EDGES, ncol=NCOL, method="drizzle")
    assert dz.inverse_covariance is None
    with pytest.raises(ParameterError, match="method='gls' needs the cube's inverse covariance"):
        extract_spectrum(dz, psf=psf, method="gls")
    with pytest.raises(ParameterError, match="inverse covariance"):
        dz.normal_matrix(0)
    unweighted = rectify(noisy, mapper=small, lbda_edges=EDGES, ncol=NCOL)       # no variance: no N
    with pytest.raises(ParameterError, match="gls"):
        extract_spectrum(unweighted, psf=psf, method="gls")
    with pytest.raises(ParameterError, match=r"unknown method 'GLS'.*valid: 'optimal', 'aperture', 'gls'"):
        extract_spectrum(cp, psf=psf, method="GLS")


def test_inverse_covariance_kept_lazy_and_rebuilt_agree(setup):
    """keep_information, the lazy rebuild and inverse_covariance(variance) give the same N; its
    inverse's diagonal is the cube's variance."""
    small, cp, var, psf, F, B, noisy, img = setup
    lazy = rectify(noisy, var, mapper=small, lbda_edges=EDGES, ncol=NCOL)
    rebuilt = inverse_covariance(var, mapper=small, lbda_edges=EDGES, ncol=NCOL)
    kept = cp.inverse_covariance
    assert kept.nbytes() > lazy.inverse_covariance.nbytes()
    print(f"inverse covariance: kept {kept.nbytes() / 2**20:.1f} MiB, lazy {lazy.inverse_covariance.nbytes() / 2**20:.2f} MiB")
    for row in (0, 17, 57):
        A = kept.matrix(row)
        assert A.shape == (10 * NCOL, 10 * NCOL)
        assert (A != lazy.normal_matrix(row)).nnz == 0 and (A != rebuilt.matrix(row)).nnz == 0
        seen = A.diagonal() > 0
        C = np.linalg.inv(A.toarray()[np.ix_(seen, seen)])
        np.testing.assert_allclose(np.diag(C), cp.variance[:, row, :].ravel()[seen], rtol=1e-9)
    with pytest.raises(ParameterError, match="row"):
        kept.matrix(58)
    with pytest.raises(ParameterError, match=r"row \(cube row\) must be an integer in \[0, 57\], got 2.5"):
        kept.matrix(2.5)                                      # was truncated to row 2


def test_gls_on_the_cube_is_gls_on_the_pixels(setup):
    """θ̂ from the cube and N equals the weighted fit of P M θ to the detector pixels rectify used
    (unshared, finite variance), flux and covariance."""
    from slicersim.backends.projection_transpose import matrix_entries
    from slicersim.reduction.rectify import FIELDS, _slice_coverage
    small, cp, var, psf, F, B, noisy, img = setup
    g = extract_spectrum(cp, psf=psf, method="gls")
    slices = [int(s) for s in FIELDS["narrow"]]
    tables = small.projection_tables(slices, NCOL, EDGES)
    pix, cell, w = matrix_entries(tables, 0, tables.host().ncell)
    S, nl = len(slices), EDGES.size - 1
    P = sp.csr_matrix((w, (pix, cell)), shape=(var.size, S * nl * NCOL))      # cells (S, nλ, ncol)
    usable = (np.asarray(P.sum(axis=1)).ravel() > 0) & (_slice_coverage(small, NCOL, EDGES, (1, 1), 4.0) == 1).ravel()
    # M: cells in gather order (slice s ↔ cube row S − 1 − s) → (F_λ, B_λ)
    s_i, l_i, c_i = np.indices((S, nl, NCOL)).reshape(3, -1)
    p = psf[l_i, S - 1 - s_i, c_i]
    M = sp.csr_matrix((np.concatenate([p, np.ones(p.size)]), (np.tile(np.arange(p.size), 2),
                                                             np.concatenate([l_i, nl + l_i]))), shape=(p.size, 2 * nl))
    D = (P[usable] @ M).toarray()                                          # (pixels, 2 nλ)
    wgt = 1.0 / var.ravel()[usable]
    G = D.T @ (wgt[:, None] * D)
    cov = np.linalg.inv(G)
    for k, image in enumerate(cp.flux):
        d = (img, noisy)[k].ravel()[usable]
        theta = cov @ (D.T @ (wgt * d))
        rel = np.abs(theta[:nl] - g.flux[k]) / np.sqrt(g.variance)
        print(f"image {k}: max |θ̂_pixels − θ̂_cube| / σ = {rel.max():.1e}")
        assert rel.max() < 1e-10
    np.testing.assert_allclose(g.variance, np.diag(cov)[:nl], rtol=1e-10)
    np.testing.assert_allclose(g.background_variance, np.diag(cov)[nl:], rtol=1e-10)


@pytest.mark.slow
def test_sandwich_variance_for_weights_that_are_not_the_inverse_variance(setup):
    """Weights W ≠ Σ⁻¹ (the core pixels' variance under-estimated 40 %, as a smooth model image
    misses a sharp core): (MᵀNM)⁻¹ under-reports, the sandwich (MᵀNM)⁻¹ MᵀBM (MᵀNM)⁻¹ with
    B = PᵀWΣWP (rectify.noise_information) is the estimator's exact covariance.  Compared with the
    scatter of 400 Gaussian realisations (one factorisation for the stack): every bin within 4 σ
    of the variance's Monte Carlo error √(2/399) = 7 %, the band mean within 4 σ / √nλ; the naive
    variance is ~1.5× too small."""
    from slicersim.reduction.rectify import noise_information
    small, cp, var, psf, F, B, noisy, img = setup
    core = img > 0.3 * img.max()
    used = np.where(core, 0.6 * var, var)                      # wrong weights on the core
    rng = np.random.default_rng(11)
    n = 400
    stack = img[None] + rng.standard_normal((n,) + img.shape) * np.sqrt(var)[None]
    cw = rectify(stack, used, mapper=small, field="narrow", lbda_edges=EDGES, ncol=NCOL)
    naive = extract_spectrum(cw, psf=psf, method="gls")
    sw = extract_spectrum(cw, psf=psf, method="gls", noise_information=noise_information(cw.inverse_covariance, var))
    np.testing.assert_array_equal(sw.flux, naive.flux)          # same estimator, other variance
    emp = sw.flux.var(axis=0, ddof=1)
    err = np.sqrt(2 / (n - 1))                                  # relative MC error of a variance
    r_sw, r_naive = emp / sw.variance, emp / naive.variance
    print(f"empirical / sandwich {np.round(r_sw, 3)}; empirical / naive {np.round(r_naive, 3)} (± {err:.3f})")
    assert np.all(np.abs(r_sw - 1) < 4 * err) and abs(r_sw.mean() - 1) < 4 * err / np.sqrt(r_sw.size)
    assert r_naive.mean() > 1 + 4 * err / np.sqrt(r_naive.size)  # the naive variance under-reports
    assert "sandwich" in sw.diagnostics["variance_model"]
    with pytest.raises(ParameterError, match="gls"):
        extract_spectrum(cw, psf=psf, method="optimal", noise_information=noise_information(cw.inverse_covariance, var))
    with pytest.raises(ParameterError, match="pixels"):
        noise_information(cw.inverse_covariance, var[:10])


EDGES_RAW = SMALL_EDGES                          # 12 bins on the small test layout


@pytest.fixture(scope="module")
def small_raw(tmp_path_factory):
    """Raw ramps of a point source in the narrow field of the small test layout (660 × 600)."""
    return small_raw_ramps(tmp_path_factory.mktemp("small") / "raw.h5")[:2]


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
    cubes = [rectify(rate, var, mapper=mapper, lbda_edges=EDGES_RAW, ncol=NCOL, method=m) for m in ("drizzle", "lsq")]
    lbda = 0.5 * (EDGES_RAW[1:] + EDGES_RAW[:-1])
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
