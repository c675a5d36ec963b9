"""Bad pixels of an HgCdTe array: hot, warm, dead, low-QE and random-telegraph (RTS) pixels.

Fractions (defaults; each configurable) are of the order of the JWST NIRSpec/NIRCam H2RG
bad-pixel statistics — operability > 99 % with hot, warm, dead, low-QE and telegraph ("popcorn")
pixels each a few 0.01 % to ≈ 0.5 % of the array (Rauscher et al. 2014, PASP 126, 739, "New and
better detectors for the JWST Near-Infrared Spectrograph"; JWST User Documentation, bad-pixel
masks; the flag bits are those of ``stdatamodels.jwst.datamodels.dqflags``):

* dead 0.05 %:   no response (QE factor 0);  PIXELDQ DEAD | DO_NOT_USE
* hot 0.1 %:     extra dark current 1–100 e-/s (log-uniform);  HOT | DO_NOT_USE
* warm 0.5 %:    extra dark current 0.05–1 e-/s (log-uniform);  WARM
* low QE 0.2 %:  response factor 0.2–0.8 (uniform);  LOW_QE
* telegraph 0.1 %: a read offset switching between 0 and A = 20–200 e- (log-uniform), with
  exponential dwell times of means τ_low, τ_high = 5–500 s (log-uniform, independent);
  TELEGRAPH.  RTS noise comes from a single trap in the source-follower gate switching between
  two charge states (Kirton & Uren 1989, Adv. Phys. 38, 367; seen in JWST H2RGs, Rauscher et al. 2014).

The classes are exclusive: one uniform per pixel picks the class by cumulative fraction, the
second gives its value (Philox index ``y << 16 | x``, full-detector pixel, stream
``STREAMS["bad_pixels"]``); a telegraph pixel's dwell times use sub-stream 1.  The telegraph state
is a two-state continuous-time Markov chain sampled exactly at every frame (sub-stream 2, index
``ramp << 32 | y << 16 | x``, draw = frame), starting each ramp from its stationary distribution.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from slicersim import rng, validation
from slicersim.rng import uniform_normal_grid
from slicersim.errors import EffectsError
from slicersim.physics.effects import STREAMS, check_fraction, check_number, check_shape_rows

__all__ = ["BadPixelParameters", "bad_pixel_maps", "telegraph_offsets", "telegraph_states", "DQ_FLAGS",
           "TELEGRAPH_DTYPE", "expected_run_frames"]

#: JWST PIXELDQ bits (stdatamodels.jwst.datamodels.dqflags.pixel)
DQ_FLAGS = {"DO_NOT_USE": 1, "DEAD": 1024, "HOT": 2048, "WARM": 4096, "LOW_QE": 8192, "TELEGRAPH": 32768}
TELEGRAPH_DTYPE = np.dtype([("y", "<u2"), ("x", "<u2"), ("amplitude", "<f4"), ("tau_low", "<f4"),
                            ("tau_high", "<f4")])
CLASSES = ("dead", "hot", "warm", "low_qe", "telegraph")
SUB_CLASS, SUB_DWELL, SUB_STATE = 0, 1, 2
ROWS_PER_CHUNK = 256


def _check_range(name, value, low, high):
    """A (min, max) pair of numbers in [low, high] with min ≤ max, else EffectsError naming it."""
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != 2:
        raise EffectsError(f"{name} must be a (min, max) pair, got {validation.short_repr(value)}")
    lo = check_number(f"{name} min", value[0], low, high)
    hi = check_number(f"{name} max", value[1], low, high)
    if hi < lo:
        raise EffectsError(f"{name} must have min ≤ max, got {validation.short_repr(value)}")
    return (lo, hi)


@validation.checked_fields(error=EffectsError)
@dataclass(kw_only=True)
class BadPixelParameters:
    """Fractions of the array in each (exclusive) class and the ranges of their values:
    hot_dark, warm_dark : e-/s;  low_qe : response factor;  telegraph_amplitude : e-;
    telegraph_dwell : s (mean dwell time of each state)."""

    dead_fraction: float = 5e-4
    hot_fraction: float = 1e-3
    warm_fraction: float = 5e-3
    low_qe_fraction: float = 2e-3
    telegraph_fraction: float = 1e-3
    hot_dark: tuple = (1.0, 100.0)
    warm_dark: tuple = (0.05, 1.0)
    low_qe: tuple = (0.2, 0.8)
    telegraph_amplitude: tuple = (20.0, 200.0)
    telegraph_dwell: tuple = (5.0, 500.0)

    def __post_init__(self):
        for c in CLASSES:
            setattr(self, f"{c}_fraction", check_fraction(f"bad_pixels.{c}_fraction", getattr(self, f"{c}_fraction")))
        total = sum(getattr(self, f"{c}_fraction") for c in CLASSES)
        if total > 1.0:
            raise EffectsError(f"bad_pixels fractions must sum to ≤ 1, got {total:g}")
        self.hot_dark = _check_range("bad_pixels.hot_dark [e-/s]", self.hot_dark, 1e-6, 1e7)
        self.warm_dark = _check_range("bad_pixels.warm_dark [e-/s]", self.warm_dark, 1e-6, 1e7)
        self.low_qe = _check_range("bad_pixels.low_qe", self.low_qe, 0.0, 1.0)
        self.telegraph_amplitude = _check_range("bad_pixels.telegraph_amplitude [e-]", self.telegraph_amplitude,
                                                1e-3, 1e6)
        self.telegraph_dwell = _check_range("bad_pixels.telegraph_dwell [s]", self.telegraph_dwell, 1e-3, 1e9)

    def to_dict(self):
        d = asdict(self)
        for k, v in d.items():
            if isinstance(v, tuple):
                d[k] = list(v)
        return d


def _log_uniform(u, lo_hi):
    lo, hi = lo_hi
    return lo * (hi / lo) ** u


def _pixel_index(y, x):
    return (np.asarray(y, np.uint64) << np.uint64(16)) | np.asarray(x, np.uint64)


def bad_pixel_maps(seed, shape, params, rows=None):
    """Bad-pixel maps of the detector (or of its ``rows`` = (r0, r1), same values as the full
    detector's): dict of ``extra_dark`` [e-/s] float32 (ny, nx), ``qe_factor`` float32 (0 for dead),
    ``dead`` bool, ``pixeldq`` uint32 (JWST bits) and ``telegraph`` (:data:`TELEGRAPH_DTYPE`,
    full-detector y, x, sorted by (y, x))."""
    (ny, nx), (r0, r1) = check_shape_rows(shape, rows)
    rng.seed_to_key(seed)
    edges = np.cumsum([getattr(params, f"{c}_fraction") for c in CLASSES])
    n = r1 - r0
    extra_dark = np.zeros((n, nx), np.float32)
    qe = np.ones((n, nx), np.float32)
    pdq = np.zeros((n, nx), np.uint32)
    tel_y, tel_x, tel_u = [], [], []
    for c0 in range(r0, r1, ROWS_PER_CHUNK):
        yy = np.arange(c0, min(c0 + ROWS_PER_CHUNK, r1))
        u, _ = uniform_normal_grid(yy.size, nx, seed, STREAMS["bad_pixels"] + SUB_CLASS, 0, first_index=c0 << 16,
                                   row_stride=1 << 16)                   # index y << 16 | x
        cls = np.searchsorted(edges, u[..., 0], side="right")        # 0 dead … 4 telegraph, 5 good
        rel = slice(c0 - r0, c0 - r0 + yy.size)
        v = u[..., 1]
        dead, hot, warm, low, tel = (cls == i for i in range(5))
        extra_dark[rel] = np.where(hot, _log_uniform(v, params.hot_dark),
                                   np.where(warm, _log_uniform(v, params.warm_dark), 0.0))
        qe[rel] = np.where(dead, 0.0, np.where(low, params.low_qe[0] + v * (params.low_qe[1] - params.low_qe[0]),
                                                1.0))
        pdq[rel] = (dead * (DQ_FLAGS["DEAD"] | DQ_FLAGS["DO_NOT_USE"])
                    + hot * (DQ_FLAGS["HOT"] | DQ_FLAGS["DO_NOT_USE"])
                    + warm * DQ_FLAGS["WARM"] + low * DQ_FLAGS["LOW_QE"] + tel * DQ_FLAGS["TELEGRAPH"])
        ty, tx = np.nonzero(tel)
        tel_y.append(yy[ty])
        tel_x.append(tx)
        tel_u.append(v[ty, tx])
    ty, tx, tu = (np.concatenate(a) if a else np.zeros(0) for a in (tel_y, tel_x, tel_u))
    telegraph = np.zeros(ty.size, TELEGRAPH_DTYPE)
    telegraph["y"], telegraph["x"] = ty, tx
    telegraph["amplitude"] = _log_uniform(tu, params.telegraph_amplitude)
    dwell = rng.uniform(seed, _pixel_index(ty, tx), STREAMS["bad_pixels"] + SUB_DWELL, 0)
    telegraph["tau_low"] = _log_uniform(dwell[:, 0], params.telegraph_dwell)
    telegraph["tau_high"] = _log_uniform(dwell[:, 1], params.telegraph_dwell)
    return {"extra_dark": extra_dark, "qe_factor": qe, "dead": (pdq & DQ_FLAGS["DEAD"]) != 0, "pixeldq": pdq,
            "telegraph": telegraph}


def telegraph_states(seed, ramp, nframes, tframe, pixels):
    """State (0 low, 1 high) of each telegraph pixel at every frame of a ramp: uint8 (nframes, npix).

    Two-state continuous-time Markov chain with leaving rates a = 1/τ_low, b = 1/τ_high, sampled
    exactly every t_frame: P(low→high) = a/λ (1 − e^{−λ t_f}), P(high→low) = b/λ (1 − e^{−λ t_f}),
    λ = a + b; frame 0 from the stationary law P(high) = τ_high/(τ_low + τ_high)."""
    ramp = validation.integer("ramp", ramp, low=0, high=2 ** 32 - 1, error=EffectsError)
    nframes = validation.integer("nframes", nframes, low=0, high=2 ** 32 - 1, error=EffectsError)
    tframe = check_number("tframe [s]", tframe, 0.0, low_open=True)
    pixels = np.asarray(pixels)
    a = 1.0 / pixels["tau_low"].astype(np.float64)
    b = 1.0 / pixels["tau_high"].astype(np.float64)
    lam = a + b
    settle = -np.expm1(-lam * tframe)
    p_up, p_down = a / lam * settle, b / lam * settle
    index = (np.uint64(ramp) << np.uint64(32)) | _pixel_index(pixels["y"], pixels["x"])
    stream = STREAMS["bad_pixels"] + SUB_STATE
    states = np.empty((nframes, pixels.size), np.uint8)
    if nframes == 0 or pixels.size == 0:
        return states
    state = rng.uniform(seed, index, stream, 0)[:, 0] < a / lam                  # stationary P(high)
    states[0] = state
    for f in range(1, nframes):
        u = rng.uniform(seed, index, stream, f)[:, 0]
        state = np.where(state, u >= p_down, u < p_up)
        states[f] = state
    return states


def telegraph_offsets(seed, ramp, nmd, tframe, pixels, params=None):
    """Group-averaged telegraph read offsets [e-]: float32 (ngroups, npix) = amplitude × the mean
    state over the m read frames of each group of MACC (n, m, d) (dropped frames evolve the state
    but are not read).  ``pixels``: the ``telegraph`` array of :func:`bad_pixel_maps`."""
    if isinstance(nmd, (str, bytes)) or not hasattr(nmd, "__len__") or len(nmd) != 3:
        raise EffectsError(f"nmd must be (n, m, d) integers, got {validation.short_repr(nmd)}")
    n = validation.integer("nmd[0] (n, groups)", nmd[0], low=1, error=EffectsError)
    m = validation.integer("nmd[1] (m, frames per group)", nmd[1], low=1, error=EffectsError)
    d = validation.integer("nmd[2] (d, dropped frames)", nmd[2], low=0, error=EffectsError)
    nframes = n * (m + d) - d
    states = telegraph_states(seed, ramp, nframes, tframe, pixels)
    starts = np.arange(n) * (m + d)
    read = (starts[:, None] + np.arange(m)[None, :]).ravel()
    mean_state = states[read].reshape(n, m, -1).mean(axis=1)
    return (mean_state * np.asarray(pixels)["amplitude"][None, :].astype(np.float64)).astype(np.float32)


def expected_run_frames(tau_from, tau_to, tframe):
    """Mean run length [frames] of a state with mean dwell ``tau_from`` in the sampled chain."""
    a, b = 1.0 / tau_from, 1.0 / tau_to
    lam = a + b
    return 1.0 / (a / lam * -math.expm1(-lam * tframe))
