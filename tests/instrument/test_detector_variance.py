"""Ramp variance models (Rauscher07, Kubik16), readout times, data volume; Monte Carlo check.

Hand values are written out as explicit arithmetic from the published formulas,
never by calling the library twice, so a wrong coefficient in
:mod:`slicersim.instrument.detector` fails here.
"""
import math

import numpy as np
import pytest

from slicersim.errors import ReadoutError
from slicersim.instrument.detector import Detector
from slicersim.physics.readout import (check_readout, rauscher07_coefficients, readout_times, variance_kubik16,
                                       variance_rauscher07)

TF = 2.83   # s, Lazuli frame time


# --------------------------------------------------------------------------- #
#  Rauscher et al. 2007 (corrected): hand values                              #
# --------------------------------------------------------------------------- #
def test_rauscher07_hand_value():
    # nmd = (16, 8, 0), t_f = 2.83 s, σ = 12 e-, S = flux + dark = 0.1 e-/s, g = 1
    #   t_g = (8 + 0)·2.83 = 22.64 s
    #   a   = 12·15 / (8·16·17)            = 180/2176 = 45/544
    #   a σ² = 45·144/544                  = 405/34   = 11.911764705882353
    #   b1  = 6·(16²+1)/(5·16·17) · 15 · 22.64 = 1542/1360 · 339.6 = 385.0464705882353
    #   b2  = 2·(8²−1)·15/(8·16·17) · 2.83    = 1890/2176 · 2.83  = 2.4580422794117645
    #   b S = (385.0464705882353 − 2.4580422794117645)·0.1 = 38.258842830882354
    #   V   = 11.911764705882353 + 38.258842830882354 = 50.170607536764706  (= 54585621/1088000)
    a = 12 * 15 / (8 * 16 * 17)
    b = 6 * (16**2 + 1) / (5 * 16 * 17) * 15 * (8 * 2.83) - 2 * (8**2 - 1) * 15 / (8 * 16 * 17) * 2.83
    expected = a * 12.0**2 + b * 0.1
    assert expected == pytest.approx(54585621 / 1088000, rel=1e-15)
    got = variance_rauscher07(0.1, (16, 8, 0), TF, 12.0, 0.0)
    assert got == pytest.approx(expected, rel=1e-12)
    # the dark current adds to the flux: 0.09 e-/s + 0.01 e-/s is the same S
    assert variance_rauscher07(0.09, (16, 8, 0), TF, 12.0, 0.01) == pytest.approx(expected, rel=1e-12)
    # coefficients exposed separately
    ca, cb = rauscher07_coefficients((16, 8, 0), TF)
    assert ca == pytest.approx(45 / 544, rel=1e-14)
    assert cb == pytest.approx(41625621 / 108800, rel=1e-12)


def test_rauscher07_hand_value_with_drops_and_gain():
    # nmd = (10, 4, 2), t_f = 2.83, σ = 20 e-, S = 3 + 0.01 e-/s, gain 2 ADU/e-
    #   t_g = 6·2.83 = 16.98 s
    #   a   = 12·9/(4·10·11) = 108/440 = 27/110
    #   b   = 6·101/(5·10·11)·9·16.98 − 2·15·9/(4·10·11)·2.83
    #       = 606/550·152.82 − 270/440·2.83 = 168.38564727… − 1.73659090… = 166.6430545454…
    #   V   = (27/110·400 + 166.64305454…·3.01) / 2² = (98.18181818… + 501.59559418…)/4 = 149.944510431818
    #   (reference convention: the e-² variance is divided by gain²)
    a = 12 * 9 / (4 * 10 * 11)
    b = 6 * (10**2 + 1) / (5 * 10 * 11) * 9 * (6 * 2.83) - 2 * (4**2 - 1) * 9 / (4 * 10 * 11) * 2.83
    expected = (a * 20.0**2 + b * 3.01) / 2.0**2
    assert expected == pytest.approx(149.94451043181817, rel=1e-14)
    assert variance_rauscher07(3.0, (10, 4, 2), TF, 20.0, 0.01, gain=2.0,
                               conventions="slicersim-1.0") == pytest.approx(expected, rel=1e-12)
    # physical: ADU = g·e-, so the e-² variance (599.7780…) is multiplied by g² = 4
    assert variance_rauscher07(3.0, (10, 4, 2), TF, 20.0, 0.01, gain=2.0) == pytest.approx(
        expected * 2.0**4, rel=1e-12)


