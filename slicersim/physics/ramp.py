"""Up-the-ramp readout physics of an H4RG: MACC frame schedule, mean charge per frame,
digitisation, and the validated parameters of a ramp simulation.

Samplers (OpenCL kernel and NumPy twin) are in :mod:`slicersim.backends.ramp`;
the driver writing raw files is :func:`slicersim.products.ramps.simulate`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from slicersim import validation
from slicersim.errors import ParameterError
from slicersim.physics.readout import readout_times

__all__ = ["RampParameters", "DEFAULT_BIAS", "MAX_FRAME_CHARGE", "check_frame_charge", "readpatt", "macc_frame_schedule",
           "frame_mean_charge", "to_adu", "sparse_threshold", "SPARSE_GROUP_CAP", "MAX_SPARSE_WINDOW"]

DEFAULT_BIAS = 2000.0          # ADU pedestal: read noise never clips at 0
#: the largest mean charge per frame [e-] a pixel is simulated with: 10⁴ full wells of an H4RG
#: (~1e5 e-), i.e. saturated in the first 1e-4 of the frame; beyond ~1.5e9 e- the samplers' exponent
#: (exp(−μ) by 2^n, n an int32) overflows
MAX_FRAME_CHARGE = 1e9
P_POISSON, P_READ, P_KTC, P_SPARSE = 0, 1, 2, 3
#: dense ramp sampler: CDF inversion below this mean charge per frame [e-], PTRS at and above (the
#: inversion's cost grows with the mean, PTRS's rejection loop costs about 30 steps of it per draw)
RAMP_PTRS_MIN_MEAN = 30.0


@validation.checked_fields
@dataclass(kw_only=True)
class RampParameters:
    """Validated readout and detector parameters of a ramp simulation (keyword-only).

    Each value is checked with :mod:`slicersim.validation` (a non-integer readout such as
    ``(2.7, 1, 0)`` is refused, not truncated); a bad one raises a
    :class:`~slicersim.errors.ReadoutError` (``nmd``, ``nramps``) or
    :class:`~slicersim.errors.ParameterError` naming it.  Physical values accept an astropy
    Quantity, converted to the unit given here.

    Parameters
    ----------
    nmd : tuple of int
        (n, m, d) MACC readout.
    nramps : int, optional
        Ramps (integrations).
    tframe : float, optional
        Frame time [s].
    ron : float, optional
        Read noise per frame [electron].
    dark : float or numpy.ndarray of shape (ny, nx), optional
        Dark current [e-/s/px] (may be a per-pixel array).
    thermal_dark : float, optional
        Thermal dark [e-/s/px].
    roic_glow : float, optional
        ROIC glow [e-/px/frame].
    gain : float, optional
        Gain [ADU/e-].
    saturation, bias : float, optional
        Saturation and bias [ADU].
    ktc_noise : float, optional
        kTC noise [e- per reset].
    full_well : float, optional
        Full well [e-] (default (saturation − bias)/gain).
    sparse_max_group : float, optional
        [e-/group] (None: auto).
    gauss_min_mean : float, optional
        [e-/frame] above which Poisson increments are drawn as Gaussians.
    """

    nmd: tuple
    nramps: int = 1
    tframe: float = 2.83
    ron: float = 12.0
    dark: object = 2.8e-3
    thermal_dark: float = 0.0
    roic_glow: float = 3e-3
    gain: float = 1.0
    saturation: float = 65535.0
    bias: float = DEFAULT_BIAS
    ktc_noise: float = 0.0
    full_well: float | None = None
    sparse_max_group: float | None = None
    gauss_min_mean: float = np.inf
    nframes: int = field(init=False)
    tgroup: float = field(init=False)

    def __post_init__(self):
        self.nmd = validation.readout(self.nmd, name="nmd")
        self.nramps = validation.nramps(self.nramps)
        top = validation.DETECTOR_MAX
        self.tframe = validation.number("tframe", self.tframe, low=0, low_open=True, high=top["tframe"], unit="s")
        self.gain = validation.number("gain", self.gain, low=0, low_open=True, high=top["gain"], unit="adu / electron")
        self.ron = validation.number("ron", self.ron, low=0, high=top["ron"], unit="electron")
        self.dark = _dark(self.dark)
        for name, unit in (("roic_glow", "electron"), ("ktc_noise", "electron"), ("thermal_dark", "electron / s"),
                           ("bias", "adu")):
            setattr(self, name, validation.number(name, getattr(self, name), low=0, unit=unit))
        self.saturation = validation.number("saturation", self.saturation, low=0, low_open=True, high=65535,
                                            unit="adu")
        self.full_well = float((self.saturation - self.bias) / self.gain) if self.full_well is None else \
            validation.number("full_well", self.full_well, low=0, low_open=True, unit="electron")
        if self.sparse_max_group is not None:
            self.sparse_max_group = validation.number("sparse_max_group", self.sparse_max_group, low=0,
                                                      unit="electron")
        self.gauss_min_mean = _number_or_inf("gauss_min_mean", self.gauss_min_mean)
        t = readout_times(self.nmd, self.tframe)
        self.nframes, self.tgroup = t["nframes"], t["group_time"]

    def attrs(self, seed):
        """Root attributes of the raw file (JWST-like names)."""
        n, m, d = self.nmd
        return {"NINTS": self.nramps, "NGROUPS": n, "NFRAMES": m, "GROUPGAP": d, "TFRAME": self.tframe,
                "TGROUP": self.tgroup, "READPATT": readpatt(self.nmd), "GAIN": self.gain,
                "READNOISE": self.ron, "SEED": int(seed), "BUNIT": "ADU", "BIAS": self.bias,
                "SATURATION": self.saturation, "FULLWELL": self.full_well}


def check_frame_charge(rate, p, names=None):
    """ParameterError naming the largest term (``names`` maps rate, dark, thermal_dark, roic_glow to
    what the caller calls them) and the bound when the mean charge of a frame, (rate + dark + thermal
    dark)·tframe + ROIC glow, exceeds :data:`MAX_FRAME_CHARGE` anywhere."""
    terms = {"rate": (float(np.max(rate, initial=0.0)), "e-/s", p.tframe),
             "dark": (float(np.max(p.dark, initial=0.0)), "e-/s", p.tframe),
             "thermal_dark": (p.thermal_dark, "e-/s", p.tframe), "roic_glow": (p.roic_glow, "e-/frame", 1.0)}
    mu = sum(value * per_frame for value, _, per_frame in terms.values())
    if mu > MAX_FRAME_CHARGE:
        key = max(terms, key=lambda k: terms[k][0] * terms[k][2])
        value, unit, _ = terms[key]
        raise ParameterError(f"{(names or {}).get(key, key)} reaches {value:g} {unit}: {mu:.3g} e- per frame of "
                             f"{p.tframe:g} s, more than the {MAX_FRAME_CHARGE:g} e- accepted "
                             f"({MAX_FRAME_CHARGE / p.full_well:.3g} full wells of {p.full_well:g} e-: the pixel "
                             f"saturates within the first {p.full_well / mu * p.tframe:.2g} s)")


def _dark(dark):
    """Dark current [e-/s]: a number ≥ 0 (a Quantity in 1/s is converted) or a per-pixel array ≥ 0."""
    if np.ndim(dark) == 0 or hasattr(dark, "unit"):
        if np.ndim(dark) == 0:
            return validation.number("dark", dark, low=0, unit="electron / s")
        try:
            dark = dark.to_value("electron / s")
        except Exception:
            raise ParameterError(f"dark must be in units convertible to electron / s, got {dark.unit}") from None
    return validation.array("dark", dark, low=0.0)


def _number_or_inf(name, value):
    """A number ≥ 0 where +inf is allowed (a threshold that is never reached)."""
    if isinstance(value, (int, float, np.floating)) and not isinstance(value, bool) and value == math.inf:
        return math.inf
    return validation.number(name, value, low=0)


def readpatt(nmd):
    """Readout pattern name, e.g. ``MACC(16,8,0)``."""
    return "MACC({},{},{})".format(*nmd)


def macc_frame_schedule(nmd):
    """(group index or −1 for dropped, is_read) per frame of one ramp."""
    n, m, d = nmd
    groups, reads = [], []
    for g in range(n):
        last = m if g == n - 1 else m + d
        for j in range(last):
            groups.append(g if j < m else -1)
            reads.append(j < m)
    return np.array(groups), np.array(reads)


def frame_mean_charge(rate, dark, thermal_dark, roic_glow, tframe):
    """Mean charge per frame μ = (rate + dark + thermal dark)·t_f + ROIC glow [e-/frame].

    rate, dark : e-/s (arrays or scalars);  roic_glow : e-/frame (also during dropped frames).
    """
    return (np.asarray(rate, dtype=float) + dark + thermal_dark) * tframe + roic_glow


def to_adu(charge_mean, reset, p):
    """rint(bias + gain·(reset + mean charge)) clipped to the uint16 range (float64 out)."""
    adu = np.rint(p.bias + p.gain * (reset + charge_mean))
    return np.clip(adu, 0.0, 65535.0)


SPARSE_GROUP_CAP = 64.0        # e-/group: larger sparse_max_group values act as this (CDF inversion cost)
MAX_SPARSE_WINDOW = 4096       # frames per group window: event positions use (x·w) >> 52, x < 2⁵²


def sparse_threshold(p):
    """Expected e- per group below which a pixel takes the sparse path (0: never).

    ``p.sparse_max_group`` None: 0.9·(m + d) − 1, where the two kernels cost the same on a CPU
    (PoCL, AVX-512: a sparse event ≈ 3.8 ns, a dense frame ≈ 3.3 ns per pixel; ≈ 0.75 e-/frame
    for m + d = 8; never for m + d = 1); any value is capped at SPARSE_GROUP_CAP.  Both paths
    are exact: the choice changes the random numbers, not their distribution.
    """
    n, m, d = p.nmd
    smg = 0.9 * (m + d) - 1.0 if p.sparse_max_group is None else p.sparse_max_group
    if m + d > MAX_SPARSE_WINDOW or not smg > 0:
        return 0.0
    return min(smg, SPARSE_GROUP_CAP)
