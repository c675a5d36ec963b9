"""Ramps → rates (slicersim.reduction.ramp_fit, kernels/ramp_fit.cl and its NumPy twin).

Physics checks with quantified Monte Carlo errors: exact rates on noiseless ramps, unbiased slopes
and unit pulls against the Rauscher07 variance (OLS) and the exact GLS variance computed here by
dense linear algebra, jump detection on simulated cosmic rays, saturation, reference-pixel and
nonlinearity corrections, and agreement with stcal (the JWST pipeline's fitter) on the same files.
"""
import logging
import os
import math

import numpy as np
import pytest
from conftest import flip_chunk_byte
from scipy.special import erfc

from slicersim.backends.ramp_fit import fit_block_numpy, fit_block_opencl, fit_constants
from slicersim.errors import ParameterError, RampFileError
from slicersim.io.rampfile import read_ramps
from slicersim.io.uncal import write_uncal_from_hdf5
from slicersim.physics.nonlinearity import inverse_coefficients, measured_charge
from slicersim.physics.readout import readout_times, variance_rauscher07
from slicersim.products.ramps import simulate
from slicersim.reduction.ramp_fit import fit_ramps
import subprocess
import sys

TF = 2.83
QUIET = dict(progress=False, dark=0.0, roic_glow=0.0)


def group_times(nmd, tframe=TF):
    """Mean time of each group's reads [s] (first read one frame after the reset)."""
    n, m, d = nmd
    return (np.arange(n) * (m + d) + (m + 1) / 2.0) * tframe


def gls_variance(rate, nmd, ron, tframe=TF):
    """Exact GLS slope variance [e-²/s²] of one ramp with an intercept, from the covariance of group
    means built read by read: Cov(Q̄_j, Q̄_k) = λ·mean_ab min(t_ja, t_kb) + (σ²/m + 1/12) δ_jk."""
    n, m, d = nmd
    reads = (np.arange(n)[:, None] * (m + d) + np.arange(m)[None, :] + 1.0) * tframe
    cov = rate * np.minimum(reads[:, None, :, None], reads[None, :, None, :]).mean(axis=(2, 3))
    cov += np.eye(n) * (ron**2 / m + 1.0 / 12.0)
    X = np.stack([np.ones(n), group_times(nmd, tframe)], axis=1)
    return np.linalg.inv(X.T @ np.linalg.solve(cov, X))[1, 1]


# ----------------------------------------------------------------------------- exactness and twins
@pytest.mark.parametrize("weighting", ["gls", "ols"])
@pytest.mark.parametrize("backend", ["numpy", "opencl"])
def test_noiseless_ramps_give_the_rates_to_float_precision(weighting, backend):
    """Exactly linear float ramps (2 integrations, d > 0, gain 1.7, an excluded group, a flagged jump,
    saturated tails): the rate is the truth to 1e-13 relative, no jump is found, DQ says what was flagged."""
    nmd, gain = (10, 4, 1), 1.7
    rate = np.linspace(0.0, 900.0, 12 * 16).reshape(12, 16)
    sci = 2000.0 + gain * rate[None, None] * group_times(nmd)[None, :, None, None]
    sci = np.concatenate([sci, sci + 7.0])                               # second integration, other offset
    gdq = np.zeros(sci.shape, np.uint8)
    gdq[0, 4, 2] = 1                                                     # a DO_NOT_USE group mid-ramp
    gdq[1, 6, 3] = 4                                                     # a jump flagged upstream
    gdq[:, 7:, 5] = 2                                                    # saturated tail
    attrs = dict(NFRAMES=4, GROUPGAP=1, TFRAME=TF, GAIN=gain, READNOISE=0.0, NGROUPS=10, NINTS=2)
    r = fit_ramps((sci, gdq, None, attrs), weighting=weighting, backend=backend)
    assert np.max(np.abs(r.rate - rate) / np.maximum(rate, 1.0)) < 1e-13
    assert r.njumps.sum() == 16 and not r.njumps[[0, 1, 2, 4, 5]].any()   # row 3: the upstream flag only
    assert np.all(r.dq[5] == 2) and np.all(r.dq[3] == 4) and not r.dq[[0, 1, 2, 4]].any()
    assert np.all(r.variance[1:] > 0) and np.allclose(r.variance, r.var_poisson + r.var_rnoise, rtol=1e-14)
    assert np.all(r.var_rnoise == 0.0)                                   # no read noise


def test_noiseless_nonlinear_ramps_are_linearised():
    """Noiseless reads through M(Q) = Q + a₂Q² + a₃Q³ (m = 1): with the JWST inverse coefficients the
    rates come back to the correction's tolerance (< 3e-4); uncorrected they are low (> 2 % for the brightest)."""
    nmd, full_well = (8, 1, 0), 60000.0
    rate = np.tile(np.geomspace(50.0, 2500.0, 32), (4, 1))               # up to ~50 000 e- at the end
    a2, a3 = np.full(rate.shape, -0.04 / full_well), np.full(rate.shape, -0.01 / full_well**2)
    q = rate[None, None] * group_times(nmd)[None, :, None, None]
    sci = 1000.0 + measured_charge(q, a2, a3)
    coeffs = inverse_coefficients(a2, a3, full_well, 1.0)
    attrs = dict(NFRAMES=1, GROUPGAP=0, TFRAME=TF, GAIN=1.0, READNOISE=0.0, BIAS=1000.0)
    plain = fit_ramps((sci, None, None, attrs), linearity=False, jump_threshold=None)
    fixed = fit_ramps((sci, None, None, attrs), linearity=coeffs)
    assert fixed.attrs["LINEARITY"] == "user" and fixed.attrs["SUPERBIAS"] == "BIAS keyword"
    assert np.max(np.abs(fixed.rate / rate - 1)) < 3e-4
    assert np.max(1 - plain.rate / rate) > 0.02 and np.all(plain.rate < rate)


def _messy_block(seed=1, nints=3, n=14, npix=3000):
    rng = np.random.default_rng(seed)
    rate = 10 ** rng.uniform(-1, 3, npix)
    t = group_times((n, 4, 1))
    sci = 2000 + rate[None, None] * t[None, :, None] + rng.normal(0, 6, (nints, n, npix))
    hits = rng.random((nints, n, npix)) < 0.01
    sci += np.cumsum(hits * rng.uniform(30, 3000, hits.shape), axis=1)
    sci = np.clip(np.rint(sci), 0, 65535).astype(np.uint16)
    gdq = np.zeros(sci.shape, np.uint8)
    gdq[:, 3][rng.random((nints, npix)) < 0.05] |= 1
    gdq[:, 9][rng.random((nints, npix)) < 0.05] |= 4
    return sci, gdq, rng.integers(0, 2, npix).astype(np.uint32) * 1024


@pytest.mark.parametrize("weighting", ["gls", "ols"])
def test_kernel_matches_numpy_twin_at_several_chunkings(weighting):
    """Cosmic-ray jumps, saturation (at 40 000 DN), DO_NOT_USE groups, upstream jump flags, 3
    integrations, uint16 and float64 input: the kernel and the twin agree to 1e-12 relative with the
    same flags, and fit_ramps gives the same product for row blocks of 1, 7 and all rows."""
    sci, gdq, pdq = _messy_block()
    k = fit_constants((14, 4, 1), TF, 1.0, 12.0, 1 / 12, 40000, 4.0, weighting)
    for data in (sci, sci.astype(np.float64)):
        ref, cl = fit_block_numpy(data, gdq, pdq, k), fit_block_opencl(data, gdq, pdq, k)
        ok = np.isfinite(ref[0][0])
        assert ok.mean() > 0.95 and ref[2].sum() > 500 and (ref[1] & 2).any()
        assert np.array_equal(np.isfinite(cl[0]), np.isfinite(ref[0]))
        assert np.max(np.abs(cl[0][:, ok] - ref[0][:, ok]) / np.abs(ref[0][:, ok]).clip(1e-300)) < 1e-12
        for a, b in zip(cl[1:], ref[1:]):
            assert np.array_equal(a, b)
    attrs = dict(NFRAMES=4, GROUPGAP=1, TFRAME=TF, GAIN=1.0, READNOISE=12.0, SATURATION=40000.0)
    arrays = (sci.reshape(3, 14, 60, 50), gdq.reshape(3, 14, 60, 50), pdq.reshape(60, 50), attrs)
    per_row = 50 * (3 * 14 * 8 + 96)                                 # uint16 SCI, GROUPDQ returned
    products = [fit_ramps(arrays, weighting=weighting, backend=be, max_bytes=per_row * rows, return_groupdq=True)
                for be, rows in (("numpy", 60), ("opencl", 1), ("opencl", 7), ("opencl", 60))]
    for p in products[1:]:
        assert np.array_equal(p.rate, products[0].rate, equal_nan=True)
        assert np.array_equal(p.dq, products[0].dq) and np.array_equal(p.groupdq, products[0].groupdq)