def test_rauscher07_two_groups_is_cds():
    # n = 2, m = 1: correlated double sampling, V = 2σ² + S t_f exactly
    #   a = 12·1/(1·2·3) = 2;  b = 6·5/(5·2·3)·1·t_f − 0 = t_f
    got = variance_rauscher07(np.array([0.0, 7.0]), (2, 1, 0), TF, 15.0, 0.0)
    np.testing.assert_allclose(got, [2 * 15.0**2, 2 * 15.0**2 + 7.0 * 2.83], rtol=1e-14)


# --------------------------------------------------------------------------- #
#  Kubik et al. 2016: hand values                                              #
# --------------------------------------------------------------------------- #
def _kubik_by_hand(flux, n, m, d, tf, sigma, dark, g):
    """Kubik16 written out step by step (used with the literal values below)."""
    t_int = (n - 1) * (m + d) * tf
    s_a = (flux + dark) * g * t_int
    ghat = s_a / (n - 1)
    alpha = (1 - m**2) / (3 * m * (m + d))
    gamma = 2 * g**2 * sigma**2 / m
    beta = gamma / (1 + alpha)
    s_beta = ghat + beta / g
    return (((n - 1) + alpha) * ghat + gamma / g) * g * 4 * s_beta**2 / ((1 + alpha) ** 2 * g**2 + 4 * s_beta**2)


def _rauscher_by_hand(flux, n, m, d, tf, sigma, dark, g=1.0):
    """Rauscher et al. 2007 (corrected) written out: (a σ² + b S) / g²."""
    tg = (m + d) * tf
    a = 12 * (n - 1) / (m * n * (n + 1))
    b = 6 * (n**2 + 1) / (5 * n * (n + 1)) * (n - 1) * tg - 2 * (m**2 - 1) * (n - 1) / (m * n * (n + 1)) * tf
    return (a * sigma**2 + b * (flux + dark)) / g**2


def test_kubik16_read_noise_dominated():
    # nmd = (16, 8, 0), t_f = 2.83, σ = 12, flux = 1e-3 e-/s, dark 0, g = 1
    #   t_int = 15·8·2.83 = 339.6 s;  S_A = 0.3396;  ĝ = 0.3396/15 = 0.02264
    #   α = (1−64)/(3·8·8) = −0.328125;  γ = 2·144/8 = 36;  β = 36/0.671875 = 53.58139534883721
    #   s_β = 0.02264 + 53.58139534883721 = 53.60403534883721
    #   [(15 − 0.328125)·0.02264 + 36] = 36.33217125
    #   4 s_β² = 11493.5704…;  (1+α)² = 0.451416015625
    #   V = 36.33217125 · 11493.5704 / (0.451416 + 11493.5704) = 36.33074434093242
    s_beta = 0.02264 + 36 / (1 - 0.328125)
    expected = (14.671875 * 0.02264 + 36) * 4 * s_beta**2 / (0.671875**2 + 4 * s_beta**2)
    assert expected == pytest.approx(36.33074434093242, rel=1e-14)
    assert _kubik_by_hand(1e-3, 16, 8, 0, 2.83, 12.0, 0.0, 1.0) == pytest.approx(expected, rel=1e-14)
    got = variance_kubik16(1e-3, (16, 8, 0), TF, 12.0, 0.0)
    assert got == pytest.approx(expected, rel=1e-12)
    # read-noise dominated: close to the two-point limit γ = 2σ²/m = 36
    assert abs(got / 36.0 - 1) < 0.01


