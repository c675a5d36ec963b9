"""Bad pixels (physics/bad_pixels.py): fractions, flags, values, telegraph statistics."""
import math

import numpy as np
import pytest

from slicersim.errors import EffectsError
from slicersim.physics import bad_pixels as bp

SHAPE = (1024, 1024)


@pytest.fixture(scope="module")
def maps():
    p = bp.BadPixelParameters(dead_fraction=0.002, hot_fraction=0.003, warm_fraction=0.01, low_qe_fraction=0.005,
                              telegraph_fraction=0.004)
    return p, bp.bad_pixel_maps(21, SHAPE, p)


def test_fractions_within_binomial_3_sigma(maps):
    p, m = maps
    n = SHAPE[0] * SHAPE[1]
    dq = m["pixeldq"]
    for name, flag in (("dead", "DEAD"), ("hot", "HOT"), ("warm", "WARM"), ("low_qe", "LOW_QE"),
                       ("telegraph", "TELEGRAPH")):
        f = getattr(p, f"{name}_fraction")
        k = np.count_nonzero(dq & bp.DQ_FLAGS[flag])
        assert abs(k - n * f) < 3 * math.sqrt(n * f * (1 - f)), name
    assert m["telegraph"].size == np.count_nonzero(dq & bp.DQ_FLAGS["TELEGRAPH"])


def test_flags_and_values(maps):
    p, m = maps
    from stdatamodels.jwst.datamodels import dqflags
    for k, v in bp.DQ_FLAGS.items():
        assert dqflags.pixel[k] == v
    dq, dark, qe = m["pixeldq"], m["extra_dark"], m["qe_factor"]
    assert dq.dtype == np.uint32 and dark.dtype == np.float32 and qe.dtype == np.float32 and m["dead"].dtype == bool
    dead, hot = (dq & 1024) != 0, (dq & 2048) != 0
    warm, low, tel = (dq & 4096) != 0, (dq & 8192) != 0, (dq & 32768) != 0
    # exclusive classes; DO_NOT_USE exactly on dead and hot
    assert np.all(dead.astype(int) + hot + warm + low + tel <= 1)
    np.testing.assert_array_equal((dq & 1) != 0, dead | hot)
    np.testing.assert_array_equal(m["dead"], dead)
    assert np.all(qe[dead] == 0) and np.all(qe[~(dead | low)] == 1)
    assert qe[low].min() >= 0.2 and qe[low].max() <= 0.8
    assert abs(qe[low].mean() - 0.5) < 4 * 0.6 / math.sqrt(12 * low.sum())
    assert np.all(dark[~(hot | warm)] == 0)
    assert dark[hot].min() >= 1.0 * (1 - 1e-6) and dark[hot].max() <= 100 * (1 + 1e-6)
    assert dark[warm].min() >= 0.05 * (1 - 1e-6) and dark[warm].max() <= 1.0 * (1 + 1e-6)
    # log-uniform: log10(dark) uniform over two decades for hot pixels
    lg = np.log10(dark[hot])
    assert abs(lg.mean() - 1.0) < 4 * (2 / math.sqrt(12)) / math.sqrt(hot.sum())
    t = m["telegraph"]
    assert np.all(tel[t["y"], t["x"]])
    assert np.all(np.diff(t["y"].astype(np.int64) * 65536 + t["x"]) > 0)


def test_row_windows_equal_full_map(maps):
    p, m = maps
    part = bp.bad_pixel_maps(21, SHAPE, p, rows=(100, 300))
    for k in ("extra_dark", "qe_factor", "dead", "pixeldq"):
        np.testing.assert_array_equal(part[k], m[k][100:300])
    sel = (m["telegraph"]["y"] >= 100) & (m["telegraph"]["y"] < 300)
    np.testing.assert_array_equal(part["telegraph"], m["telegraph"][sel])