@pytest.mark.parametrize("weighting", ["gls", pytest.param("ols", marks=pytest.mark.slow)])
def test_every_vector_width_gives_the_same_bits(weighting):
    """The kernel fits VW pixels per work item (lanes of vector types, 8 by default on CPUs, 1 on
    GPUs): every width gives bit for bit the results of the scalar kernel (VW = 1) on the messy
    block — jumps, saturation, DO_NOT_USE and upstream flags, 3 integrations (the GLS pass reloads
    the used flags), uint16 and float64 — including a last work item with fewer valid pixels than
    lanes (npix = 2999, not a multiple of any width); a lane past the end is never stored."""
    sci, gdq, pdq = (a[..., :2999] for a in _messy_block())
    k = fit_constants((14, 4, 1), TF, 1.0, 12.0, 1 / 12, 40000, 4.0, weighting)
    for data in (sci, sci.astype(np.float64)):
        scalar = fit_block_opencl(data, gdq, pdq, k, vector_width=1)
        assert scalar[2].sum() > 500 and (scalar[1] & 2).any()
        for vw in (2, 4, 8, 16, None):
            out = tuple(np.full(3000, -7.0) for _ in range(4)) + (np.zeros(3000, np.uint32), np.zeros(3000, np.int32))
            got = fit_block_opencl(data, gdq, pdq, k, vector_width=vw, out=tuple(a[:2999] for a in out))
            assert np.array_equal(np.asarray(got[0]), scalar[0], equal_nan=True), vw
            for a, b in zip(got[1:], scalar[1:]):
                assert np.array_equal(a, b), vw
            assert all(a[-1] == -7.0 for a in out[:4]) and out[4][-1] == 0 and out[5][-1] == 0
    for bad in (3, 0, 32, True, 8.0, "8"):
        with pytest.raises(ParameterError, match="vector_width"):
            fit_block_opencl(sci, gdq, pdq, k, vector_width=bad)


def test_the_kernel_writes_a_callers_images_in_place():
    """``out=``: fit_ramps hands the kernel its own rate images (no copy of each block, no fresh
    memory: first touches of memory cost 2 ms/MB on the 2-core VM).  The results land in those
    arrays, equal to the twin's, and anything but six writeable (npix,) arrays of the kernel's
    dtypes is refused before a launch."""
    sci, gdq, pdq = _messy_block()
    k = fit_constants((14, 4, 1), TF, 1.0, 12.0, 1 / 12, 40000, 4.0, "gls")
    npix = sci.shape[2]
    out = tuple(np.full(npix, -7.0) for _ in range(4)) + (np.zeros(npix, np.uint32), np.zeros(npix, np.int32))
    fit, dq, nj, _ = fit_block_opencl(sci, gdq, pdq, k, out=out)
    ref = fit_block_numpy(sci, gdq, pdq, k)
    assert all(a is b for a, b in zip((*fit, dq, nj), out))
    ok = np.isfinite(ref[0][0])
    assert np.array_equal(np.isfinite(out[0]), ok) and not np.any(out[0] == -7.0)
    for got, want in zip(out[:4], ref[0]):
        assert np.allclose(got[ok], want[ok], rtol=1e-12, atol=0)
    assert np.array_equal(out[4], ref[1]) and np.array_equal(out[5], ref[2])
    for bad in (out[:5], (out[0][:-1],) + out[1:], (out[0].astype(np.float32),) + out[1:],
                out[:4] + (out[5], out[4]), (np.empty(2 * npix)[::2],) + out[1:]):
        with pytest.raises(ValueError, match="six writeable"):
            fit_block_opencl(sci, gdq, pdq, k, out=bad)


def test_pipelined_blocks_keep_their_own_results_on_the_device_copy_path(monkeypatch):
    """fit_ramps launches block k+1's kernel before it fetches block k's results (wait=False).  On a
    GPU (device buffers reused between blocks, no zero copy) the results were read after the next
    kernel had overwritten the buffers: every block but the last got the next block's rates (H200
    runs 6-7: a 4096² reduction's pulls -945 +- 60780, while a one-block 16-row strip was exact).
    PoCL takes that path with read-only inputs, and fit_ramps takes it everywhere when the device
    reads as a GPU: pipelined blocks sharing a workspace each give their own twin results."""
    from slicersim.backends import opencl
    from slicersim.backends import ramp_fit as backend_fit
    k = fit_constants((14, 4, 1), TF, 1.0, 12.0, 1 / 12, 40000, 4.0, "gls")
    blocks = [_messy_block(seed=s, npix=1000) for s in (1, 2, 3)]
    for block in blocks:
        for a in block:
            a.setflags(write=False)                       # not zero-copy: the GPU's device-copy path
    workspace = {}
    pending = [fit_block_opencl(*b, k, workspace=workspace, wait=False) for b in blocks]
    for finish, block in zip(pending, blocks):
        got, ref = finish(), fit_block_numpy(*block, k)
        assert np.array_equal(got[0], ref[0], equal_nan=True) or np.nanmax(
            np.abs(got[0] - ref[0]) / np.abs(ref[0]).clip(1e-300)) < 1e-12
        for a, b in zip(got[1:], ref[1:]):
            assert np.array_equal(a, b)
    sci, gdq, pdq = _messy_block()
    attrs = dict(NFRAMES=4, GROUPGAP=1, TFRAME=TF, GAIN=1.0, READNOISE=12.0, SATURATION=40000.0)
    arrays = (sci.reshape(3, 14, 60, 50), gdq.reshape(3, 14, 60, 50), pdq.reshape(60, 50), attrs)
    per_row = 50 * (3 * 14 * 8 + 96)
    ref = fit_ramps(arrays, backend="numpy", return_groupdq=True)
    monkeypatch.setattr(backend_fit.opencl, "device_type", lambda dev=None: "GPU")
    assert backend_fit.opencl is opencl
    for rows in (1, 7):
        got = fit_ramps(arrays, backend="opencl", max_bytes=per_row * rows, return_groupdq=True)
        ok = np.isfinite(ref.rate)
        assert np.array_equal(np.isfinite(got.rate), ok)
        assert np.max(np.abs(got.rate[ok] - ref.rate[ok]) / np.abs(ref.rate[ok]).clip(1e-300)) < 1e-12
        assert np.array_equal(got.dq, ref.dq) and np.array_equal(got.groupdq, ref.groupdq)
        assert np.array_equal(got.njumps, ref.njumps)


# ----------------------------------------------------------------------------- noisy ramps
def test_white_noise_slopes_are_unbiased_with_unit_pulls(tmp_path):
    """Poisson + white read noise, MACC(24,4,1), 4 rates × 8192 pixels, jump detection on: for each
    rate the mean slope is the truth within 4 σ of its Monte Carlo error; pulls have width 1 ± 0.05
    against Rauscher07 at the true rate (OLS) and against the exact GLS variance (GLS, computed here
    by dense linear algebra); the OLS variance is Rauscher07 at the fitted rate to 1e-12; GLS beats
    OLS where Poisson noise matters; the reported errors give unit pulls from 3 e-/s up; false jumps
    stay below 3× the Gaussian rate of 4 σ two-sided excursions."""
    nmd, ron = (24, 4, 1), 10.0
    rates = np.array([0.3, 3.0, 30.0, 150.0])                          # 150 e-/s: 49 000 e- at the end
    truth = np.repeat(rates, 32)[:, None] * np.ones((1, 256))
    path = simulate(truth, nmd, seed=21, out=tmp_path / "white.h5", ron=ron, **QUIET)
    tint = readout_times(nmd, TF)["integration_time_per_ramp"]
    ron_eff = math.sqrt(ron**2 + nmd[1] / 12.0)                        # ± ½ ADU rounding of each group mean
    fits = {w: fit_ramps(path, weighting=w) for w in ("ols", "gls")}
    ndiff = truth.size * (nmd[0] - 1)
    false_rate = fits["gls"].njumps.sum() / ndiff
    print(f"false jumps per difference {false_rate:.2e} (Gaussian 4σ: {erfc(4 / math.sqrt(2)):.2e})")
    assert false_rate < 3 * erfc(4 / math.sqrt(2))
    ols_var = variance_rauscher07(np.maximum(fits["ols"].rate, 0), nmd, TF, ron_eff, 0.0) / tint**2
    clean = fits["ols"].njumps == 0
    assert np.allclose(fits["ols"].variance[clean], ols_var[clean], rtol=1e-12, atol=0)
    for i, lam in enumerate(rates):
        rows = slice(32 * i, 32 * (i + 1))
        exact = {"ols": variance_rauscher07(lam, nmd, TF, ron_eff, 0.0) / tint**2, "gls": gls_variance(lam, nmd, ron)}
        for w, product in fits.items():
            est = product.rate[rows].ravel()
            npix = est.size
            pull = (est - lam) / math.sqrt(exact[w])
            reported = (est - lam) / product.err[rows].ravel()
            print(f"{w} {lam:6.1f} e-/s: mean pull {pull.mean():+.4f} (±{1 / math.sqrt(npix):.4f}), width "
                  f"{pull.std():.4f} (±{1 / math.sqrt(2 * npix):.4f}); reported-error pulls width {reported.std():.4f}")
            assert abs(pull.mean()) < 4 / math.sqrt(npix)
            assert abs(pull.std() - 1.0) < 0.05
            if lam >= 3.0:
                assert abs(reported.std() - 1.0) < 0.05
        if lam >= 30.0:
            assert exact["gls"] < 0.95 * exact["ols"]
            assert fits["gls"].rate[rows].std() < 0.975 * fits["ols"].rate[rows].std()


