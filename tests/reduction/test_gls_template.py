"""Forward-modelled point-source templates (slicersim.reduction.templates) for the GLS extraction
(slicersim.reduction.gls_extraction, ``psf`` of shape (K, nλ, ny, nx)), on the small test layout.

A point source sharp at NATIVE resolution (2 native λ bins × 2 native columns per coarse cell)
is projected on the native grid (plus a uniform background on the coarse grid) and rectified on the
coarse grid, as the closed loop does.

Tolerances
----------
* Noiseless: the template is E[x̂] per unit flux by linearity (same mapper, grid, weights), so
  the template GLS is exact to κ·ε: 1e-8 relative (measured ~1e-13).  The coarse per-bin PSF
  (the native cube rebinned, psf_from_cube) is a model error: its bias must exceed 1 %.
* White noise, 30 realisations in one stack: mean pull within 3 Monte Carlo errors (scatter of
  the per-realisation mean pull / √n) of 0; the fit's χ²/dof over the cells within 3 of its
  Monte Carlo errors (√(2/dof/n)) of 1, and the pulls' χ² with the bins' covariance within 3 of
  theirs.
"""
import numpy as np
import pytest
from conftest import small_slicer_mapper

from slicersim.errors import ParameterError
from slicersim.physics.psf import gaussian_psf_cells
from slicersim.reduction.rectify import rectify
from slicersim.reduction.spectra import extract_spectrum, psf_from_cube
from slicersim.reduction.templates import point_source_template

EDGES = np.linspace(9050.0, 9950.0, 11)            # coarse: 10 bins of 6 px
NATIVE = np.linspace(9050.0, 9950.0, 21)           # native: 2 bins per coarse bin
NCOL, NCOL_NATIVE, NY = 24, 48, 58


def _native_scene():
    """Sharp point source (σ ≈ 0.2 coarse cell along the slice) with a steep spectrum."""
    lbda = 0.5 * (NATIVE[1:] + NATIVE[:-1])
    sig = 0.35 + 0.1 * (lbda - lbda[0]) / (lbda[-1] - lbda[0])          # native cells
    iy, ix = np.indices((NY, NCOL_NATIVE)).reshape(2, -1)
    psf = gaussian_psf_cells(0.4 * sig, sig, (NY, NCOL_NATIVE), (1.3, -2.2), (iy, ix)).reshape(-1, NY, NCOL_NATIVE)
    f = 20.0 * (1 + 0.8 * np.sin(lbda / 60.0))                           # strong variation inside a coarse bin
    ps = f[:, None, None] * psf
    return lbda, ps


