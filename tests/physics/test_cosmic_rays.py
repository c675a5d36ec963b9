"""Cosmic rays (physics/cosmic_rays.py): rate, geometry, energy loss, counter-based keying."""
import math

import numpy as np
import pytest
from scipy import stats

from slicersim.errors import EffectsError
from slicersim.physics import cosmic_rays as cr

P = cr.CosmicRayParameters()
FULL = (4096, 4096)


def test_rate_within_3_sigma_and_poisson_dispersion():
    nframes, tframe = 4000, 2.83
    counts = np.concatenate([cr.cosmic_ray_events(7, ramp, nframes, tframe, FULL, P) for ramp in range(2)])
    area = 4096 ** 2 * (10e-4) ** 2                       # cm²
    expected = 5.0 * area * tframe * counts.size            # 237.4 per frame
    assert abs(counts.sum() - expected) < 3.0 * math.sqrt(expected)
    measured_rate = counts.sum() / (area * tframe * counts.size)
    assert abs(measured_rate - 5.0) < 3.0 * 5.0 / math.sqrt(expected)
    # Poisson: index of dispersion ~ χ²(N−1)/(N−1)
    dof = counts.size - 1
    disp = counts.var(ddof=1) / counts.mean() * dof
    assert stats.chi2.sf(disp, dof) > 1e-3 and stats.chi2.cdf(disp, dof) > 1e-3


def test_rate_scales_with_parameter_and_zero_rate():
    p10 = cr.CosmicRayParameters(rate=10.0)
    n = cr.cosmic_ray_events(1, 0, 3000, 2.83, (1024, 1024), p10).sum()
    expected = 10.0 * 1024 ** 2 * 1e-6 * 2.83 * 3000
    assert abs(n - expected) < 3.0 * math.sqrt(expected)
    assert cr.cosmic_ray_deposits(1, 0, 100, 2.83, FULL, cr.CosmicRayParameters(rate=0.0)).size == 0


def _tracks(nframes=200, seed=3):
    return cr.cosmic_ray_tracks(seed, 0, nframes, 2.83, FULL, P)


def test_isotropic_flux_on_a_plane_geometry():
    t = _tracks()
    n = t["frame"].size
    assert n > 40000
    # dN/dcosθ ∝ cos θ: CDF cos²θ
    assert stats.kstest(t["cos_theta"], lambda c: c ** 2).pvalue > 1e-3
    assert stats.kstest(t["phi"] / (2 * math.pi), "uniform").pvalue > 1e-3
    assert stats.kstest(t["x0"] / 4096, "uniform").pvalue > 1e-3
    assert stats.kstest(t["y0"] / 4096, "uniform").pvalue > 1e-3
    # ion mix 87 / 12 / 1 % within binomial 3σ
    for z, f in P.species:
        k = np.count_nonzero(t["z"] == z)
        assert abs(k - f * n) < 3 * math.sqrt(n * f * (1 - f)) + 1


def test_path_lengths_sum_to_thickness_over_cos_theta():
    t = _tracks(50)
    seg = cr.track_segments(t, FULL, P)
    total = np.bincount(seg["event"], weights=seg["length"], minlength=t["frame"].size)
    full_depth = P.thickness / t["cos_theta"]
    # tracks leaving the detector sideways are shorter; all others cross the whole depth
    lateral = P.thickness / P.pixel_pitch * np.sqrt(1 - t["cos_theta"] ** 2) / t["cos_theta"]
    inside = ((t["x0"] > lateral + 1) & (t["x0"] < 4095 - lateral) & (t["y0"] > lateral + 1)
              & (t["y0"] < 4095 - lateral))
    assert inside.mean() > 0.99
    np.testing.assert_allclose(total[inside], full_depth[inside], rtol=1e-9)
    assert np.all(total <= full_depth * (1 + 1e-9))
    # pixels of a track are distinct and each step moves to a 4- or 8-neighbour
    same = seg["event"][1:] == seg["event"][:-1]
    step = np.maximum(np.abs(np.diff(seg["x"])), np.abs(np.diff(seg["y"])))[same]
    assert np.all(step == 1)
    # mean number of pixels per event: 1 + E|Δx| + E|Δy| = 1 + (t/p)(π/2)(4/π) = 1 + 2t/p (unclipped)
    npix = np.bincount(seg["event"], minlength=t["frame"].size)
    mean_pix = npix[inside].mean()
    sem = npix[inside].std() / math.sqrt(inside.sum())
    assert abs(mean_pix - (1 + 2 * P.thickness / P.pixel_pitch)) < 4 * sem


def test_most_probable_loss_matches_pdg_silicon_example():
    """PDG Fig. 34.7 (and SciPy's Landau tutorial): 10 GeV muon in 1.7 mm Si, Δp = 0.5268 MeV,
    ξ = 0.03031 MeV — our Bichsel formula with silicon's Sternheimer δ (C̄ 4.4351, x0 0.2014,
    x1 2.8715, a 0.14921, k 3.2546; Sternheimer, Berger & Seltzer 1984)."""
    bg = 10000.0 / 105.6583755
    b2 = bg ** 2 / (1 + bg ** 2)
    xi = 0.5 * cr.K_BETHE * 0.49848 * 0.17 * 2.329 / b2 * 1e6
    x = math.log10(bg)
    delta = 4.6052 * x - 4.4351 + 0.14921 * (2.8715 - x) ** 3.2546
    assert xi == pytest.approx(30310, rel=1e-3)
    assert cr.bichsel_most_probable(xi, bg, 173.0, delta) == pytest.approx(526800, rel=1e-3)