def test_cosmic_ray_jumps_are_found_and_removed(tmp_path):
    """Simulated cosmic rays (300 cm⁻² s⁻¹): ≥ 95 % of the hits above 10 σ of the difference noise
    are flagged in GROUPDQ, < 0.1 % false flags per pixel-group; rates of hit pixels keep pulls of
    width < 1.2 (without detection > 3)."""
    nmd, ron, lam = (20, 4, 0), 12.0, 2.0
    fx = {"effects": {"enabled": ["cosmic_rays"], "cosmic_rays": {"rate": 300.0}}}
    path = simulate(np.full((128, 128), lam), nmd, seed=8, out=tmp_path / "cr.h5", ron=ron, effects=fx, **QUIET)
    with_det = fit_ramps(path, return_groupdq=True, with_truth=True)
    without = fit_ramps(path, jump_threshold=None)
    import h5py
    with h5py.File(path, "r") as fh:
        hits = fh["truth/cosmic_rays"][...]
    n, m, d = nmd
    flagged = (with_det.groupdq[0] & 4) != 0
    group = np.minimum(hits["frame"] // (m + d), n - 1)
    seen = hits["frame"] < n * (m + d) - d
    sigma_diff = math.sqrt(2 * ron**2 / m + lam * (m + d) * TF)
    big = seen & (hits["electrons"] > 10 * sigma_diff) & (group >= 1)
    g, y, x = group[big], hits["y"][big], hits["x"][big]
    found = flagged[g, y, x] | flagged[np.minimum(g + 1, n - 1), y, x]
    touched = np.zeros(flagged.shape, bool)
    touched[group[seen], hits["y"][seen], hits["x"][seen]] = True
    touched[np.minimum(group[seen] + 1, n - 1), hits["y"][seen], hits["x"][seen]] = True
    false = flagged & ~touched
    print(f"jumps: {found.mean():.4f} of {big.sum()} big hits found; false flags {false.mean():.2e}")
    assert big.sum() > 500 and found.mean() >= 0.95 and false.mean() < 1e-3
    hit_px = np.zeros((128, 128), bool)
    hit_px[y, x] = True
    pull_with = ((with_det.rate - lam) / with_det.err)[hit_px]
    pull_without = ((without.rate - lam) / without.err)[hit_px]
    print(f"hit pixels: pull width {pull_with.std():.3f} with detection, {pull_without.std():.1f} without")
    assert pull_with.std() < 1.2 and pull_without.std() > 3
    assert np.all((with_det.dq[hit_px & (with_det.njumps > 0)] & 4) != 0)


def test_saturated_groups_are_excluded(tmp_path):
    """800 e-/s pixels saturate mid-ramp: unbiased rates (4 σ of the Monte Carlo error) and unit pulls
    from the unsaturated groups, DQ SATURATED; 1e5 e-/s pixels saturate in the first group: NaN and
    DO_NOT_USE; faint pixels are never flagged."""
    nmd = (10, 4, 0)
    rate = np.concatenate([np.full((20, 100), 800.0), np.full((20, 100), 20.0), np.full((2, 100), 1e5)])
    path = simulate(rate, nmd, seed=4, out=tmp_path / "sat.h5", ron=10.0, **QUIET)
    r = fit_ramps(path)
    bright = r.rate[:20]
    sem = bright.std() / math.sqrt(bright.size)
    assert abs(bright.mean() - 800.0) < 4 * sem
    assert abs(((bright - 800.0) / r.err[:20]).std() - 1) < 0.1
    assert np.all(r.dq[:20] & 2) and not (r.dq[20:40] & 3).any()
    assert np.all(np.isnan(r.rate[40:])) and np.all(r.dq[40:] == 3)
    import h5py
    written = r.write(tmp_path / "rate.h5")
    with h5py.File(written, "r") as fh:
        # the images are stored in float32 (as JWST rate files): the rates to their float32 rounding
        assert fh["RATE"].dtype == fh["VAR"].dtype == np.float32
        assert np.array_equal(fh["RATE"][...], r.rate.astype(np.float32), equal_nan=True)
        assert np.array_equal(fh["DQ"][...], r.dq)
        assert fh.attrs["BUNIT"] == "e-/s" and fh.attrs["WEIGHTING"] == "gls"
    with pytest.raises(RampFileError, match="exists"):
        r.write(written)


# ----------------------------------------------------------------------------- corrections and formats
def test_reference_pixel_and_nonlinearity_corrections(tmp_path):
    """A ramp with nonlinearity, reference pixels (per-output and per-pixel bias) and a 30 e- per-output
    pedestal drift: uncorrected, bright rates are > 2 % low and pulls are > 2 wide; with the default
    corrections (reference pixels, truth bias and coefficients, found in the file) the bright bias is
    < 1e-3 and the pulls are 1 ± 0.1.  The JWST level-1b copy gives the same rates."""
    nmd, ny, nx = (12, 4, 0), 64, 256
    rate = np.tile(np.geomspace(2.0, 900.0, nx), (ny, 1))
    fx = {"effects": {"enabled": ["nonlinearity", "reference_pixels", "correlated_noise"],
                      "correlated_noise": {"pedestal": 30.0, "c_pink": 0.0, "u_pink": 0.0, "acn": 0.0,
                                           "picture_frame": 0.0}}}
    path = simulate(rate, nmd, seed=5, out=tmp_path / "fx.h5", ron=6.0, effects=fx, **QUIET)
    raw = fit_ramps(path, refpix=False, linearity=False, with_truth=True)
    fixed = fit_ramps(path, with_truth=True)
    assert fixed.attrs["REFPIX"] and fixed.attrs["LINEARITY"] == "truth" and fixed.attrs["SUPERBIAS"] == "truth/bias"
    inner = np.zeros((ny, nx), bool)
    inner[4:-4, 4:-4] = True
    good = inner & (fixed.dq == 0)
    bright = good & (fixed.truth_rate > 300)
    for label, r in (("raw", raw), ("corrected", fixed)):
        pull = ((r.rate - r.truth_rate) / r.err)[good]
        print(f"{label}: bright bias {np.median(r.rate[bright] / r.truth_rate[bright] - 1):+.2e}, pull width {pull.std():.3f}")
    assert np.median(1 - raw.rate[bright] / raw.truth_rate[bright]) > 0.02
    assert ((raw.rate - raw.truth_rate) / raw.err)[good].std() > 2
    assert abs(np.median(fixed.rate[bright] / fixed.truth_rate[bright] - 1)) < 1e-3
    assert abs(((fixed.rate - fixed.truth_rate) / fixed.err)[good].std() - 1) < 0.1
    fits_path = write_uncal_from_hdf5(path, tmp_path / "fx.fits", groupdq_flags="truth")    # the same flags
    same = fit_ramps(fits_path, with_truth=True)
    assert same.attrs["FORMAT"] == "jwst-uncal" and np.array_equal(same.rate, fixed.rate, equal_nan=True)
    assert np.array_equal(same.dq, fixed.dq) and np.array_equal(same.truth_rate, fixed.truth_rate)


# ----------------------------------------------------------------------------- stcal
JWST_DQ = {"GOOD": 0, "DO_NOT_USE": 1, "SATURATED": 2, "JUMP_DET": 4, "PERSISTENCE": 32,
           "CHARGELOSS": 128, "NO_GAIN_VALUE": 524288, "UNRELIABLE_SLOPE": 16777216}


def _stcal(path, groupdq, readnoise_cds, algorithm="OLS_C", scale=1.0):
    """stcal's rate image (slope, err, var_rnoise) [DN/s] of a ramp file with the given GROUPDQ; the data
    and read noise are divided by ``scale`` (a power of 2: exact in float32) and the slope multiplied back,
    which keeps stcal's variances clear of its 1e6 DN²/s² cut-off."""
    import stcal.ramp_fitting.ramp_fit as stcal_fit
    from stcal.ramp_fitting.ramp_fit_class import RampData
    sci, _, pdq, attrs = read_ramps(path)
    ramp = RampData()
    ramp.set_arrays(sci.astype(np.float32) / np.float32(scale), groupdq.copy(), pdq.copy(), np.zeros(pdq.shape, np.float32))
    ramp.set_meta(name="NIRSPEC", frame_time=float(attrs["TFRAME"]), group_time=float(attrs["TGROUP"]),
                  groupgap=int(attrs["GROUPGAP"]), nframes=int(attrs["NFRAMES"]), drop_frames1=None)
    ramp.set_dqflags(JWST_DQ)
    ramp.start_row, ramp.num_rows = 0, sci.shape[2]
    ramp.suppress_one_group_ramps = True                    # as ours: a lone group gives no slope
    ramp.rejection_threshold = None                          # LIKELY: use the jumps flagged in GROUPDQ
    ramp.average_dark_current = np.zeros(pdq.shape, np.float32)
    gain = np.ones(pdq.shape, np.float32)
    rn = np.broadcast_to(np.asarray(readnoise_cds / scale, np.float32), pdq.shape).copy()
    logging.disable(logging.WARNING)
    try:
        image, _, _ = stcal_fit.ramp_fit_data(ramp, False, rn, gain, algorithm, "optimal", "none")
    finally:
        logging.disable(logging.NOTSET)
    slope, err, var_r = (image["slope"], image["err"], image["var_rnoise"]) if isinstance(image, dict) else \
        (image[0], image[4], image[3])
    return slope * scale, err * scale, var_r * scale**2


def test_rates_agree_with_stcal(tmp_path):
    """Same file (2 integrations, cosmic rays, saturation), same GROUPDQ (ours, with our jump flags),
    stcal told to drop one-group integrations as we do:

    * OLS vs stcal OLS_C with its weighting power forced to 0 (a per-pixel read noise making every
      segment's SNR < 5): the same estimator, so equal to stcal's float32 rounding, |Δ| < 1e-4 σ on
      every pixel (segments split at jumps and saturation, integrations combined alike);
    * GLS vs stcal LIKELY (Brandt 2024: also GLS with the exact covariance of group means) on the
      pixels without jumps or saturation (LIKELY drops both differences next to a flagged group and
      weights integrations its own way): they differ only in the rate put in the covariance,
      rms(Δ) < 0.1 σ overall and < 0.01 σ above 1 e-/s, where that rate is well measured;
    * GLS vs stcal OLS_C optimal (Fixsen power-law weights, an approximation of the optimal ones),
      all pixels: rms(Δ) < 0.25 σ, no mean offset (4 s.e.m.)."""
    rng = np.random.default_rng(3)
    rate = np.repeat(10 ** rng.uniform(-1, 2, 48), 96).reshape(48, 96)
    rate[:2] = 1500.0                                                    # saturate mid-ramp
    fx = {"effects": {"enabled": ["cosmic_rays"], "cosmic_rays": {"rate": 100.0}}}
    path = simulate(rate, (12, 4, 1), nramps=2, seed=19, out=tmp_path / "s.h5", ron=10.0, effects=fx, **QUIET)
    ols = fit_ramps(path, weighting="ols", return_groupdq=True)
    gls = fit_ramps(path, return_groupdq=True)
    assert ols.njumps.sum() > 50 and np.all(ols.dq[:2] & 2)
    sci = read_ramps(path)[0].astype(float)
    usable = (ols.groupdq & 3) == 0
    span = np.where(usable, sci, -np.inf).max(axis=(0, 1)) - np.where(usable, sci, np.inf).min(axis=(0, 1))
    power0_rn = 6.0 * (span + 10.0) * math.sqrt(2 * 4)                # stcal divides by √(2·nframes)
    s0, _, _ = _stcal(path, ols.groupdq, power0_rn, scale=1024.0)
    ok = np.isfinite(s0)
    assert ok.mean() > 0.99 and np.array_equal(ok, np.isfinite(ols.rate))
    d0 = np.abs(ols.rate - s0)[ok] / ols.err[ok]
    cds = math.sqrt(2.0) * math.sqrt(10.0**2 + 4 / 12.0)
    s_likely, _, _ = _stcal(path, gls.groupdq, cds, "LIKELY")
    s_opt, _, _ = _stcal(path, gls.groupdq, cds)
    print(f"OLS vs stcal power 0: max |Δ|/σ {d0.max():.1e}")
    assert d0.max() < 1e-4
    clean = (gls.njumps == 0) & (gls.dq == 0)
    d_likely = ((gls.rate - s_likely) / gls.err)[clean]
    bright = rate[clean] > 1.0
    print(f"GLS vs stcal LIKELY ({clean.sum()} clean px): rms {d_likely.std():.4f}, above 1 e-/s "
          f"{d_likely[bright].std():.4f}")
    assert clean.mean() > 0.8 and d_likely.std() < 0.1 and d_likely[bright].std() < 0.01
    good = np.isfinite(gls.rate)
    d = (gls.rate - s_opt)[good] / gls.err[good]
    print(f"GLS vs stcal OLS_C optimal: mean {d.mean():+.4f} (±{d.std() / math.sqrt(d.size):.4f}), rms {d.std():.4f}")
    assert np.array_equal(np.isfinite(s_opt), good) and d.std() < 0.25
    assert abs(d.mean()) < 4 * d.std() / math.sqrt(d.size)


# ----------------------------------------------------------------------------- bad input
def test_bad_input_gives_one_clear_error(tmp_path):
    import h5py
    path = simulate(np.full((16, 32), 5.0), (4, 2, 0), seed=1, out=tmp_path / "ok.h5", truth=False, **QUIET)
    sci, gdq, pdq, attrs = read_ramps(path)
    text = tmp_path / "notes.txt"
    text.write_text("not a ramp")
    with h5py.File(tmp_path / "other.h5", "w") as fh:
        fh["data"] = np.zeros(3)
        fh.attrs["COMPLETE"] = True
    with h5py.File(tmp_path / "partial.h5", "w") as fh:
        fh["SCI"] = sci
        fh.attrs["COMPLETE"] = False
    from astropy.io import fits
    fits.HDUList([fits.PrimaryHDU(np.zeros((2, 2)))]).writeto(tmp_path / "image.fits")
    cases = [
        (text, {}, "neither an HDF5 ramp file nor a JWST level-1b"),
        (tmp_path / "other.h5", {}, "not a slicersim ramp file"),
        (tmp_path / "image.fits", {}, "no SCI extension"),
        (tmp_path / "partial.h5", {}, "incomplete file"),
        (tmp_path / "missing.h5", {}, "cannot read"),
        (path, {"with_truth": True}, "no truth/rate"),
        (path, {"linearity": "truth"}, "no truth/nonlinearity/inverse_coefficients"),
        ((sci, gdq, pdq, {**attrs, "NGROUPS": 5}), {}, "NGROUPS = 5 but SCI has 4"),
        ((sci, gdq, pdq, {**attrs, "TGROUP": 9.0}), {}, "TGROUP = 9.0 s but"),
        ((sci, gdq, pdq, {**attrs, "READPATT": "MACC(4,4,0)"}), {}, "READPATT = MACC"),
        ((sci, gdq, pdq, {k: v for k, v in attrs.items() if k != "NFRAMES"}), {}, "missing: NFRAMES"),
        ((sci, gdq, pdq, {k: v for k, v in attrs.items() if k != "GAIN"}), {}, r"GAIN \(or pass gain=\)"),
        ((sci, gdq, pdq, {**attrs, "NFRAMES": 2.5}), {}, "NFRAMES = 2.5 is not an integer"),
        ((sci[0], gdq, pdq, attrs), {}, "4-D"),
        ((sci, gdq[:, :2], pdq, attrs), {}, "do not match SCI"),
    ]
    for source, kwargs, message in cases:
        with pytest.raises(RampFileError, match=message):
            fit_ramps(source, **kwargs)
    with pytest.raises(ParameterError, match="weighting"):
        fit_ramps(path, weighting="optimal")
    with pytest.raises(ParameterError, match="jump_threshold"):
        fit_ramps(path, jump_threshold=-1)
    with pytest.raises(ParameterError, match="superbias"):
        fit_ramps(path, refpix=True, superbias="2000")
    with pytest.raises(MemoryError, match="below one detector row"):
        fit_ramps(path, max_bytes=100)


def test_fit_options_object_equals_the_keyword_form(tmp_path):
    """fit_ramps(path, FitOptions(...)) is fit_ramps(path, **keywords); unknown keywords, bad values and
    options mixed with keywords are ParameterErrors naming the parameter; the signature still lists
    every keyword and FIT_DEFAULTS holds the defaults as data."""
    import inspect

    from slicersim.reduction.ramp_fit import FIT_DEFAULTS, FitOptions
    rate = np.full((16, 12), 30.0)
    path = simulate(rate, (6, 2, 0), seed=2, out=tmp_path / "r.h5", ron=8.0, **QUIET)
    for backend in ("numpy", "opencl"):
        a = fit_ramps(path, weighting="ols", jump_threshold=5.0, backend=backend, max_bytes=4096)
        b = fit_ramps(path, FitOptions(weighting="ols", jump_threshold=5.0, backend=backend, max_bytes=4096))
        for name in ("rate", "variance", "dq", "njumps"):
            assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=name in ("rate", "variance"))
        assert a.attrs == b.attrs
    with pytest.raises(ParameterError, match="weightng.*did you mean 'weighting'"):
        fit_ramps(path, weightng="ols")
    with pytest.raises(ParameterError, match="backend"):
        fit_ramps(path, backend="cuda")
    with pytest.raises(ParameterError, match="ron"):
        fit_ramps(path, ron=-1.0)
    with pytest.raises(ParameterError, match="options=FitOptions"):
        fit_ramps(path, FitOptions(), weighting="ols")
    params = inspect.signature(fit_ramps).parameters
    assert params["weighting"].default == "gls" and params["max_bytes"].default == 256 << 20
    assert FIT_DEFAULTS["max_bytes"] == 256 << 20 and FIT_DEFAULTS["ron"] is None
    assert set(FIT_DEFAULTS) == set(params) - {"source", "options"}


