"""Up-the-ramp readout physics of an H4RG: MACC frame schedule, mean charge per frame,
digitisation, and the validated parameters of a ramp simulation.

Samplers (OpenCL kernel and NumPy twin) are in :mod:`slicersim.backends.ramp`;
the driver writing raw files is :func:`slicersim.products.ramps.simulate`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from slicersim.errors import ReadoutError
from slicersim.physics.readout import readout_times

__all__ = ["RampParameters", "DEFAULT_BIAS", "readpatt", "macc_frame_schedule", "frame_mean_charge",
           "to_adu", "sparse_threshold", "SPARSE_GROUP_CAP", "MAX_SPARSE_WINDOW"]

DEFAULT_BIAS = 2000.0          # ADU pedestal: read noise never clips at 0
P_POISSON, P_READ, P_KTC, P_SPARSE = 0, 1, 2, 3


@dataclass(kw_only=True)
class RampParameters:
    """Validated readout and detector parameters of a ramp simulation (keyword-only).

    nmd : (n, m, d) MACC readout;  nramps : ramps (integrations);  tframe : s;
    ron : e-/read;  dark, thermal_dark : e-/s/px (dark may be a per-pixel array);
    roic_glow : e-/px/frame;  gain : ADU/e-;  saturation, bias : ADU;  ktc_noise : e- per reset;
    full_well : e- (default (saturation − bias)/gain);  sparse_max_group : e-/group (None: auto);
    gauss_min_mean : e-/frame above which Poisson increments are drawn as Gaussians.
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
        nmd = self.nmd
        try:
            n, m, d = (int(v) for v in nmd)
        except Exception as exc:
            raise ReadoutError(f"readout mode must be (n, m, d) integers, got {nmd!r}") from exc
        if m < 1:
            raise ReadoutError(f"readout mode {nmd}: m (frames per group) must be ≥ 1")
        if d < 0:
            raise ReadoutError(f"readout mode {nmd}: d (dropped frames) must be ≥ 0")
        if n < 2:
            raise ReadoutError(f"readout mode {nmd}: n must be ≥ 2 groups to measure a slope")
        if int(self.nramps) != self.nramps or self.nramps < 1:
            raise ReadoutError(f"nramps must be an integer ≥ 1, got {self.nramps!r}")
        for name in ("tframe", "gain"):
            val = getattr(self, name)
            if not (np.isfinite(val) and val > 0):
                raise ValueError(f"{name} must be > 0, got {val}")
        for name in ("ron", "roic_glow", "ktc_noise", "thermal_dark", "bias"):
            val = getattr(self, name)
            if not (np.isfinite(val) and val >= 0):
                raise ValueError(f"{name} must be finite and ≥ 0, got {val}")
        if not 0 < self.saturation <= 65535:
            raise ValueError(f"saturation must be in (0, 65535] ADU, got {self.saturation}")
        self.nmd, self.nramps = (n, m, d), int(self.nramps)
        self.tframe, self.ron, self.gain = float(self.tframe), float(self.ron), float(self.gain)
        self.thermal_dark, self.roic_glow = float(self.thermal_dark), float(self.roic_glow)
        self.saturation, self.bias, self.ktc_noise = float(self.saturation), float(self.bias), float(self.ktc_noise)
        self.full_well = float((self.saturation - self.bias) / self.gain if self.full_well is None
                               else self.full_well)
        if self.sparse_max_group is not None and not float(self.sparse_max_group) >= 0:
            raise ValueError(f"sparse_max_group must be ≥ 0 e-/group (or None), got {self.sparse_max_group}")
        self.sparse_max_group = None if self.sparse_max_group is None else float(self.sparse_max_group)
        self.gauss_min_mean = float(self.gauss_min_mean)
        t = readout_times(self.nmd, self.tframe)
        self.nframes, self.tgroup = t["nframes"], t["group_time"]

    def attrs(self, seed):
        """Root attributes of the raw file (JWST-like names)."""
        n, m, d = self.nmd
        return {"NINTS": self.nramps, "NGROUPS": n, "NFRAMES": m, "GROUPGAP": d, "TFRAME": self.tframe,
                "TGROUP": self.tgroup, "READPATT": readpatt(self.nmd), "GAIN": self.gain,
                "READNOISE": self.ron, "SEED": int(seed), "BUNIT": "ADU", "BIAS": self.bias,
                "SATURATION": self.saturation, "FULLWELL": self.full_well}


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
