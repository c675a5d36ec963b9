"""Persistence: charge trapped during a previous exposure, released as a decaying extra dark
current in the following ramps.

Model (Smith et al. 2008, Proc. SPIE 7021, "A theory for image persistence in HgCdTe
photodiodes": traps in the depletion region fill while it shrinks under illumination and empty
with a spread of emission time constants; Long et al. 2015, WFC3 ISR 2015-15 and Long, Baggett &
MacKenty 2012, Proc. SPIE 8442: the persistence amplitude is a Fermi-like function of the previous
fluence, saturating above the full well):

    trapped charge  N(Q) = N_max [F(Q) − F(0)] / [1 − F(0)],   F(Q) = 1 / (1 + e^{−(Q − Q_½)/W}),
    released current  I(t) = N(Q) Σ_i w_i / τ_i · e^{−t/τ_i}     (Σ w_i = 1),

t counted from the end of the previous exposure.  Defaults N_max = 1500 e-, Q_½ = 40 000 e-,
W = 8000 e-, τ = (100, 1000, 10 000) s with weights (0.3, 0.4, 0.3), delay 300 s: ≈ 0.3 e-/s
1000 s after a saturating exposure, the order of magnitude of HgCdTe (WFC3-IR, JWST) persistence.

Frame f of ramp r spans t ∈ [t₀, t₀ + t_f], t₀ = delay + (r · n_frames + f) · t_f (ramps back to
back, resets neglected); the charge released in it is Poisson with mean N Σ w_i (e^{−t₀/τ_i} −
e^{−(t₀+t_f)/τ_i}), drawn with Philox index ``ramp << 52 | frame << 32 | y << 16 | x`` under
``STREAMS["persistence"]`` (counter-based: independent of chunking and of other effects).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from slicersim import rng, validation
from slicersim.errors import EffectsError
from slicersim.physics.cosmic_rays import DEPOSIT_DTYPE
from slicersim.physics.effects import STREAMS, check_number

__all__ = ["PersistenceParameters", "trapped_charge", "released_mean", "persistence_deposits"]


@validation.checked_fields(error=EffectsError)
@dataclass(kw_only=True)
class PersistenceParameters:
    """trap_capacity N_max [e-]; fluence_half Q_½, fluence_width W [e-]; time_constants τ_i [s];
    weights w_i (sum 1); delay [s] from the end of the previous exposure to the first reset;
    min_trapped [e-]: pixels trapping less are ignored."""

    trap_capacity: float = 1500.0
    fluence_half: float = 40000.0
    fluence_width: float = 8000.0
    time_constants: tuple = (100.0, 1000.0, 10000.0)
    weights: tuple = (0.3, 0.4, 0.3)
    delay: float = 300.0
    min_trapped: float = 0.1

    def __post_init__(self):
        self.trap_capacity = check_number("persistence.trap_capacity [e-]", self.trap_capacity, 0.0, 1e7)
        self.fluence_half = check_number("persistence.fluence_half [e-]", self.fluence_half, 0.0, 1e8)
        self.fluence_width = check_number("persistence.fluence_width [e-]", self.fluence_width, 0.0, 1e8,
                                          low_open=True)
        taus, weights = self.time_constants, self.weights
        for name, values in (("time_constants", taus), ("weights", weights)):
            if isinstance(values, (str, bytes)) or not hasattr(values, "__len__"):
                raise EffectsError(f"persistence.{name} must be a list of numbers, got {validation.short_repr(values)}")
        if len(taus) == 0 or len(taus) != len(weights):
            raise EffectsError(f"persistence.time_constants and weights must be non-empty and of equal length, "
                               f"got {len(taus)} and {len(weights)}")
        self.time_constants = tuple(check_number("persistence.time_constants [s]", t, 0.0, 1e9, low_open=True)
                                    for t in taus)
        self.weights = tuple(check_number("persistence.weights", w, 0.0, 1.0) for w in weights)
        if abs(sum(self.weights) - 1.0) > 1e-9:
            raise EffectsError(f"persistence.weights must sum to 1, got {sum(self.weights):.12g}")
        self.delay = check_number("persistence.delay [s]", self.delay, 0.0, 1e9)
        self.min_trapped = check_number("persistence.min_trapped [e-]", self.min_trapped, 0.0, 1e7)

    def to_dict(self):
        d = asdict(self)
        d["time_constants"], d["weights"] = list(self.time_constants), list(self.weights)
        return d


def trapped_charge(prev_charge, params):
    """Trapped charge N(Q) [e-] after a previous exposure of fluence Q [e-] (0 at Q = 0)."""
    q = np.asarray(prev_charge, dtype=np.float64)

    def fermi(x):
        return 0.5 * (1.0 + np.tanh(0.5 * (x - params.fluence_half) / params.fluence_width))
    f0 = fermi(0.0)
    return params.trap_capacity * np.maximum(fermi(q) - f0, 0.0) / (1.0 - f0)


def released_mean(trapped, t0, t1, params):
    """Mean charge released between t0 and t1 [s] after the previous exposure [e-]."""
    frac = sum(w * (np.exp(-np.asarray(t0, float) / tau) - np.exp(-np.asarray(t1, float) / tau))
               for w, tau in zip(params.weights, params.time_constants))
    return np.asarray(trapped, float) * frac


def persistence_deposits(seed, ramp, nframes, tframe, prev_charge, params):
    """Charge released by persistence in each frame of a ramp, Poisson-sampled: structured array of
    :data:`~slicersim.physics.cosmic_rays.DEPOSIT_DTYPE` (rows with ≥ 1 e- only), sorted by
    (y, x, frame).  ``prev_charge``: the previous exposure's charge image [e-], full detector."""
    rng.seed_to_key(seed)
    ramp = validation.integer("ramp (persistence supports ramps 0 … 4095)", ramp, low=0, high=2 ** 12 - 1,
                              error=EffectsError)
    nframes = validation.integer("nframes (persistence: frames per ramp)", nframes, low=0, high=2 ** 20 - 1,
                                 error=EffectsError)
    tframe = check_number("tframe [s]", tframe, 0.0, low_open=True)
    prev = validation.array("prev_charge [e-]", prev_charge, ndim=2, low=0.0, error=EffectsError)
    if max(prev.shape) > 65536:
        raise EffectsError(f"prev_charge must be a 2-D image (ny, nx ≤ 65536), got shape {prev.shape}")
    trapped = trapped_charge(prev, params)
    y, x = np.nonzero(trapped > params.min_trapped)
    if y.size == 0 or nframes == 0:
        return np.zeros(0, DEPOSIT_DTYPE)
    n_trap = trapped[y, x]
    t0 = params.delay + (ramp * nframes + np.arange(nframes, dtype=np.float64)) * tframe
    mean = released_mean(n_trap[None, :], t0[:, None], t0[:, None] + tframe, params)   # (nframes, npix)
    pix = (y.astype(np.uint64) << np.uint64(16)) | x.astype(np.uint64)
    index = ((np.uint64(ramp) << np.uint64(52)) | (np.arange(nframes, dtype=np.uint64)[:, None] << np.uint64(32))
             | pix[None, :])
    counts = rng.poisson(mean, seed, index, STREAMS["persistence"])
    f, p = np.nonzero(counts > 0)
    out = np.empty(f.size, DEPOSIT_DTYPE)
    order = np.lexsort((f, x[p], y[p]))
    out["ramp"] = ramp
    out["frame"] = f[order]
    out["y"], out["x"] = y[p][order], x[p][order]
    out["electrons"] = counts[f, p][order]
    return out