def test_fit_ramps_renamed_keywords(tmp_path):
    """read_noise and memory_budget (the earlier names of ron and max_bytes) still work, with a
    DeprecationWarning, and give the same fit; both names at once are a ParameterError; ron takes a
    Quantity."""
    import astropy.units as u
    rate = np.full((16, 12), 30.0)
    path = simulate(rate, (6, 2, 0), seed=2, out=tmp_path / "r.h5", ron=8.0, **QUIET)
    new = fit_ramps(path, ron=5.0, max_bytes=4096, backend="numpy")
    with pytest.warns(DeprecationWarning, match="'read_noise' is deprecated, use 'ron'"):
        old = fit_ramps(path, read_noise=5.0, backend="numpy")
    assert np.array_equal(old.variance, new.variance) and old.attrs["READNOISE"] == 5.0
    with pytest.warns(DeprecationWarning, match="'memory_budget' is deprecated, use 'max_bytes'"):
        fit_ramps(path, memory_budget=4096, backend="numpy")
    with pytest.raises(ParameterError, match="'ron'"):
        fit_ramps(path, ron=5.0, read_noise=5.0)
    with pytest.raises(MemoryError, match="max_bytes"):
        fit_ramps(path, max_bytes=100)
    quantity = fit_ramps(path, ron=5.0 * u.electron, backend="numpy")
    assert np.array_equal(quantity.variance, new.variance)


