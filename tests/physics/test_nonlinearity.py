"""Nonlinearity (physics/nonlinearity.py): per-pixel M(Q), JWST-convention inverse, stcal."""
import numpy as np
import pytest

from slicersim.errors import EffectsError
from slicersim.physics import nonlinearity as nl

FW = 63535.0
P = nl.NonlinearityParameters()


def test_coefficients_statistics_and_keying():
    a = nl.nonlinearity_coefficients(3, (64, 256), P, FW)
    assert a.shape == (2, 64, 256) and a.dtype == np.float64
    deficit = -(a[0] * FW + a[1] * FW ** 2)                  # 1 − M(Q_fw)/Q_fw
    n = deficit.size
    assert abs(deficit.mean() - 0.05) < 4 * 0.005 / np.sqrt(n)
    assert deficit.std() == pytest.approx(0.005, rel=4 / np.sqrt(2 * n))
    share = -a[1] * FW ** 2 / deficit
    assert abs(share.mean() - 0.25) < 4 * 0.05 / np.sqrt(n)
    # keyed by the full-detector pixel: a window equals the same pixels of a larger map
    big = nl.nonlinearity_coefficients(3, (64, 512), P, FW)
    np.testing.assert_array_equal(big[:, :, :256], a)
    np.testing.assert_array_equal(nl.nonlinearity_coefficients(3, (64, 256), P, FW, rows=(20, 40)), a[:, 20:40])
    with pytest.raises(EffectsError, match="rows"):
        nl.nonlinearity_coefficients(3, (64, 256), P, FW, rows=(40, 20))
    assert not np.array_equal(nl.nonlinearity_coefficients(4, (64, 256), P, FW), a)


def test_round_trip_forward_inverse_below_1e4():
    a = nl.nonlinearity_coefficients(5, (32, 64), P, FW)
    for gain in (1.0, 0.5, 2.2):
        c = nl.inverse_coefficients(a[0], a[1], FW, gain)
        assert c.dtype == np.float32 and c.shape == (6, 32, 64) and np.all(c[0] == 0)
        q = np.linspace(0, FW, 2001)[1:, None, None]
        dn = gain * nl.measured_charge(q, a[0], a[1])
        err = np.abs(nl.apply_correction(dn, c) / (gain * q) - 1)
        assert err.max() < 1e-4
    # the truth: M(linear_charge(M)) = M
    m = np.linspace(0, 60000, 101)[:, None, None] + np.zeros((32, 64))
    np.testing.assert_allclose(nl.measured_charge(nl.linear_charge(m, a[0], a[1]), a[0], a[1]), m, rtol=1e-13,
                               atol=1e-9)


def test_interpolated_fit_equals_exact_fit():
    """Large maps use the (A2, A3)-interpolated fits: same coefficients as the exact per-pixel fit."""
    a = nl.nonlinearity_coefficients(8, (48, 512), P, FW)             # 24576 > EXACT_MAX_PIXELS
    assert a[0].size > nl.EXACT_MAX_PIXELS
    c = nl.inverse_coefficients(a[0], a[1], FW, 1.0)
    exact = nl.inverse_coefficients(a[0][:4], a[1][:4], FW, 1.0)
    np.testing.assert_allclose(c[1:, :4], exact[1:], rtol=2e-5)
    assert nl.check_invertible(a[0], a[1], FW, coeffs=c) < 1e-4


def test_stcal_linearity_correction_restores_linear_ramps():
    """stcal 1.20 linearity_correction with our coefficients on noiseless nonlinear ramps: < 0.1 %."""
    from stcal.linearity.linearity import linearity_correction
    ny, nx, ngroups, gain = 16, 24, 12, 1.0
    a = nl.nonlinearity_coefficients(11, (ny, nx), P, FW)
    coeffs = nl.inverse_coefficients(a[0], a[1], FW, gain)
    rate = np.linspace(200.0, 0.95 * FW / ngroups, ny * nx).reshape(ny, nx)       # e-/group
    q = rate[None] * np.arange(1, ngroups + 1)[:, None, None]                       # linear charge
    data = (gain * nl.measured_charge(q, a[0], a[1]))[None].astype(np.float32)    # (1, ng, ny, nx)
    assert np.max(1 - data[0, -1] / (gain * q[-1])) > 0.03                          # really nonlinear
    gdq = np.zeros(data.shape, np.uint8)
    pdq = np.zeros((ny, nx), np.uint32)
    lin_dq = np.zeros((ny, nx), np.uint32)
    flags = {"SATURATED": 2, "DO_NOT_USE": 1, "NO_LIN_CORR": 2 ** 20}
    out, new_pdq, _ = linearity_correction(data.copy(), gdq, pdq, coeffs, lin_dq, flags)
    rel = np.abs(out[0] / (gain * q) - 1)
    assert rel.max() < 1e-3
    assert np.all(new_pdq == 0)