def test_telegraph_two_levels_and_dwell_statistics():
    """RTS with τ_low = 20 s, τ_high = 50 s sampled every 1 s: mean run lengths and the fraction of
    time high match the exact chain within 4σ of their Monte Carlo errors."""
    pix = np.zeros(200, bp.TELEGRAPH_DTYPE)
    pix["y"], pix["x"] = np.arange(200) // 50, np.arange(200) % 50
    pix["amplitude"], pix["tau_low"], pix["tau_high"] = 80.0, 20.0, 50.0
    off = bp.telegraph_offsets(4, 0, (5000, 1, 0), 1.0, pix)
    assert off.shape == (5000, 200)
    assert set(np.unique(off)) == {0.0, 80.0}                   # two levels (m = 1)
    states = (off > 0).astype(np.int8)
    frac_high = states.mean()
    p_high = 50.0 / 70.0
    # correlated samples: effective number ≈ N·t_f/(2 τ_c), τ_c = 1/λ = 14.3 s
    n_eff = states.size / (2 * 14.29)
    assert abs(frac_high - p_high) < 4 * math.sqrt(p_high * (1 - p_high) / n_eff)
    runs = {0: [], 1: []}
    for col in states.T:
        edges = np.flatnonzero(np.diff(col)) + 1
        bounds = np.concatenate([[0], edges, [col.size]])
        for a, b in zip(bounds[1:-2], bounds[2:-1]):               # complete runs only
            runs[int(col[a])].append(b - a)
    for s, (tf, tt) in ((0, (20.0, 50.0)), (1, (50.0, 20.0))):
        r = np.array(runs[s])
        expected = bp.expected_run_frames(tf, tt, 1.0)           # ≈ τ / t_f
        assert abs(r.mean() - expected) < 4 * expected / math.sqrt(r.size)
        # geometric (discretised exponential) dwell: std ≈ mean
        assert r.std() == pytest.approx(expected, rel=0.1)


def test_group_average_and_determinism():
    pix = np.zeros(50, bp.TELEGRAPH_DTYPE)
    pix["x"] = np.arange(50)
    pix["amplitude"], pix["tau_low"], pix["tau_high"] = 100.0, 10.0, 10.0
    nmd = (20, 4, 2)
    off = bp.telegraph_offsets(9, 2, nmd, 2.83, pix)
    states = bp.telegraph_states(9, 2, 20 * 6 - 2, 2.83, pix)
    expected = np.stack([states[g * 6:g * 6 + 4].mean(axis=0) for g in range(20)]) * 100.0
    np.testing.assert_allclose(off, expected, rtol=1e-6)
    np.testing.assert_array_equal(off, bp.telegraph_offsets(9, 2, nmd, 2.83, pix))
    assert not np.array_equal(off, bp.telegraph_offsets(9, 3, nmd, 2.83, pix))


def test_bad_parameters_rejected():
    for kw in ({"dead_fraction": -0.1}, {"hot_fraction": 1.5}, {"warm_fraction": 0.6, "low_qe_fraction": 0.6},
               {"hot_dark": (10.0, 1.0)}, {"low_qe": (0.2, 1.5)}, {"telegraph_dwell": (0.0, 1.0)},
               {"telegraph_amplitude": "big"}):
        with pytest.raises(EffectsError):
            bp.BadPixelParameters(**kw)
    with pytest.raises(EffectsError, match="rows"):
        bp.bad_pixel_maps(1, (10, 10), bp.BadPixelParameters(), rows=(5, 20))


def test_telegraph_arguments_are_integers_not_truncated():
    with pytest.raises(EffectsError, match=r"^ramp must be an integer"):
        bp.telegraph_states(1, 0.5, 4, 2.83, np.zeros(0, bp.TELEGRAPH_DTYPE))
    with pytest.raises(EffectsError, match=r"nmd\[0\] \(n, groups\) must be an integer"):
        bp.telegraph_offsets(1, 0, (2.7, 1, 0), 2.83, np.zeros(0, bp.TELEGRAPH_DTYPE))
    with pytest.raises(EffectsError, match=r"bad_pixels.hot_dark \[e-/s\] must be a \(min, max\) pair"):
        bp.BadPixelParameters(hot_dark=5.0)