def test_fit_ramps_reads_compressed_ramps_in_a_fresh_process(tmp_path):
    """Known item (a): fit_ramps called directly (no check_ramp_file first) on lz4/zstd ramps
    failed in a fresh process with h5py's 'can't open directory (/usr/local/lib/plugin)'."""
    for comp in ("lz4", "zstd"):
        path = simulate(np.full((8, 16), 5.0), (4, 2, 0), seed=1, progress=False, out=tmp_path / f"{comp}.h5",
                        compression=comp)
        code = ("import sys; from slicersim.reduction.ramp_fit import fit_ramps; "
                "print(fit_ramps(sys.argv[1], progress=False).rate.shape)")
        proc = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True)
        assert proc.returncode == 0 and "(8, 16)" in proc.stdout, proc.stderr[-500:]


def test_truncated_fits_ramps_are_named_in_one_line(tmp_path, capsys):
    """A level-1b FITS cut inside an extension gave 'mmap length is greater than file size' (no file
    name) after an astropy WARNING line."""
    from slicersim.app.cli import main
    from slicersim.errors import RampFileError
    from slicersim.reduction.ramp_fit import fit_ramps
    path = simulate(np.full((16, 32), 5.0), (4, 2, 0), seed=1, progress=False, out=tmp_path / "raw.fits")
    cut = tmp_path / "cut.fits"
    from astropy.io import fits
    with fits.open(path) as hdul:
        start = hdul.fileinfo(hdul.index_of("SCI"))["datLoc"]  # first byte of SCI's data
    with open(path, "rb") as fh:
        cut.write_bytes(fh.read()[:start + 1360])            # cut inside SCI's data
    with pytest.raises(RampFileError, match=r"cut.fits: truncated file: extension SCI ends at byte \d+ "
                                            r"\(declared shape \(1, 4, 16, 32\)"):
        fit_ramps(cut, progress=False)
    capsys.readouterr()
    assert main(["reduce", str(cut), "--out", str(tmp_path / "r.h5"), "--quiet"]) == 2
    captured = capsys.readouterr()
    err = (captured.err + captured.out).strip().splitlines()
    assert len(err) == 1 and "truncated file" in err[0], err
    assert not (tmp_path / "r.h5").exists()


@pytest.mark.parametrize("value", [0, -1, "3", True])
def test_fit_ramps_saturation_must_be_positive(value):
    """saturation=0, -1, "3" or True flagged every group SATURATED: an all-NaN rate image, no error."""
    from slicersim.errors import ParameterError
    from slicersim.reduction.ramp_fit import fit_ramps
    sci = np.full((1, 4, 4, 8), 1000, np.uint16) + np.arange(4, dtype=np.uint16)[None, :, None, None] * 10
    attrs = {"NFRAMES": 1, "GROUPGAP": 0, "TFRAME": 1.0, "GAIN": 1.0, "READNOISE": 5.0}
    assert np.allclose(fit_ramps((sci, None, None, attrs), progress=False).rate, 10.0)
    with pytest.raises(ParameterError, match="saturation must be a number of DN > 0"):
        fit_ramps((sci, None, None, attrs), saturation=value, progress=False)
    with pytest.raises(Exception, match="SATURATION = 0.0 DN must be > 0"):
        fit_ramps((sci, None, None, dict(attrs, SATURATION=0.0)), progress=False)


def _forged(path, shape=(1, 4, 100000, 100000)):
    """An HDF5 'ramp' of a few kB whose SCI declares ``shape`` (empty chunked datasets: never written)."""
    import h5py
    with h5py.File(path, "w") as fh:
        fh.create_dataset("SCI", shape=shape, dtype="u2", chunks=(1, 1, 64, 64))
        fh.create_dataset("GROUPDQ", shape=shape, dtype="u1", chunks=(1, 1, 64, 64))
        fh.attrs.update(COMPLETE=True, NFRAMES=1, GROUPGAP=0, TFRAME=2.83, GAIN=1.0, READNOISE=12.0)
    return path


def test_a_declared_shape_the_file_does_not_hold_is_refused_before_allocating(tmp_path):
    """A 2 kB file declaring SCI (1, 4, 10⁵, 10⁵) gave 'out of memory' (74.5 GiB) without naming the file."""
    from slicersim.reduction.checks import check_ramp_file
    path = _forged(tmp_path / "forged.h5")
    assert os.path.getsize(path) < 100_000
    needle = (r"forged.h5: dataset SCI declares shape \(1, 4, 100000, 100000\) uint16 \(74.5 GiB\) but the file "
              r"stores 0 of its 9771876 chunks: its data were never written")
    for call in (lambda: fit_ramps(path), lambda: read_ramps(path), lambda: check_ramp_file(path),
                 lambda: write_uncal_from_hdf5(path, tmp_path / "u.fits")):
        with pytest.raises(RampFileError, match=needle):
            call()
    assert not (tmp_path / "u.fits").exists()


def test_rates_larger_than_the_machine_memory_are_refused_naming_the_file(tmp_path, monkeypatch):
    from slicersim import validation
    from slicersim.errors import ResourceError, SlicersimError
    path = simulate(np.full((16, 32), 5.0), (4, 2, 0), seed=1, out=tmp_path / "ok.h5", **QUIET)
    monkeypatch.setattr(validation, "physical_memory", lambda: 5000)
    with pytest.raises(ResourceError, match=r"ok.h5: the rates of dataset SCI \(1, 4, 16, 32\) would take .* GiB, more "
                                            r"than this machine's .* GiB of memory") as info:
        fit_ramps(path)
    assert isinstance(info.value, SlicersimError) and isinstance(info.value, MemoryError)
    with pytest.raises(ResourceError, match=r"ok.h5: dataset SCI of shape \(1, 4, 16, 32\) read whole"):
        read_ramps(path)


@pytest.mark.parametrize("source, got", [(123, "got 123"), (np.zeros((4, 8, 8)), "got an array of shape (4, 8, 8)"),
                                         ([1, 2], "got a list of 2 item(s)"), (None, "got None")])
def test_a_source_of_another_kind_says_what_is_accepted(source, got):
    """fit_ramps(123) said only 'arrays must be (SCI, GROUPDQ or None, PIXELDQ or None, attrs)'."""
    from slicersim.reduction.checks import check_ramp_file
    from slicersim.reduction.pipeline import reduce_exposure
    for call, name in ((fit_ramps, "fit_ramps source"), (reduce_exposure, "reduce_exposure raw_path")):
        with pytest.raises(ParameterError) as info:
            call(source)
        text = str(info.value)
        assert text.startswith(f"{name} must be a ramp file path (str or os.PathLike") and got in text, text
        assert "SCI (nints, ngroups, ny, nx)" in text and "NFRAMES, GROUPGAP, TFRAME, GAIN, READNOISE" in text
    with pytest.raises(ParameterError, match="check_ramp_file path must be a ramp file path"):
        check_ramp_file(source)


def test_a_flipped_pixeldq_byte_is_a_checksum_error_naming_the_file(tmp_path):
    """A corrupted PIXELDQ chunk gave h5py's bare "Can't synchronously read data" without the file."""
    path = simulate(np.full((16, 32), 5.0), (4, 2, 0), seed=1, out=tmp_path / "r.h5", **QUIET)
    flip_chunk_byte(path, "PIXELDQ")
    with pytest.raises(RampFileError, match=r"checksum mismatch in dataset PIXELDQ of .*r\.h5"):
        fit_ramps(path, progress=False)


@pytest.mark.parametrize("key, match", [("gain", r"gain \[adu / electron\] must be in \(0, 1000\]"),
                                        ("ron", r"ron \[electron\] must be in \[0, 10000\]")])
def test_fit_gain_and_read_noise_beyond_their_range_are_refused(tmp_path, key, match):
    """fit_ramps(path, gain=1e300) overflowed (OverflowError) instead of naming the option."""
    path = simulate(np.full((16, 32), 5.0), (4, 2, 0), seed=1, out=tmp_path / "r.h5", **QUIET)
    with pytest.raises(ParameterError, match=match):
        fit_ramps(path, progress=False, **{key: 1e300})