def test_non_invertible_rejected():
    a2 = np.full((2, 2), -0.6 / FW)                           # dM/dQ = 1 − 1.2 Q/Q_fw < 0 near Q_fw
    a3 = np.zeros((2, 2))
    with pytest.raises(EffectsError, match="not invertible"):
        nl.check_invertible(a2, a3, FW)
    with pytest.raises(EffectsError, match="not invertible"):
        nl.inverse_coefficients(a2, a3, FW, 1.0)
    # positive cubic with a slope minimum inside the well
    a2 = np.array([-1.2 / FW])
    a3 = np.array([0.3 / FW ** 2])                           # slope 1 − 2.4 q + 0.9 q²: min < 0 at q = 1
    with pytest.raises(EffectsError):
        nl.check_invertible(a2, a3, FW)
    # invertible but too strong for a low-degree correction: misses the tolerance
    a2, a3 = np.array([-0.2 / FW]), np.array([-0.05 / FW ** 2])
    with pytest.raises(EffectsError, match="tolerance"):
        nl.inverse_coefficients(a2, a3, FW, 1.0, degree=3)
    with pytest.raises(EffectsError, match="finite"):
        nl.check_invertible(np.array([np.nan]), np.array([0.0]), FW)


def test_bad_parameters_rejected():
    for kw in ({"deficit": -0.01}, {"deficit": 0.5}, {"deficit_scatter": -1}, {"cubic_share": 1.5},
               {"degree": 2.5}, {"degree": 1}, {"tolerance": 0}):
        with pytest.raises(EffectsError):
            nl.NonlinearityParameters(**kw)
    with pytest.raises(EffectsError, match="full_well"):
        nl.nonlinearity_coefficients(1, (4, 4), P, -5.0)


def test_apply_correction_out_aliasing_dn_is_refused_or_correct():
    """``out=dn`` silently returned a wrong polynomial (Horner reads dn after overwriting it; up to 1e3 DN):
    refused with a ValueError, as a float32 or misshapen ``out``."""
    rng = np.random.default_rng(1)
    c = np.stack([rng.normal(0, 1, (3, 4)), 1 + rng.normal(0, 1e-3, (3, 4)), rng.normal(0, 1e-6, (3, 4))])
    x = rng.normal(1000, 100, (3, 4))
    ref = nl.apply_correction(x, c)
    y = x.copy()
    with pytest.raises(ValueError, match="sharing no memory"):
        nl.apply_correction(y, c, out=y)
    assert np.array_equal(y, x)                      # refused before anything was written
    for bad in (np.empty((3, 4), np.float32), np.empty((4, 3))):
        with pytest.raises(ValueError, match="float64 array of shape"):
            nl.apply_correction(x, c, out=bad)
    assert np.array_equal(nl.apply_correction(x, c, out=np.empty((3, 4))), ref)


def test_apply_correction_out_is_bit_identical_and_returned():
    rng = np.random.default_rng(2)
    for shape in [(1, 1), (1, 7), (5, 1), (2, 3, 4)]:
        c = np.stack([rng.normal(0, 1, shape[-2:]), 1 + rng.normal(0, 1e-3, shape[-2:]), rng.normal(0, 1e-6, shape[-2:])])
        c[2, 0, 0] = np.inf
        x = rng.normal(1000, 100, shape)
        with np.errstate(invalid="ignore", over="ignore"):
            ref = nl.apply_correction(x, c)
            out = np.empty(shape)
            assert nl.apply_correction(x, c, out=out) is out
        assert np.array_equal(out.view(np.uint8), ref.view(np.uint8))