def _rebin(cube):
    nl, ny, nx = cube.shape
    return cube.reshape(nl // 2, 2, ny, nx // 2, 2).sum(axis=(1, 4))


@pytest.fixture(scope="module")
def setup():
    small = small_slicer_mapper()
    lbda, ps = _native_scene()
    # the background on the coarse grid (the GLS model's uniform B_λ); a uniform NATIVE background
    # is not exactly uniform once rectified (its image differs at the ~2 % level near the band's
    # ends): 1.5e-5 relative on F̂ here, a separate model question from the point source's
    coarse_lbda = 0.5 * (EDGES[1:] + EDGES[:-1])
    img = small.project_fields(lbda, NATIVE, narrow=ps) + \
        small.project_fields(coarse_lbda, EDGES, narrow=np.full((EDGES.size - 1, NY, NCOL), 0.04))
    var = np.where(img > 0, 2e-3 + 0.01 * img, 2e-3)
    n = 30
    rng = np.random.default_rng(7)
    stack = np.concatenate([img[None], img[None] + rng.standard_normal((n,) + img.shape) * np.sqrt(var)])
    cp = rectify(stack, var, mapper=small, field="narrow", lbda_edges=EDGES, ncol=NCOL, keep_information=True)
    T = point_source_template(ps, NATIVE, EDGES, mapper=small, field="narrow", ncol=NCOL, variance=var)
    truth = ps.reshape(EDGES.size - 1, 2, NY, NCOL_NATIVE).sum(axis=(1, 2, 3))
    return small, cp, var, T, truth, psf_from_cube(_rebin(ps)), n


@pytest.mark.slow
def test_noiseless_template_is_exact_and_the_coarse_psf_is_biased(setup):
    small, cp, var, T, truth, coarse_psf, n = setup
    assert T.shape == (10, 10, NY, NCOL)
    single = type(cp)(**{**cp.__dict__, "flux": cp.flux[0]})
    coarse = extract_spectrum(single, psf=coarse_psf, method="gls")
    tpl = extract_spectrum(single, psf=T, method="gls")
    bias_coarse = np.abs(coarse.flux / truth - 1).max()
    err = np.abs(tpl.flux / truth - 1).max()
    print(f"noiseless: coarse PSF max |F̂/F − 1| = {bias_coarse:.2e}; template {err:.1e}, "
          f"background {tpl.background.mean():.4f} (truth 0.04 per coarse cell), χ² {tpl.diagnostics['chi2'][0]:.1e}")
    assert bias_coarse > 1e-2
    assert err < 1e-8
    np.testing.assert_allclose(tpl.background, 0.04, rtol=1e-8)
    assert tpl.variance.shape == truth.shape and tpl.diagnostics["covariance"].shape == (10, 10)
    assert np.allclose(np.diag(tpl.diagnostics["covariance"]), tpl.variance, rtol=0, atol=0)
    assert tpl.diagnostics["dof"] == coarse.diagnostics["dof"]


def test_white_noise_template_gls_is_unbiased_with_chi2_one(setup):
    small, cp, var, T, truth, coarse_psf, n = setup
    g = extract_spectrum(cp, psf=T, method="gls")
    z = (g.flux[1:] - truth) / np.sqrt(g.variance)                           # (n, nλ)
    zb = z.mean(axis=1)
    bias, bias_err = zb.mean(), zb.std(ddof=1) / np.sqrt(n)
    dof = g.diagnostics["dof"]
    fit_chi2 = g.diagnostics["chi2"][1:] / dof
    chi2_err = np.sqrt(2.0 / dof / n)
    d = g.flux[1:] - truth
    cinv = np.linalg.inv(g.diagnostics["covariance"])
    pull_chi2 = np.einsum("ni,ij,nj->n", d, cinv, d) / truth.size
    pull_err = pull_chi2.std(ddof=1) / np.sqrt(n)
    print(f"white noise ({n}): bias {bias:+.3f} ± {bias_err:.3f} σ; fit χ²/dof {fit_chi2.mean():.4f} ± "
          f"{chi2_err:.4f} (dof {dof}); pulls χ²/nλ {pull_chi2.mean():.3f} ± {pull_err:.3f}")
    assert abs(bias) < 3 * bias_err
    assert abs(fit_chi2.mean() - 1) < 3 * chi2_err
    assert abs(pull_chi2.mean() - 1) < 3 * pull_err


def test_template_inputs_are_checked(setup):
    small, cp, var, T, truth, coarse_psf, n = setup
    lbda, ps = _native_scene()
    kw = dict(mapper=small, field="narrow", ncol=NCOL, variance=var)
    with pytest.raises(ParameterError, match="native edge"):
        point_source_template(ps, NATIVE, np.where(np.arange(11) == 3, EDGES + 10.0, EDGES), **kw)
    with pytest.raises(ParameterError, match="within the native grid"):
        point_source_template(ps, NATIVE, np.append(EDGES, 10000.0), **kw)
    with pytest.raises(ParameterError, match="native_lbda_edges"):
        point_source_template(ps, NATIVE[:-1], EDGES, **kw)
    with pytest.raises(ParameterError, match="native_cube"):
        point_source_template(ps[0], NATIVE, EDGES, **kw)
    with pytest.raises(ParameterError, match="no positive flux"):
        point_source_template(np.where(np.arange(20)[:, None, None] < 2, 0.0, ps), NATIVE, EDGES, **kw)
    with pytest.raises(ParameterError, match="field"):
        point_source_template(ps, NATIVE, EDGES, mapper=small, field="both", ncol=NCOL)
    with pytest.raises(ParameterError, match=r"unknown field \(one cube per template\) 'both'"):
        point_source_template(ps, NATIVE, EDGES, mapper=small, field="both", ncol=NCOL)
    with pytest.raises(ParameterError, match=r"ncol \(columns of the coarse cube\) must be an integer ≥ 1"):
        point_source_template(ps, NATIVE, EDGES, mapper=small, field="narrow", ncol=0)
    with pytest.raises(ParameterError, match=r"ncol \(columns of the coarse cube\) must be an integer ≥ 1, got 24.5"):
        point_source_template(ps, NATIVE, EDGES, mapper=small, field="narrow", ncol=24.5)
    from slicersim.reduction.templates import background_template
    for bad, match in (((58,), r"native_shape \(ny, nx_native\) must be 2 integers"),
                       ((58, 2.5), r"native_shape \(ny, nx_native\)\[1\] must be an integer"),
                       ((0, 10), r"native_shape \(ny, nx_native\)\[0\] must be an integer in \[1, 65536\]")):
        with pytest.raises(ParameterError, match=match):                   # 2.5 was truncated to 2
            background_template(bad, NATIVE, EDGES, **kw)
    with pytest.raises(ParameterError, match="mapper"):
        point_source_template(ps, NATIVE, EDGES, mapper=None, field="narrow", ncol=NCOL)
    with pytest.raises(ParameterError, match="template psf"):
        extract_spectrum(cp, psf=T[:3], method="gls")
    with pytest.raises(ParameterError, match="template psf"):
        extract_spectrum(cp, psf=np.where(T > 0, np.nan, T), method="gls")


def test_a_diagonal_template_is_the_per_bin_psf(setup):
    """T[k, λ] = δ_kλ P_λ is the 3-D PSF model: the same normal equations and spectrum."""
    from slicersim.reduction.gls_extraction import gls_normal_equations
    small, cp, var, T, truth, coarse_psf, n = setup
    diag = np.zeros((10,) + coarse_psf.shape)
    diag[np.arange(10), np.arange(10)] = coarse_psf
    for background in (True, False):
        G3, b3, q3, s3 = gls_normal_equations(cp, coarse_psf, background)
        G4, b4, q4, s4 = gls_normal_equations(cp, diag, background)
        np.testing.assert_allclose(G4, G3, rtol=1e-13, atol=1e-13 * np.abs(G3).max())
        np.testing.assert_allclose(b4, b3, rtol=1e-12, atol=1e-13 * np.abs(b3).max())
        assert np.array_equal(q4, q3) and s4 == s3
    a, b = (extract_spectrum(cp, psf=p, method="gls") for p in (coarse_psf, diag))
    np.testing.assert_allclose(b.flux, a.flux, rtol=1e-10)
    np.testing.assert_allclose(b.variance, a.variance, rtol=1e-10)
    np.testing.assert_allclose(b.enclosed_energy, a.enclosed_energy, rtol=1e-13)
    with pytest.raises(ParameterError, match="template psf"):
        gls_normal_equations(cp, diag[:, :3])


@pytest.mark.slow
def test_background_template_removes_the_native_sky_model_error():
    """A sky uniform at NATIVE resolution is not uniform once rectified on the coarse grid: fitted
    with a uniform B_λ it biases a faint point source's flux (4.4e-5 relative here, asserted
    > 1e-5, noiseless);
    with background_template (the same forward model as the point source's) the flux and the
    sky's coarse-cell value come back to κ·ε (asserted < 1e-8)."""
    from slicersim.reduction.templates import background_template
    small = small_slicer_mapper()
    lbda, ps = _native_scene()
    ps = ps * 0.05                                                      # faint: the sky matters
    sky = 0.04 / 4                                                      # per native cell and bin: 0.04 per coarse cell
    img = small.project_fields(lbda, NATIVE, narrow=ps + sky)
    var = np.where(img > 0, 2e-3 + 0.01 * img, 2e-3)
    cp = rectify(img, var, mapper=small, field="narrow", lbda_edges=EDGES, ncol=NCOL)
    T = point_source_template(ps, NATIVE, EDGES, mapper=small, field="narrow", ncol=NCOL, variance=var)
    Tb = background_template((NY, NCOL_NATIVE), NATIVE, EDGES, mapper=small, field="narrow", ncol=NCOL, variance=var)
    truth = ps.reshape(EDGES.size - 1, 2, NY, NCOL_NATIVE).sum(axis=(1, 2, 3))
    uniform = extract_spectrum(cp, psf=T, method="gls")
    fwd = extract_spectrum(cp, psf=T, method="gls", background_template=Tb)
    err_uniform = np.abs(uniform.flux / truth - 1).max()
    err = np.abs(fwd.flux / truth - 1).max()
    print(f"native sky: uniform B_λ max |F̂/F − 1| = {err_uniform:.2e}; background template {err:.1e}; "
          f"B̂ {fwd.background.mean():.6f} (0.04)")
    assert err_uniform > 1e-5
    assert err < 1e-8
    np.testing.assert_allclose(fwd.background, 0.04, rtol=1e-8)
    with pytest.raises(ParameterError, match="gls"):
        extract_spectrum(cp, psf=T[0], method="optimal", background_template=Tb)
    with pytest.raises(ParameterError, match="background_template must"):
        extract_spectrum(cp, psf=T, method="gls", background_template=Tb[:2])