def test_rates_beyond_float32_are_refused_not_stored_as_inf(tmp_path):
    """Rate files store RATE / VAR / VAR_POISSON / VAR_RNOISE in float32: a float64 ramp of 1e36 DN fitted
    to rates of 6e38 e-/s (finite in memory) and the file held inf for them, with only numpy's
    'overflow encountered in cast' warning.  Now one RampFileError naming the image; nothing written.
    NaN and inf (no rate) are stored as they are."""
    import warnings
    sci, gdq, pdq = _messy_block(npix=60)
    attrs = dict(NFRAMES=4, GROUPGAP=1, TFRAME=TF, GAIN=1.0, READNOISE=12.0)
    p = fit_ramps(((sci * 1e36).reshape(3, 14, 6, 10), gdq.reshape(3, 14, 6, 10), pdq.reshape(6, 10), attrs),
                  backend="numpy")
    assert np.isfinite(p.rate).all() and np.nanmax(p.rate) > np.finfo(np.float32).max
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(RampFileError, match="RATE holds finite values up to 6.*float32"):
            p.write(tmp_path / "rates.h5")
    assert not list(tmp_path.iterdir())
    p.rate[...] = np.nan
    p.rate[0, 0] = np.inf
    p.variance[...], p.var_poisson[...], p.var_rnoise[...] = 1.0, 0.5, 0.5
    p.write(tmp_path / "rates.h5")


def test_out_images_sharing_memory_are_refused():
    """``out=`` checked each array alone: the same float64 array as rate and variance came back as the
    variance for both with no error, and an output that is a view of the float64 ramp writes into the
    input the kernel reads in place (which must stay untouched until the results are fetched).  Images sharing memory with one another or with the inputs are refused."""
    sci, gdq, pdq = _messy_block()
    sci = sci.astype(np.float64)
    k = fit_constants((14, 4, 1), TF, 1.0, 12.0, 1 / 12, 40000, 4.0, "gls")
    npix = sci.shape[2]
    out = tuple(np.empty(npix) for _ in range(4)) + (np.zeros(npix, np.uint32), np.zeros(npix, np.int32))
    for bad in ((out[0], out[0]) + out[2:], (sci[0, -1],) + out[1:]):
        with pytest.raises(ValueError, match="sharing no memory"):
            fit_block_opencl(sci, gdq, pdq, k, out=bad)
    fit_block_opencl(sci, gdq, pdq, k, out=out)                   # distinct images: fine


def test_ramp_files_are_read_with_a_chunk_cache_wider_than_a_row_block(tmp_path):
    """The reduction reads row blocks narrower than the files' chunks (20 rows of a 49-row SCI chunk,
    of a 170-row compressed nonlinearity chunk); with h5py's 1 MiB chunk cache every block read and
    decompressed those chunks again (16 of 20 CPU-s of reading in one effects reduction).  Both
    readers of ramp files open them with ``READ_CHUNK_CACHE`` (64 MiB per dataset)."""
    from slicersim.io.rampfile import READ_CHUNK_CACHE, open_hdf5_input
    from slicersim.reduction.ramp_sources import open_ramps
    path = simulate(np.full((32, 32), 5.0), (4, 1, 0), seed=3, out=tmp_path / "c.h5", ron=5.0, **QUIET)
    src = open_ramps(path)
    try:
        assert src.fh.id.get_access_plist().get_cache()[2] == READ_CHUNK_CACHE["rdcc_nbytes"] >= 64 << 20
    finally:
        src.close()
    with open_hdf5_input(path) as fh:
        assert fh.id.get_access_plist().get_cache()[2] == READ_CHUNK_CACHE["rdcc_nbytes"]


def test_corrections_plane_by_plane_equal_the_whole_block_formula():
    """``_correct`` works one (integration, group) plane at a time (the polynomial's passes in the
    cache); its DN are bit for bit those of the whole-block formula (superbias, reference-pixel column
    and row terms, Horner's polynomial), non-finite results DO_NOT_USE and 0, saturation from raw DN."""
    from slicersim.physics.nonlinearity import apply_correction
    from slicersim.reduction.ramp_fit import _correct
    rng = np.random.default_rng(7)
    nints, n, ny, nx, y0 = 2, 5, 6, 9, 3
    raw = rng.integers(0, 65535, (nints, n, ny, nx)).astype(np.uint16)
    raw[0, 2, 1, 1] = 65535
    bias = rng.normal(1000, 30, (ny + y0, nx))
    col, row = rng.normal(0, 5, (nints, n, nx)), rng.normal(0, 5, (nints, n, ny + y0))
    coeffs = np.stack([rng.normal(0, 1, (ny + y0, nx)), 1 + rng.normal(0, 1e-3, (ny + y0, nx)),
                       rng.normal(0, 1e-7, (ny + y0, nx))])
    coeffs[2, y0 + 4, 5] = np.inf                       # a non-finite result: DO_NOT_USE, 0
    k = fit_constants((n, 1, 0), TF, 1.0, 10.0, saturation=60000.0)
    gdq = np.zeros(raw.shape, np.uint8)
    dn, k2 = _correct(raw, gdq, y0, y0 + ny, k, bias, (col, row), coeffs)
    want = raw.astype(np.float64) - bias[y0:]
    want -= col[:, :, None, :]
    want -= row[:, :, y0:, None]
    with np.errstate(invalid="ignore"):
        want = apply_correction(want, coeffs[:, y0:])
    bad = ~np.isfinite(want)
    assert bad.sum() == nints * n and np.all(gdq[bad] & 1) and not np.any(gdq[~bad] & 1)
    want[bad] = 0.0
    assert np.array_equal(dn, want) and k2.satlim == math.inf
    assert np.array_equal((gdq & 2) != 0, raw >= 60000) and ((gdq & 2) != 0).any()
    out = np.empty_like(want)
    with np.errstate(invalid="ignore"):
        assert apply_correction(want, coeffs[:, y0:], out=out) is out


# ----------------------------------------------------------------------------- adversarial pass (vector lanes)
# Findings of an adversarial pass on the vectorised kernel, each fixed: a NaN difference made the median
# read private memory it had not sorted (results depending on the width, run to run); kernel and twin
# disagreed on NaN differences and on lam0 = max(NaN, 0); SCI ≥ 1e300 was saturated by the kernel only;
# 16 lanes × 65 groups × 256 work items crashed the process (PoCL thread stack); empty blocks were an
# OpenCL error.  The other tests record what was tried and holds.
import warnings  # noqa: E402

WIDTHS = (1, 2, 4, 8, 16)


def _block(ramps, nints=1):
    """(nints, n, npix) float64 SCI from a list of per-pixel ramps, no flags."""
    sci = np.array(ramps, float).T[None].repeat(nints, 0).copy()
    return sci, np.zeros(sci.shape, np.uint8), np.zeros(sci.shape[2], np.uint32)


def _fits(sci, gdq, pdq, k, **kw):
    out = {}
    for vw in WIDTHS:
        fit, dq, nj, g = fit_block_opencl(sci, gdq, pdq, k, vector_width=vw, **kw)
        out[vw] = (np.asarray(fit).copy(), dq.copy(), nj.copy(), None if g is None else g.copy())
    return out


def _same_bits(a, b):
    return all(np.array_equal(np.asarray(x).view(np.uint8), np.asarray(y).view(np.uint8))
               for x, y in zip(a, b) if x is not None)


def test_nan_difference_gives_the_same_bits_at_every_width():
    """float64 SCI with a NaN group (no flag): D = [10, NaN, NaN, 500] has nv = 4 used differences,
    two of them NaN; klo = 1, khi = 2 but only 2 values land in the bracket, so the median reads A[2]."""
    k = fit_constants((5, 4, 1), TF, 1.0, 12.0, 1 / 12, None, 4.0, "ols")
    nan_ramp, filler = [0, 10, np.nan, 500, 1000], [0, 1e5, 2e5, 3e5, 3e5 + 10]
    for ramps in ([nan_ramp], [filler, nan_ramp], ([filler] + [nan_ramp]) * 8):
        res = _fits(*_block(ramps), k)
        for vw in WIDTHS[1:]:
            assert _same_bits(res[vw], res[1]), (len(ramps), vw, res[vw][3][0, :, -1], res[1][3][0, :, -1])


