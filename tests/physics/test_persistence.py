"""Persistence (physics/persistence.py): trapped charge, decay, Poisson release, keying."""
import math

import numpy as np
import pytest

from slicersim.errors import EffectsError
from slicersim.physics import persistence as ps
from slicersim.physics.cosmic_rays import DEPOSIT_DTYPE

P = ps.PersistenceParameters()


def test_trapped_charge_shape():
    q = np.array([0.0, 10000.0, 40000.0, 80000.0, 1e6])
    n = ps.trapped_charge(q, P)
    assert n[0] == 0.0 and np.all(np.diff(n) > 0)
    assert n[-1] == pytest.approx(1500.0, rel=1e-3)              # saturates at the trap capacity
    # ≈ 0.3 e-/s 1000 s after a saturating exposure (order of HgCdTe persistence)
    rate = ps.released_mean(n[-1], 1000.0, 1001.0, P)
    assert 0.1 < rate < 1.0


def test_released_charge_matches_model_and_decays():
    prev = np.zeros((64, 64))
    prev[10:30, 10:40] = 90000.0                                  # a saturated patch (600 px)
    nframes, tframe = 256, 2.83
    dep = ps.persistence_deposits(3, 0, nframes, tframe, prev, P)
    assert dep.dtype == DEPOSIT_DTYPE
    assert np.all((dep["y"] >= 10) & (dep["y"] < 30) & (dep["x"] >= 10) & (dep["x"] < 40))
    expected = 600 * ps.released_mean(ps.trapped_charge(90000.0, P), P.delay, P.delay + nframes * tframe, P)
    total = dep["electrons"].sum()
    assert abs(total - expected) < 3 * math.sqrt(expected)       # Poisson
    # decays: first half of the ramp releases more than the second, as the model says
    early = dep["electrons"][dep["frame"] < nframes // 2].sum()
    late = dep["electrons"][dep["frame"] >= nframes // 2].sum()
    n = ps.trapped_charge(90000.0, P) * 600
    t_mid = P.delay + nframes // 2 * tframe
    e_early = ps.released_mean(n, P.delay, t_mid, P)
    e_late = ps.released_mean(n, t_mid, P.delay + nframes * tframe, P)
    assert e_early > e_late
    assert abs(early - e_early) < 3 * math.sqrt(e_early) and abs(late - e_late) < 3 * math.sqrt(e_late)
    # the next ramp starts later: less charge
    dep1 = ps.persistence_deposits(3, 1, nframes, tframe, prev, P)
    assert dep1["electrons"].sum() < total
    key = (dep["y"].astype(np.int64) << 40) | (dep["x"].astype(np.int64) << 20) | dep["frame"]
    assert np.all(np.diff(key) > 0)


def test_deterministic_and_window_independent():
    prev = np.zeros((32, 32))
    prev[5, 5] = prev[20, 7] = 70000.0
    d1 = ps.persistence_deposits(8, 2, 64, 2.83, prev, P)
    np.testing.assert_array_equal(d1, ps.persistence_deposits(8, 2, 64, 2.83, prev, P))
    big = np.zeros((64, 64))
    big[:32, :32] = prev
    np.testing.assert_array_equal(d1, ps.persistence_deposits(8, 2, 64, 2.83, big, P))
    assert ps.persistence_deposits(8, 2, 64, 2.83, np.zeros((32, 32)), P).size == 0


def test_bad_input_rejected():
    for kw in ({"trap_capacity": -1}, {"weights": (0.5, 0.4, 0.3)}, {"time_constants": (1.0, 2.0)},
               {"time_constants": (0.0, 10.0, 100.0)}, {"delay": -5}):
        with pytest.raises(EffectsError):
            ps.PersistenceParameters(**kw)
    with pytest.raises(EffectsError, match="prev_charge"):
        ps.persistence_deposits(1, 0, 10, 2.83, -np.ones((4, 4)), P)
    with pytest.raises(EffectsError, match="prev_charge"):
        ps.persistence_deposits(1, 0, 10, 2.83, np.ones(4), P)