def test_kubik16_photon_dominated():
    # nmd = (10, 4, 2), t_f = 2.83, σ = 10, flux = 200, dark = 0.01, g = 1.5
    #   t_int = 9·6·2.83 = 152.82;  S_A = 200.01·1.5·152.82 = 45848.2923 ADU;  ĝ = 5094.2547
    #   α = (1−16)/(3·4·6) = −0.208333…;  γ = 2·2.25·100/4 = 112.5;  β = 112.5/0.791666… = 142.1052631578947
    #   s_β = 5094.2547 + 142.10526/1.5 = 5188.991542105263
    #   V = [(9 − 0.208333)·5094.2547 + 112.5/1.5]·1.5·4 s_β² / [0.791666²·2.25 + 4 s_β²]
    #     = 67292.9829751786 ADU²
    ghat = 200.01 * 1.5 * (9 * 6 * 2.83) / 9
    alpha = -15 / 72
    s_beta = ghat + 112.5 / (1 + alpha) / 1.5
    expected = ((9 + alpha) * ghat + 75.0) * 1.5 * 4 * s_beta**2 / ((1 + alpha) ** 2 * 2.25 + 4 * s_beta**2)
    assert expected == pytest.approx(67292.9829751786, rel=1e-13)
    got = variance_kubik16(200.0, (10, 4, 2), TF, 10.0, 0.01, gain=1.5)
    assert got == pytest.approx(expected, rel=1e-12)
    # photon dominated: the Poisson part (n−1+α) ĝ g dominates (read noise < 0.2 %)
    assert abs(got / ((9 + alpha) * ghat * 1.5) - 1) < 2e-3


def test_gain_conventions():
    # Physical: a signal of N e- reads g·N ADU, so every variance in ADU² is the e-²
    # variance times g² (both models).  slicersim 1.0 divided Rauscher07 by g²
    # (conventions="slicersim-1.0"); its Kubik16 formula already scaled as g².
    # With the Lazuli gain of 1 the conventions coincide.
    flux, nmd = np.array([1e-2, 1.0, 300.0]), (12, 4, 1)
    r1 = variance_rauscher07(flux, nmd, TF, 11.0, 0.02, gain=1.0)
    k1 = variance_kubik16(flux, nmd, TF, 11.0, 0.02, gain=1.0)
    np.testing.assert_allclose(variance_rauscher07(flux, nmd, TF, 11.0, 0.02, gain=2.5), r1 * 2.5**2, rtol=1e-13)
    np.testing.assert_allclose(variance_kubik16(flux, nmd, TF, 11.0, 0.02, gain=2.5), k1 * 2.5**2, rtol=1e-12)
    old = dict(conventions="slicersim-1.0")
    np.testing.assert_array_equal(variance_rauscher07(flux, nmd, TF, 11.0, 0.02, gain=1.0, **old), r1)
    np.testing.assert_allclose(variance_rauscher07(flux, nmd, TF, 11.0, 0.02, gain=2.5, **old), r1 / 2.5**2,
                               rtol=1e-13)
    np.testing.assert_allclose(variance_kubik16(flux, nmd, TF, 11.0, 0.02, gain=2.5, **old), k1 * 2.5**2,
                               rtol=1e-12)


@pytest.mark.parametrize("gain", [0.5, 2.0])
def test_snr_does_not_depend_on_gain(gain):
    """Physical convention: the band SNR of a target is independent of the gain (noise and
    signal both scale with g); slicersim 1.0 made it ∝ g² (SNR 80.9 instead of 20.2 at g = 2)."""
    from slicersim import LazuliSupernova
    sn = LazuliSupernova(1.0)
    band = (8000.0, 13600.0)
    ref = sn.simulation.get_band_snr(band, nmd=(56, 8, 0), nramps=4, frame="obs")
    sn.simulation.update(gain=gain)
    assert sn.simulation.get_band_snr(band, nmd=(56, 8, 0), nramps=4, frame="obs") == pytest.approx(ref, rel=1e-12)
    old = LazuliSupernova(1.0, conventions="slicersim-1.0")
    ref_old = old.simulation.get_band_snr(band, nmd=(56, 8, 0), nramps=4, frame="obs")
    old.simulation.update(gain=gain)
    assert old.simulation.get_band_snr(band, nmd=(56, 8, 0), nramps=4, frame="obs") == pytest.approx(ref_old * gain**2,
                                                                                         rel=1e-12)