def test_material_constants():
    zoa, rho, mean_i = cr.hgcdte_properties(0.6)
    assert 0.40 < zoa < 0.42 and 6.5 < rho < 7.0 and 450 < mean_i < 650
    assert 1.24 / cr.band_gap(0.6, 100.0) == pytest.approx(1.69, abs=0.02)     # 1.7 µm cut-off
    assert cr.pair_creation_energy(0.6, 100.0) == pytest.approx(2.65, abs=0.01)


def test_straggling_is_moyal_around_the_most_probable_value():
    """λ = (Δ − Δp)/ξ of every unclipped pixel must follow the Moyal density; the mean charge per
    µm of long segments must match (Δp + (γ_E + ln 2) ξ)/ε within its Monte Carlo error."""
    t = _tracks(200, seed=11)
    seg = cr.track_segments(t, FULL, P)
    e = cr.segment_electrons(11, 0, t, seg, P)
    z, length = t["z"][seg["event"]], seg["length"]
    mpv = cr.most_probable_loss(length, z, P)
    xi = cr.landau_xi(length, z, P)
    ok = length > 1.0
    lam = (e[ok] / P.electrons_per_ev - mpv[ok]) / xi[ok]
    assert ok.sum() > 30000
    assert stats.kstest(lam, stats.moyal.cdf).pvalue > 1e-3
    # protons on ≥ 4 µm segments: mean charge vs analytic expectation
    sel = ok & (z == 1) & (length > 4.0)
    expected = (mpv[sel] + cr.MOYAL_MEAN * xi[sel]) * P.electrons_per_ev
    sigma = math.sqrt(np.sum((xi[sel] * P.electrons_per_ev) ** 2) * cr.MOYAL_VAR)
    assert abs(e[sel].sum() - expected.sum()) < 3 * sigma
    # most probable charge per µm for a vertical proton: ≈ 150 e-/µm in 6 µm of HgCdTe
    per_um = cr.most_probable_loss(6.0, 1, P) * P.electrons_per_ev / 6.0
    assert 120 < per_um < 180
    # an alpha loses ≥ 4× a proton (z² ξ; the log term grows too)
    assert cr.most_probable_loss(6.0, 2, P) > 4 * cr.most_probable_loss(6.0, 1, P)


def test_deposits_layout_sorted_and_deterministic():
    d1 = cr.cosmic_ray_deposits(5, 3, 64, 2.83, FULL, P)
    d2 = cr.cosmic_ray_deposits(5, 3, 64, 2.83, FULL, P)
    assert d1.dtype == cr.DEPOSIT_DTYPE and d1.size > 10000
    np.testing.assert_array_equal(d1, d2)
    assert np.all(d1["ramp"] == 3) and d1["frame"].max() < 64
    key = (d1["y"].astype(np.int64) << 40) | (d1["x"].astype(np.int64) << 20) | d1["frame"]
    assert np.all(np.diff(key) >= 0)
    assert np.all(d1["electrons"] >= 0) and np.all(np.isfinite(d1["electrons"]))
    # a different ramp or seed gives different hits
    assert not np.array_equal(cr.cosmic_ray_deposits(5, 4, 64, 2.83, FULL, P)["x"][:100], d1["x"][:100])


def test_frames_independent_of_ramp_length():
    """Counter-based: the first 32 frames of a 64-frame ramp equal a 32-frame ramp's."""
    long = cr.cosmic_ray_deposits(9, 1, 64, 2.83, FULL, P)
    short = cr.cosmic_ray_deposits(9, 1, 32, 2.83, FULL, P)
    np.testing.assert_array_equal(long[long["frame"] < 32], short)


def test_bad_parameters_rejected():
    for kw in ({"rate": -1.0}, {"thickness": 0.0}, {"pixel_pitch": float("nan")},
               {"species": ((1, 0.5), (2, 0.2))}, {"species": ((0, 1.0),)}, {"species": "protons"},
               {"species": ((1, 1.2), (2, -0.2))}, {"pair_energy": -3.0}):
        with pytest.raises(EffectsError):
            cr.CosmicRayParameters(**kw)
    with pytest.raises(EffectsError, match="shape"):
        cr.cosmic_ray_deposits(1, 0, 10, 2.83, (0, 10), P)
    with pytest.raises(EffectsError, match="tframe"):
        cr.cosmic_ray_deposits(1, 0, 10, -1.0, FULL, P)


def test_species_charges_and_call_arguments_are_integers_not_truncated():
    """A charge z = 2.5 was read as helium (int()); ramp 1.5 as ramp 1: both are refused now."""
    with pytest.raises(EffectsError, match=r"cosmic_rays.species charge z must be an integer in \[1, 92\]"):
        cr.CosmicRayParameters(species=[(1, 0.9), (2.5, 0.1)])
    with pytest.raises(EffectsError, match="cosmic_rays.species must be a list of"):
        cr.CosmicRayParameters(species="proton")
    with pytest.raises(EffectsError, match=r"^ramp must be an integer"):
        cr._check_call(1, 1.5, 4, 2.83, (32, 32))
    with pytest.raises(EffectsError, match=r"shape \(detector\)\[0\] must be an integer"):
        cr._check_call(1, 0, 4, 2.83, (0, 32))