@pytest.mark.parametrize("weighting", ["gls", "ols"])
def test_nan_sci_kernel_matches_twin(weighting):
    k = fit_constants((10, 4, 1), TF, 1.0, 12.0, 1 / 12, None, 4.0, weighting)
    sci, gdq, pdq = _block([[0, 10, 20, 3000, 40, 50, 60, 70, 80, np.nan]])
    cl = fit_block_opencl(sci, gdq, pdq, k, vector_width=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = fit_block_numpy(sci, gdq, pdq, k)
    assert np.array_equal(cl[2], ref[2]) and np.array_equal(cl[1], ref[1]) and np.array_equal(cl[3], ref[3])
    assert np.array_equal(np.isnan(cl[0]), np.isnan(ref[0]))


def test_saturation_none_with_huge_float_sci_kernel_matches_twin():
    k = fit_constants((10, 4, 1), TF, 1.0, 12.0, 1 / 12, None, 4.0, "ols")
    sci, gdq, pdq = _block([[0, 10, 20, 30, 40, 1e300, 60, 70, 80, 90]])
    cl = fit_block_opencl(sci, gdq, pdq, k)
    ref = fit_block_numpy(sci, gdq, pdq, k)
    assert np.array_equal(cl[1], ref[1]) and np.array_equal(cl[2], ref[2]) and np.array_equal(cl[3], ref[3])


@pytest.mark.parametrize("shape", [(1, 6, 0), (0, 6, 5)])
def test_empty_blocks(shape):
    k = fit_constants((6, 4, 1), TF, 1.0, 12.0, 1 / 12, 40000, 4.0, "gls")
    sci, gdq, pdq = np.zeros(shape, np.uint16), np.zeros(shape, np.uint8), np.zeros(shape[2], np.uint32)
    ref = fit_block_numpy(sci, gdq, pdq, k)
    cl = fit_block_opencl(sci, gdq, pdq, k)
    assert np.array_equal(cl[1], ref[1])


def _messy(rng, n, nints, npix, sat=40000.0):
    t = np.arange(n) * 5 * TF
    kind = rng.integers(0, 9, npix)
    sci = 2000 + (10 ** rng.uniform(-1, 3, npix))[None, None] * t[None, :, None] + rng.normal(0, 6, (nints, n, npix))
    hits = rng.random((nints, n, npix)) < 0.08
    sci += np.cumsum(hits * rng.uniform(30, 3000, hits.shape), axis=1)
    sci[:, :, kind == 1] = 1234                                                    # all equal
    m = kind == 2
    sci[:, :, m] = 2000 + np.cumsum(rng.integers(0, 3, (nints, n, m.sum())) * 10, axis=1)  # tied differences
    sci = np.clip(np.rint(sci), 0, 65535)
    gdq = np.zeros(sci.shape, np.uint8)
    gdq[rng.random(sci.shape) < 0.05] |= 1
    gdq[rng.random(sci.shape) < 0.05] |= 4
    gdq[:, 0, kind == 4] |= 2                                                      # saturated at group 0
    gdq[:, :, kind == 5] |= 1                                                      # every group DO_NOT_USE
    sci[:, 0, kind == 6] = sat + 1
    gdq[:, 1:, kind == 7] |= 4
    pdq = (rng.integers(0, 2**32, npix, dtype=np.uint64) * (rng.random(npix) < 0.3)).astype(np.uint32)
    return sci, gdq, pdq


@pytest.mark.parametrize("n", [pytest.param(2, marks=pytest.mark.slow), 3, pytest.param(4, marks=pytest.mark.slow),
                               pytest.param(64, marks=pytest.mark.slow), pytest.param(65, marks=pytest.mark.slow),
                               pytest.param(66, marks=pytest.mark.slow)])
@pytest.mark.parametrize("weighting", ["gls", pytest.param("ols", marks=pytest.mark.slow)])
def test_edge_group_counts_tails_and_flags_are_bit_identical(n, weighting):
    """NGROUPS at the edges (1 and 2 differences, JUMP_MIN_DIFFS, the sorting network's 64 on/off),
    npix not a multiple of any width, 1-3 integrations, tied/equal ramps, saturation at the first
    group, all DO_NOT_USE, upstream jumps, pixeldq bits, a tiny threshold: every width gives the
    scalar bits, and the twin the same flags and 1e-12 relative floats."""
    rng = np.random.default_rng(n)
    for nints, npix, thr in ((1, 13, 4.0), (3, 17, 1e-300)):
        k = fit_constants((n, 4, 1), TF, 2.3, 12.0, 1 / 12, 40000.0, thr, weighting)
        sci, gdq, pdq = _messy(rng, n, nints, npix)
        res = _fits(sci, gdq, pdq, k)
        for vw in WIDTHS[1:]:
            assert _same_bits(res[vw], res[1]), vw
        ref = fit_block_numpy(sci, gdq, pdq, k)
        for a, b in zip(res[1][1:], ref[1:]):
            assert np.array_equal(a, b)
        ok = np.isfinite(ref[0])
        assert np.array_equal(np.isfinite(res[1][0]), ok)
        assert np.all(np.abs(res[1][0][ok] - ref[0][ok]) <= 1e-12 * np.abs(ref[0][ok]))


@pytest.mark.slow
@pytest.mark.parametrize("npix", [1, 3, 9, 17])
def test_out_views_of_larger_buffers_are_not_written_past_npix(npix):
    rng = np.random.default_rng(npix)
    k = fit_constants((6, 4, 1), TF, 1.0, 12.0, 1 / 12, 40000, 4.0, "gls")
    sci = (2000 + np.arange(6)[None, :, None] * 30 + rng.normal(0, 5, (2, 6, npix))).round().astype(np.uint16)
    sci[:, 3:, ::2] += 900
    gdq, pdq = np.zeros(sci.shape, np.uint8), np.full(npix, 1024, np.uint32)
    ref = fit_block_opencl(sci, gdq, pdq, k, vector_width=1)
    for vw in (2, 4, 8, 16):
        for wg in (None, 1, 7):
            bufs = [np.full(npix + 40, -7.0) for _ in range(4)] + [np.full(npix + 40, 77, np.uint32),
                                                                   np.full(npix + 40, 77, np.int32)]
            fit_block_opencl(sci, gdq, pdq, k, vector_width=vw, out=tuple(b[3:3 + npix] for b in bufs), work_group=wg)
            for b, r in zip(bufs, (*ref[0], ref[1], ref[2])):
                assert np.array_equal(b[3:3 + npix].view(np.uint8), np.ascontiguousarray(r).view(np.uint8))
                assert np.all(b[:3] == b[0]) and np.all(b[3 + npix:] == b[0]) and b[0] in (-7.0, 77)


def test_explicit_wide_lanes_with_a_large_work_group_do_not_crash():
    """16 lanes × 65 groups × 256 work items crashed the process (SIGSEGV: PoCL keeps a work group's private
    arrays on a thread's stack).  Such an explicit width is one ParameterError naming work_group and
    vector_width; with the default width a large work group gets fewer lanes and runs (a subprocess, so
    that a crash fails the test instead of the suite)."""
    import subprocess
    import sys
    k = fit_constants((65, 4, 1), TF, 1.0, 12.0, 1 / 12, 40000.0, 4.0, "gls")
    sci = np.zeros((1, 65, 1), np.uint16)
    with pytest.raises(ParameterError, match="work_group 256 x vector_width 16"):
        fit_block_opencl(sci, np.zeros(sci.shape, np.uint8), np.zeros(1, np.uint32), k, vector_width=16, work_group=256)
    code = ("import numpy as np\n"
            "from slicersim.backends.ramp_fit import fit_block_opencl, fit_constants\n"
            "for n in (65, 200):\n"
            "    k = fit_constants((n, 4, 1), 2.83, 1.0, 12.0, 1/12, 40000.0, 4.0, 'gls')\n"
            "    sci = np.zeros((1, n, 300), np.uint16)\n"
            "    r = fit_block_opencl(sci, np.zeros(sci.shape, np.uint8), np.zeros(300, np.uint32), k, work_group=256)\n"
            "    assert np.all(r[0][0] == 0)\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr[-2000:]


# ----------------------------------------------------------------------------- adversarial pass 2 (chunk cache, plane-by-plane corrections, work_group)
def _old_correct(raw, gdq, y0, y1, consts, bias, terms, coeffs):
    """``_correct`` before the plane-by-plane change (whole block at once), the reference."""
    from dataclasses import replace
    from slicersim.physics.nonlinearity import apply_correction
    from slicersim.reduction.ramp_fit import _bias_rows
    if raw.dtype == np.uint16:
        gdq |= (raw >= consts.satlim).view(np.uint8) * np.uint8(2)
    dn = raw.astype(np.float64)
    dn -= _bias_rows(bias, y0, y1)
    if terms is not None:
        col, row = terms
        dn -= col[:, :, None, :]
        dn -= row[:, :, y0:y1, None]
    if coeffs is not None:
        dn = apply_correction(dn, np.asarray(coeffs[:, y0:y1], np.float64))
    bad = ~np.isfinite(dn)
    gdq[bad] |= np.uint8(1)
    dn[bad] = 0.0
    return dn, replace(consts, satlim=math.inf) if raw.dtype == np.uint16 else consts


@pytest.mark.parametrize("shape", [(1, 2, 1, 1), (1, 3, 1, 7), (3, 2, 5, 1), (2, 4, 3, 3), (1, 5, 0, 4), (2, 3, 4, 0)])
@pytest.mark.parametrize("dtype", [np.uint16, np.float64])
def test_plane_by_plane_corrections_odd_shapes_bit_identical(shape, dtype):
    """1 row, 1 column, empty blocks, nints > 1, float64 SCI with NaN/inf, bias None / scalar / float32
    scalar / 0-d / map / float32 map, with and without refpix terms, 2-5 coefficients (float32 ones too),
    NaN/±inf coefficients, y0 > 0: DN, GROUPDQ and the constants equal the whole-block formula bit for bit."""
    import itertools
    from slicersim.reduction.ramp_fit import _correct
    rng = np.random.default_rng(sum(shape))
    nints, n, ny, nx = shape
    for biaskind, withterms, ncoef, y0, poison in itertools.product(
            ["none", "scalar", "f32", "0d", "map", "map_f32"], [False, True], [None, 2, 3, 5], [0, 2], [False, True]):
        H = ny + y0 + 1
        raw = rng.integers(0, 65535, shape).astype(dtype)
        if dtype == np.float64:
            raw = raw + rng.random(shape) * 1e-3
            if poison and raw.size:
                raw.flat[0], raw.flat[-1] = np.nan, np.inf
        bias = {"none": None, "scalar": 1000.3, "f32": np.float32(1000.3), "0d": np.array(999.7),
                "map": rng.normal(1000, 30, (H, nx)), "map_f32": rng.normal(1000, 30, (H, nx)).astype(np.float32)}[biaskind]
        terms = (rng.normal(0, 5, (nints, n, nx)), rng.normal(0, 5, (nints, n, H))) if withterms else None
        coeffs = None
        if ncoef:
            coeffs = np.stack([rng.normal(0, 1, (H, nx))] + [(j == 1) + rng.normal(0, 1e-5 ** j, (H, nx))
                                                             for j in range(1, ncoef)])
            if poison and ny and nx:
                coeffs[-1, y0, 0], coeffs[0, y0 + ny - 1, nx - 1] = np.inf, np.nan
            coeffs = coeffs.astype(np.float32) if ncoef == 3 else coeffs
        k = fit_constants((n, 1, 0), TF, 1.0, 10.0, saturation=60000.0)
        g1 = rng.integers(0, 256, shape).astype(np.uint8)
        g2 = g1.copy()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            a, ka = _correct(raw, g1, y0, y0 + ny, k, bias, terms, coeffs)
            b, kb = _old_correct(raw, g2, y0, y0 + ny, k, bias, terms, coeffs)
        case = (biaskind, withterms, ncoef, y0, poison)
        assert a.dtype == b.dtype and np.array_equal(a.view(np.uint8), b.view(np.uint8)), case
        assert np.array_equal(g1, g2) and ka == kb, case


def _lazuli(tmp_path, name="laz.h5", nramps=2):
    return simulate(np.full((64, 64), 5.0), (6, 4, 1), out=tmp_path / name, effects="lazuli", seed=11,
                    nramps=nramps, progress=False)


@pytest.mark.parametrize("backend", [pytest.param("numpy", marks=pytest.mark.slow), "opencl"])
def test_lazuli_products_identical_at_every_row_block_size(tmp_path, backend):
    """An effects file (reference pixels, nonlinearity, bias, ...): rates, variances, DQ, jumps and GROUPDQ
    are bit-identical whatever ``max_bytes`` (1 row per block up to the whole detector)."""
    path = _lazuli(tmp_path)
    res = []
    for mb in (1 << 15, 3 * 30720 + 100, 17 * 30720, 256 << 20):          # 1, 3, 17 rows, everything
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r = fit_ramps(path, max_bytes=mb, backend=backend, progress=False, return_groupdq=True)
        res.append([np.ascontiguousarray(getattr(r, key)).view(np.uint8) for key in
                    ("rate", "variance", "var_poisson", "var_rnoise", "dq", "njumps", "groupdq")])
    for other in res[1:]:
        assert all(np.array_equal(a, b) for a, b in zip(res[0], other))


def test_a_damaged_linearity_chunk_is_one_ramp_file_error(tmp_path):
    """A damaged chunk of the file's linearity coefficients (read row block by row block) was h5py's bare
    OSError ("filter returned failure during read"); now one RampFileError naming the dataset."""
    path = _lazuli(tmp_path, nramps=1)
    flip_chunk_byte(path, "truth/nonlinearity/inverse_coefficients", offset=100)
    with pytest.raises(RampFileError, match="inverse_coefficients|checksum"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fit_ramps(path, backend="numpy", progress=False)


@pytest.mark.parametrize("work_group", [0, -1, 10**6])
def test_a_bad_work_group_is_refused_before_reading_data(tmp_path, work_group):
    """work_group 0 / -1 were accepted by FitOptions, and the device's range was checked only after the
    first row block (and the reference-pixel pass) had been read: now refused before any read."""
    from slicersim.reduction import ramp_sources
    from slicersim.reduction.ramp_fit import FitOptions
    path = simulate(np.full((16, 16), 5.0), (6, 1, 0), out=tmp_path / "w.h5", seed=1, progress=False)
    reads = []
    orig = ramp_sources._HDF5Ramps.read

    def spy(self, *args, **kw):
        reads.append(args[:2])
        return orig(self, *args, **kw)
    ramp_sources._HDF5Ramps.read = spy
    try:
        if work_group < 1:                      # beyond the device's maximum: known at run time, before reading
            with pytest.raises(ParameterError, match="work_group"):
                FitOptions(work_group=work_group)
        with pytest.raises(ParameterError, match="work_group"):
            fit_ramps(path, work_group=work_group, backend="opencl", progress=False)
        assert reads == []
    finally:
        ramp_sources._HDF5Ramps.read = orig


def test_a_work_group_beyond_the_private_budget_is_refused_before_reading_data(tmp_path):
    """The CPU private-memory refusal (work_group × lanes × groups > 6 MiB) came after a row block was
    read; now ``check_launch`` runs before any read."""
    from slicersim.backends import opencl
    from slicersim.reduction import ramp_sources
    if "GPU" in opencl.device_type(opencl.get_device()) or opencl.get_device().max_work_group_size < 1024:
        pytest.skip("a CPU device with work groups of 1024")
    path = simulate(np.full((8, 8), 5.0), (130, 1, 0), out=tmp_path / "g.h5", seed=1, progress=False)
    reads = []
    orig = ramp_sources._HDF5Ramps.read
    ramp_sources._HDF5Ramps.read = lambda self, *a, **kw: reads.append(a[:2]) or orig(self, *a, **kw)
    try:
        with pytest.raises(ParameterError, match="private memory"):
            fit_ramps(path, work_group=1024, backend="opencl", progress=False)
        assert reads == []
    finally:
        ramp_sources._HDF5Ramps.read = orig


@pytest.mark.parametrize("shape", [(1, 6, 0), (0, 6, 5), (0, 6, 0)])
@pytest.mark.parametrize("dtype", [np.uint16, np.float64])
def test_empty_blocks_wait_false_and_out(shape, dtype):
    """Empty blocks: wait=False returns a callable giving the twin's results; ``out`` gets them written
    and the results are views of it; wrong ``out`` is still refused."""
    k = fit_constants((6, 4, 1), TF, 1.0, 12.0, 1 / 12, 40000, 4.0, "gls")
    sci, gdq, pdq = np.zeros(shape, dtype), np.zeros(shape, np.uint8), np.zeros(shape[2], np.uint32)
    ref = fit_block_numpy(sci, gdq, pdq, k)
    for want in (True, False):
        r = fit_block_opencl(sci, gdq, pdq, k, wait=False, want_gdq=want)()
        assert all(np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True) for a, b in zip(r[:3], ref[:3]))
        assert (r[3] is None) != want
    npix = shape[2]
    out = tuple(np.full(npix, -7.0) for _ in range(4)) + (np.full(npix, 9, np.uint32), np.full(npix, 9, np.int32))
    r = fit_block_opencl(sci, gdq, pdq, k, out=out, wait=False)()
    for a, b in zip((*ref[0], ref[1], ref[2]), out):
        assert np.array_equal(a, b, equal_nan=True)
    with pytest.raises(ValueError, match="out must be"):
        fit_block_opencl(sci, gdq, pdq, k, out=tuple(np.empty(npix + 1) for _ in range(6)))


@pytest.mark.parametrize("value", [np.nan] + [pytest.param(v, marks=pytest.mark.slow)
                                              for v in (np.inf, -np.inf, 1.7e308, -1.7e308)])
@pytest.mark.parametrize("saturation", [None, pytest.param(40000.0, marks=pytest.mark.slow)])
def test_non_finite_and_extreme_float_groups_kernel_matches_twin(value, saturation):
    """A ±inf / NaN / ±1.7e308 group at every position, satlim inf (unclamped) or finite, 1-2 integrations,
    widths 1, 2, 8: the kernel's flags, jumps and GROUPDQ are the twin's; rates 1e-12 relative."""
    for weighting in ("gls", "ols"):
        k = fit_constants((8, 4, 1), TF, 1.0, 12.0, 1 / 12, saturation, 4.0, weighting)
        for pos in range(8):
            ramp = np.arange(8) * 100.0 + 1000
            ramp[pos] = value
            for nints in (1, 2):
                sci = np.stack([ramp, np.arange(8) * 50.0], axis=1)[None].repeat(nints, 0).copy()
                gdq, pdq = np.zeros(sci.shape, np.uint8), np.zeros(2, np.uint32)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    ref = fit_block_numpy(sci, gdq, pdq, k)
                    for vw in (1, 2, 8):
                        cl = fit_block_opencl(sci, gdq, pdq, k, vector_width=vw)
                        assert all(np.array_equal(a, b) for a, b in zip(cl[1:], ref[1:])), (weighting, pos, nints, vw)
                        ok = np.isfinite(ref[0])
                        assert np.array_equal(np.isfinite(cl[0]), ok)
                        assert np.all(np.abs(cl[0][ok] - ref[0][ok]) <= 1e-12 * np.abs(ref[0][ok]))