# --------------------------------------------------------------------------- #
#  where the two models agree and where they depart                            #
# --------------------------------------------------------------------------- #
FLUXES = np.logspace(-3, 3, 601)   # e-/s per pixel


@pytest.mark.parametrize("ron, dark", [(12.0, 0.0), (10.0, 2.8e-3), (20.0, 1e-2)])
def test_models_agree_for_few_groups(ron, dark):
    # For n = 2 and 3 the least-squares slope is the maximum-likelihood one and
    # Kubik16 reproduces Rauscher07 (requirement: within 3 %).  Both library
    # models are checked point by point against the formulas written out by hand
    # (_rauscher_by_hand, _kubik_by_hand), so the agreement is not a bound copied
    # from the implementation's output.
    worst = 0.0
    for n in (2, 3):
        for m in (1, 4, 8):
            for d in (0, 2):
                r = variance_rauscher07(FLUXES, (n, m, d), TF, ron, dark)
                k = variance_kubik16(FLUXES, (n, m, d), TF, ron, dark)
                np.testing.assert_allclose(r, _rauscher_by_hand(FLUXES, n, m, d, TF, ron, dark), rtol=1e-12)
                np.testing.assert_allclose(k, _kubik_by_hand(FLUXES, n, m, d, TF, ron, dark, 1.0), rtol=1e-12)
                worst = max(worst, float(np.max(np.abs(k / r - 1))))
    assert worst < 0.03


def test_models_depart_for_many_groups():
    nmd = (64, 8, 0)
    n = nmd[0]
    m, d = nmd[1], nmd[2]
    # read-noise dominated (flux 1e-3 e-/s, σ = 12, no dark): Kubik16 keeps the
    # two-point read-noise term 2σ²/m while the least-squares term falls as
    # 12(n−1)σ²/(m n (n+1)): the ratio is the hand formulas' ratio, well above 2.
    ratio = float(variance_kubik16(1e-3, nmd, TF, 12.0, 0.0) / variance_rauscher07(1e-3, nmd, TF, 12.0, 0.0))
    hand = _kubik_by_hand(1e-3, n, m, d, TF, 12.0, 0.0, 1.0) / _rauscher_by_hand(1e-3, n, m, d, TF, 12.0, 0.0)
    assert ratio == pytest.approx(hand, rel=1e-12)
    assert ratio > 2
    # flux → 0: exactly the ratio of the read-noise terms, (2σ²/m) / (12(n−1)σ²/(m n (n+1)))
    #          = n (n+1) / (6 (n−1)) = 11.0053
    ratio0 = float(variance_kubik16(0.0, nmd, TF, 12.0, 0.0) / variance_rauscher07(0.0, nmd, TF, 12.0, 0.0))
    assert ratio0 == pytest.approx(n * (n + 1) / (6 * (n - 1)), rel=1e-3)
    # photon dominated (1000 e-/s): read noise is negligible and both are linear in S:
    #   Kubik16 → (n−1+α) S t_int/(n−1),  α = (1−m²)/(3m(m+d));  Rauscher07 → b S.
    # K/R → (n−1+α) t_int/(n−1) / b < 1: the maximum-likelihood estimator beats least squares.
    alpha = (1 - m**2) / (3 * m * (m + d))
    t_int = (n - 1) * (m + d) * TF
    b = _rauscher_by_hand(1.0, n, m, d, TF, 0.0, 0.0)
    limit = (n - 1 + alpha) * t_int / (n - 1) / b
    ratio_bright = float(variance_kubik16(1e3, nmd, TF, 12.0, 0.0) / variance_rauscher07(1e3, nmd, TF, 12.0, 0.0))
    assert ratio_bright == pytest.approx(limit, rel=1e-3)
    assert ratio_bright < 1


