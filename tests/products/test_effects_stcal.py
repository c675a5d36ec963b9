"""Detector effects checked by independent algorithms: stcal (the JWST pipeline's jump detection and
linearity correction) on ramps written by :func:`slicersim.products.ramps.simulate`."""
import numpy as np
import pytest
from stcal.jump.jump import detect_jumps_data
from stcal.jump.jump_class import JumpData
from stcal.linearity.linearity import linearity_correction

from slicersim.io.rampfile import read_ramps
from slicersim.physics.effects import DetectorEffects
from slicersim.products.ramps import simulate

DQFLAGS = {"GOOD": 0, "DO_NOT_USE": 1, "SATURATED": 2, "JUMP_DET": 4, "NO_GAIN_VALUE": 524288,
           "REFERENCE_PIXEL": 2**31, "NO_LIN_CORR": 1048576}


def _truth(path, name):
    import h5py
    with h5py.File(path, "r") as fh:
        return fh[f"truth/{name}"][...]


def test_stcal_jump_detection_recovers_cosmic_rays(tmp_path):
    """≥ 95 % of the truth hits above 10σ of the group-difference noise are flagged by stcal's
    two-point-difference jump detection, with < 0.1 % false flags per pixel-group."""
    nmd, ron, rate_e = (20, 4, 0), 12.0, 2.0
    shape = (128, 128)
    effects = DetectorEffects.from_config({"effects": {"enabled": ["cosmic_rays"], "cosmic_rays": {"rate": 300.0}}})
    path = simulate(np.full(shape, rate_e), nmd, seed=8, out=tmp_path / "cr.h5", ron=ron, dark=0.0, roic_glow=0.0,
                    effects=effects)
    sci, gdq, pdq, attrs = read_ramps(path)
    hits = _truth(path, "cosmic_rays")
    n, m, d = nmd
    # stcal's read noise is that of a CDS pair of frames [DN]: √2 σ_frame, with the ±½ ADU rounding of
    # each group mean (m/12 in frame units) included
    cds_noise = np.sqrt(2.0) * np.sqrt(ron**2 + m / 12.0)
    jd = JumpData(gain2d=np.ones(shape, np.float32), rnoise2d=np.full(shape, cds_noise, np.float32), dqflags=DQFLAGS)
    jd.init_arrays_from_arrays(sci.astype(np.float32), gdq.copy(), pdq.copy())
    jd.nframes = m
    jd.dt_group = np.ones(1)
    jd.n_reads_groupdiff = np.ones(1) * 2 * m
    jd.flag_4_neighbors = False
    jd.rejection_thresh, jd.three_grp_thresh, jd.four_grp_thresh = 4.0, 6.0, 5.0
    jd.max_cores = "none"
    out_gdq, _, *_ = detect_jumps_data(jd)
    flagged = (out_gdq[0] & DQFLAGS["JUMP_DET"]) != 0                     # (n, ny, nx)
    # truth hits per (group, y, x): the group whose reads first see the charge
    group_of_frame = np.minimum(hits["frame"] // (m + d), n - 1)
    seen = hits["frame"] < n * (m + d) - d
    sigma_diff = np.sqrt(2 * ron**2 / m + rate_e * (m + d) * attrs["TFRAME"])    # e-, difference of groups
    big = seen & (hits["electrons"] > 10 * sigma_diff) & (group_of_frame >= 1)
    g, y, x = group_of_frame[big], hits["y"][big], hits["x"][big]
    nxt = np.minimum(g + 1, n - 1)
    recovered = flagged[g, y, x] | flagged[nxt, y, x]
    assert big.sum() > 100, big.sum()
    frac = recovered.mean()
    print(f"stcal jump: {recovered.sum()}/{big.sum()} hits > 10σ recovered ({frac:.4f})")
    assert frac >= 0.95, f"{frac:.3f} of {big.sum()} hits recovered"
    # false flags: flagged pixel-groups with no deposit in that group or the one before
    touched = np.zeros(flagged.shape, bool)
    gs = group_of_frame[seen]
    touched[gs, hits["y"][seen], hits["x"][seen]] = True
    touched[np.minimum(gs + 1, n - 1), hits["y"][seen], hits["x"][seen]] = True
    false = flagged & ~touched
    print(f"stcal jump: false flags {false.sum()} of {false.size} pixel-groups ({false.mean():.2e})")
    assert false.mean() < 1e-3, f"false-flag rate {false.mean():.2e}"


def test_stcal_linearity_correction_restores_linear_ramps(tmp_path):
    """Our nonlinear ramps, corrected by stcal with our truth inverse coefficients, equal the same
    ramps simulated without nonlinearity (same seed: the same Poisson electrons) to < 0.1 %."""
    ny, nx = 32, 128
    rate = np.tile(np.geomspace(20.0, 2000.0, nx), (ny, 1))           # e-/s: up to ~55 000 e- at the end
    kw = dict(seed=12, progress=False, ron=0.0, dark=0.0, roic_glow=0.0, tframe=2.83)
    nmd = (10, 1, 0)
    path = simulate(rate, nmd, out=tmp_path / "nl.h5", effects="nonlinearity", **kw)
    linear = simulate(rate, nmd, **kw).astype(float) - 2000.0
    sci, gdq, pdq, attrs = read_ramps(path)
    coeffs = _truth(path, "nonlinearity/inverse_coefficients")
    data = (sci.astype(np.float32) - 2000.0)
    corrected, _, _ = linearity_correction(data.copy(), gdq.copy(), pdq.copy(), coeffs, np.zeros((ny, nx), np.uint32), DQFLAGS)
    good = (gdq == 0) & (linear > 1000.0)
    rel = np.abs(corrected[good] - linear[good]) / linear[good]
    nonlinear = np.abs(data[good] - linear[good]) / linear[good]
    print(f"stcal linearity: max relative residual {rel.max():.2e} (uncorrected {nonlinear.max():.2e}), "
          f"{good.sum()} groups")
    assert nonlinear.max() > 0.02                                     # the effect is there
    assert rel.max() < 1e-3