# --------------------------------------------------------------------------- #
#  readout bookkeeping                                                         #
# --------------------------------------------------------------------------- #
def test_readout_times_hand_values():
    t = readout_times((64, 8, 0), 2.83)
    assert t["nframes"] == 512                                         # 64·8 − 0
    assert t["exposure_time_per_ramp"] == pytest.approx(1448.96, rel=1e-14)     # 512·2.83
    assert t["integration_time_per_ramp"] == pytest.approx(1426.32, rel=1e-14)  # 63·8·2.83
    assert t["group_time"] == pytest.approx(22.64, rel=1e-14)          # 8·2.83
    t = readout_times((10, 4, 2), 2.83)
    assert t["nframes"] == 58                                          # 10·6 − 2
    assert t["exposure_time_per_ramp"] == pytest.approx(164.14, rel=1e-14)      # 58·2.83
    assert t["integration_time_per_ramp"] == pytest.approx(152.82, rel=1e-14)   # 9·6·2.83
    assert t["group_time"] == pytest.approx(16.98, rel=1e-14)          # 6·2.83


def test_detector_times_follow_nmd():
    det = Detector(nmd=(10, 4, 2), tframe=2.0)
    assert det.exposure_time_per_ramp == pytest.approx(58 * 2.0)
    assert det.integration_time_per_ramp == pytest.approx(9 * 6 * 2.0)


def test_data_volume():
    det = Detector()
    # nramps · n · 4096² pixels · 16 bit / 8e9 → GB
    assert det.data_volume((64, 8, 0), 1) == pytest.approx(64 * 4096**2 * 16 / 8e9, rel=1e-14)
    assert det.data_volume((64, 8, 0), 1) == pytest.approx(2.147483648, rel=1e-14)
    assert det.data_volume((10, 4, 2), 3) == pytest.approx(3 * 10 * 4096**2 * 16 / 8e9, rel=1e-14)
    assert det.data_volume((10, 4, 2), 3) == pytest.approx(1.00663296, rel=1e-14)
    # m and d do not change the number of stored groups
    assert det.data_volume((10, 1, 0), 3) == det.data_volume((10, 8, 5), 3)


def test_check_readout_returns_ints():
    nmd, r = check_readout((np.int64(16), 8.0, 0), 2.0)
    assert nmd == (16, 8, 0) and r == 2
    assert all(type(v) is int for v in nmd) and type(r) is int
    with pytest.raises(ReadoutError, match="exceeds max_group"):
        check_readout((65, 8, 0), 1, max_group=64)


# --------------------------------------------------------------------------- #
#  Rauscher07 is the variance of the least-squares slope of MACC group means   #
# --------------------------------------------------------------------------- #
def _ls_frame_weights(nmd, tf):
    """Weights w on the N_f frame reads such that the estimate = w · reads = slope · t_int."""
    n, m, d = nmd
    nframes = n * (m + d) - d
    groups = np.zeros((n, nframes))
    for j in range(n):
        groups[j, j * (m + d): j * (m + d) + m] = 1.0 / m
    tg = groups @ (np.arange(nframes) * tf)
    tc = tg - tg.mean()
    return (tc / np.sum(tc**2)) @ groups * (n - 1) * (m + d) * tf


@pytest.mark.parametrize("nmd", [(2, 8, 0), (3, 8, 0), (16, 8, 0), (10, 4, 2), (8, 1, 3), (64, 8, 0), (5, 3, 7)])
def test_rauscher07_exact_for_least_squares(nmd):
    # Var(w·reads) = σ² Σ w_k² + flux t_f Σ_{k≥1} (Σ_{j≥k} w_j)²: each frame has its own
    # read noise; the Poisson increment before frame k enters every later read.
    w = _ls_frame_weights(nmd, TF)
    tail = np.cumsum(w[::-1])[::-1]
    for flux, sigma in [(0.0, 12.0), (1.0, 12.0), (50.0, 5.0)]:
        exact = sigma**2 * np.sum(w**2) + flux * TF * np.sum(tail[1:] ** 2)
        assert variance_rauscher07(flux, nmd, TF, sigma, 0.0) == pytest.approx(exact, rel=1e-12)


@pytest.mark.parametrize("nmd, flux, sigma", [
    # photon dominated; the −2(m²−1)… term is 33 % of b here: without it the MC
    # variance is 46 σ away, with the uncorrected 2007 term (2m−1)(m−1) 32 σ away
    ((2, 8, 0), 50.0, 12.0),
    ((10, 4, 2), 5.0, 12.0),    # dropped frames
    ((8, 1, 3), 2.0, 12.0),     # m = 1 with drops
    ((16, 8, 0), 0.05, 12.0),   # read-noise dominated
])
def test_rauscher07_monte_carlo(nmd, flux, sigma):
    n, m, d = nmd
    nramps = 20000
    nframes = n * (m + d) - d
    rng = np.random.default_rng(20240 + 97 * n + 13 * m + d)
    charge = np.cumsum(rng.poisson(flux * TF, size=(nramps, nframes)), axis=1, dtype=float)
    reads = charge + rng.normal(0.0, sigma, size=(nramps, nframes))
    start = np.arange(n) * (m + d)
    idx = (start[:, None] + np.arange(m)[None, :]).ravel()
    group_means = reads[:, idx].reshape(nramps, n, m).mean(axis=2)
    times = (np.arange(nframes) * TF)[idx].reshape(n, m).mean(axis=1)
    tc = times - times.mean()
    slope = group_means @ tc / np.sum(tc**2)
    t_int = (n - 1) * (m + d) * TF
    estimate = slope * t_int
    var_mc = estimate.var(ddof=1)
    var_model = float(variance_rauscher07(flux, nmd, TF, sigma, 0.0))
    sigma_var = var_model * math.sqrt(2.0 / (nramps - 1))
    # unbiased: the mean estimate is the expected integrated charge
    assert abs(estimate.mean() - flux * t_int) < 5 * math.sqrt(var_model / nramps)
    assert abs(var_mc - var_model) < 4 * sigma_var, (var_mc, var_model, sigma_var)


def test_detector_scalars_accept_quantities():
    """Detector tframe [s], dark [e-/s], ron [e-], gain [ADU/e-], pixel size [µm], saturation [ADU]:
    a Quantity gives the same detector as the plain number in the documented unit; a wrong
    unit is a ParameterError naming the parameter."""
    import astropy.units as u
    from slicersim.errors import ParameterError
    from slicersim.instrument.detector import Detector
    plain = Detector(tframe=2.83, dark=0.01, ron=12.0, gain=1.5, pixel_size=10.0)
    quant = Detector(tframe=2830 * u.ms, dark=36.0 * u.electron / u.hour, ron=12 * u.electron,
                     gain=1.5 * u.adu / u.electron, pixel_size=0.01 * u.mm)
    for name in ("tframe", "dark", "ron", "gain", "pixel_size"):
        assert getattr(quant, name) == pytest.approx(getattr(plain, name), rel=1e-12)
    np.testing.assert_allclose(quant.pixel_variance(np.array([0.5, 5.0])), plain.pixel_variance(np.array([0.5, 5.0])),
                               rtol=1e-12)
    with pytest.raises(ParameterError, match=r"tframe must be in units convertible to s"):
        Detector(tframe=3 * u.m)
    with pytest.raises(ParameterError, match=r"ron \[electron\] must be in \[0, 10000\], got -1"):
        Detector(ron=-1.0)
    with pytest.raises(ParameterError, match="max_group"):
        Detector(max_group=2.5)


@pytest.mark.parametrize("key, value, match", [("ron", 1e300, r"ron \[electron\] must be in \[0, 10000\]"),
                                               ("gain", 1e300, r"gain \[adu / electron\] must be in \(0, 1000\]"),
                                               ("dark", 1e300, r"dark \[electron / s\] must be in \[0, 1e\+06\]"),
                                               ("tframe", 1e300, r"tframe \[s\] must be in \(0, 10000\]")])
def test_detector_numbers_beyond_their_physical_range_are_refused(key, value, match):
    """Detector(ron=1e300) was accepted; the ETC then overflowed squaring it (OverflowError)."""
    from slicersim.errors import ParameterError
    from slicersim.targets import LazuliSupernova
    with pytest.raises(ParameterError, match=match):
        Detector(**{key: value})
    sn = LazuliSupernova(redshift=1.0)
    with pytest.raises(ParameterError, match=match):
        sn.update(**{key: value})
    assert sn.setup_to_snr(20)["nmd"] == (49, 8, 0)              # unchanged and usable
