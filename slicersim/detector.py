"""H4RG-like detector: QE, gain, dark, ROIC glow, read noise, MACC readout and variance models.

A MACC(n, m, d) ramp has n groups of m averaged frames with d dropped frames
between groups; ``nramps`` ramps are summed.  Times (frame time t_f):

* frames per ramp  N_f   = n (m + d) − d
* exposure / ramp  t_exp = N_f t_f
* integration      t_int = (n − 1)(m + d) t_f     (first to last group)
* group time       t_g   = (m + d) t_f
"""
from __future__ import annotations

import numpy as np

from .curves import read_curve

__all__ = ["Detector", "ReadoutError", "check_readout", "readout_times",
           "variance_rauscher07", "variance_kubik16", "rauscher07_coefficients",
           "VARIANCE_MODELS"]


class ReadoutError(ValueError):
    """Impossible readout mode or number of ramps."""


def check_readout(nmd, nramps=1, min_group=2, max_group=None):
    """Validate a MACC readout (n, m, d) and a number of ramps; return ints."""
    try:
        n, m, d = (int(v) for v in nmd)
    except Exception as exc:
        raise ReadoutError(f"readout mode must be a triple (n, m, d) of integers, got {nmd!r}") from exc
    if any(int(v) != v for v in nmd):
        raise ReadoutError(f"readout mode values must be integers, got {nmd!r}")
    if m < 1:
        raise ReadoutError(f"readout mode {nmd}: m (frames per group) must be ≥ 1")
    if d < 0:
        raise ReadoutError(f"readout mode {nmd}: d (dropped frames) must be ≥ 0")
    if n < max(2, min_group or 2):
        raise ReadoutError(f"readout mode {nmd}: n (groups) must be ≥ {max(2, min_group or 2)} "
                           "(a slope needs at least two groups)")
    if max_group is not None and n > max_group:
        raise ReadoutError(f"readout mode {nmd}: n = {n} exceeds max_group = {max_group}")
    if int(nramps) != nramps or nramps < 1:
        raise ReadoutError(f"nramps must be an integer ≥ 1, got {nramps!r}")
    return (n, m, d), int(nramps)


def readout_times(nmd, tframe):
    """Dict of frames per ramp, exposure, integration and group times [s] for (n, m, d)."""
    n, m, d = nmd
    nframes = n * (m + d) - d
    return {"nframes": nframes, "exposure_time": nframes * tframe,
            "integration_time": (n - 1) * (m + d) * tframe, "group_time": (m + d) * tframe}


# --------------------------------------------------------------------------- #
#  variance models (per pixel, e- rate in, ADU² out, reference gain convention) #
# --------------------------------------------------------------------------- #
def rauscher07_coefficients(nmd, tframe):
    """(a, b) with V_R = a σ_r² + b S  [e-²] for a rate S [e-/s] (Rauscher et al. 2007, corrected).

    a = 12 (n−1) / (m n (n+1))
    b = 6 (n²+1) (n−1) t_g / (5 n (n+1)) − 2 (m²−1)(n−1) t_f / (m n (n+1))
    """
    n, m, d = (np.asarray(v, dtype=float) for v in nmd)
    tgroup = (m + d) * tframe
    a = 12.0 * (n - 1) / (m * n * (n + 1))
    b = 6.0 * (n**2 + 1) / (5.0 * n * (n + 1)) * (n - 1) * tgroup \
        - 2.0 * (m**2 - 1) * (n - 1) / (m * n * (n + 1)) * tframe
    return a, b


def variance_rauscher07(flux, nmd, tframe, ron, dark, gain=1.0):
    """Variance [ADU²] of the integrated signal over t_int for a pixel receiving ``flux`` [e-/s]
    plus ``dark`` [e-/s] (Rauscher et al. 2007 as corrected in 2010).  Divided by gain²
    (slicersim 1.0 convention)."""
    a, b = rauscher07_coefficients(nmd, tframe)
    return (a * ron**2 + b * (np.asarray(flux, dtype=float) + dark)) / gain**2


def variance_kubik16(flux, nmd, tframe, ron, dark, gain=1.0):
    """Variance [ADU²] of the Kubik et al. (2016) maximum-likelihood signal estimator.

    With S_A = (flux + dark) g t_int [ADU], ĝ = S_A/(n−1), α = (1−m²)/(3m(m+d)),
    γ = 2 g² σ_r²/m, β = γ/(1+α), s_β = ĝ + β/g:
    V = [((n−1)+α) ĝ + γ/g] g · 4 s_β² / [(1+α)² g² + 4 s_β²].
    It equals Rauscher07 for n ≤ 3 in the read-noise limit and within ~4 % for
    bright pixels with few groups; for many groups the read-noise term stays at
    2σ²/m (two-point limit) where Rauscher's least-squares term falls as 12σ²/(m n).
    """
    n, m, d = nmd
    tint = (n - 1) * (m + d) * tframe
    signal = (np.asarray(flux, dtype=float) + dark) * gain * tint
    gghat = signal / (n - 1)
    alpha = (1.0 - m**2) / (3.0 * m * (m + d))
    gamma = 2.0 * gain**2 * ron**2 / m
    beta = gamma / (1.0 + alpha)
    s_beta = gghat + beta / gain
    var = (((n - 1) + alpha) * gghat + gamma / gain) * gain * 4 * s_beta**2
    return var / ((1 + alpha) ** 2 * gain**2 + 4 * s_beta**2)


VARIANCE_MODELS = {"rauscher07": variance_rauscher07, "rauscher10": variance_rauscher07,
                   "kubik16": variance_kubik16}


class Detector:
    """HxRG detector with a MACC readout.

    Parameters
    ----------
    qe : float, (λ[Å], QE) arrays or ECSV/CSV path — QE [e-/ph], 0 outside the table
    gain : ADU/e-;  dark : e-/s/px;  roic_glow : e-/px/frame;  ron : e-/frame
    tframe : s;  pixel_size : µm;  saturation : ADU (0 or None: none)
    nmd : (n, m, d);  min_group, max_group : allowed n range
    variance_model : "Rauscher07" or "Kubik16"
    """

    mutable_parameters = ("qe", "gain", "dark", "roic_glow", "ron", "tframe", "pixel_size",
                          "saturation", "nmd", "min_group", "max_group", "variance_model", "shape",
                          "thermal_dark_range")

    def __init__(self, qe=0.8, gain=1.0, dark=2.8e-3, roic_glow=3e-3, ron=12.0, tframe=2.83,
                 pixel_size=10.0, saturation=65535.0, nmd=(16, 8, 0), min_group=2, max_group=64,
                 variance_model="Rauscher07", shape=(4096, 4096), thermal_dark_range=None):
        self.qe = qe
        self.gain = float(gain)
        self.dark = float(dark)
        self.roic_glow = float(roic_glow)
        self.ron = float(ron)
        self.tframe = float(tframe)
        self.pixel_size = float(pixel_size)
        self.saturation = float(saturation) if saturation else np.inf
        self.min_group = int(min_group)
        self.max_group = int(max_group) if max_group else None
        self.variance_model = str(variance_model)
        self.shape = tuple(int(s) for s in shape)
        self.thermal_dark_range = thermal_dark_range
        self._check()
        self.nmd, _ = check_readout(nmd, 1, self.min_group, None)
        self._qe_table = self._load_qe(qe)

    def _check(self):
        for name in ("gain", "tframe", "pixel_size"):
            if not getattr(self, name) > 0:
                raise ValueError(f"detector {name} must be > 0")
        for name in ("dark", "roic_glow", "ron"):
            val = getattr(self, name)
            if not (np.isfinite(val) and val >= 0):
                raise ValueError(f"detector {name} must be finite and ≥ 0, got {val}")
        if self.variance_model.lower() not in VARIANCE_MODELS:
            raise ValueError(f"unknown variance model {self.variance_model!r}: "
                             "use 'Rauscher07' or 'Kubik16'")
        if self.min_group < 2:
            raise ValueError("min_group must be ≥ 2")

    @staticmethod
    def _load_qe(qe):
        if isinstance(qe, str):
            lbda, cols = read_curve(qe)
            return lbda, next(iter(cols.values()))
        if np.isscalar(qe):
            if not 0 <= float(qe) <= 10:
                raise ValueError(f"QE must be ≥ 0, got {qe}")
            return None
        lbda, val = (np.asarray(v, dtype=float) for v in qe)
        return lbda, val

    def update(self, **kwargs):
        """Change mutable parameters (validated)."""
        for key in kwargs:
            if key not in self.mutable_parameters:
                raise ValueError(f"unknown detector parameter {key!r}")
        params = {k: getattr(self, k) for k in self.mutable_parameters}
        params["saturation"] = 0 if not np.isfinite(self.saturation) else self.saturation
        params.update(kwargs)
        self.__init__(**params)

    # -- curves -----------------------------------------------------------------
    def get_qe(self, lbda):
        """QE [e-/ph] at λ [Å]: linear interpolation of the table, 0 outside it."""
        lbda = np.asarray(lbda, dtype=float)
        if self._qe_table is None:
            return np.full_like(lbda, float(self.qe))
        tl, tv = self._qe_table
        return np.interp(lbda, tl, tv, left=0.0, right=0.0)

    # -- readout ------------------------------------------------------------------
    @property
    def pixel_area(self):
        """Pixel area [m²]."""
        return (self.pixel_size * 1e-6) ** 2

    def times(self, nmd=None):
        return readout_times(self.nmd if nmd is None else nmd, self.tframe)

    @property
    def integration_time(self):
        """(n − 1)(m + d) t_f [s] per ramp."""
        return self.times()["integration_time"]

    @property
    def exposure_time(self):
        """(n (m + d) − d) t_f [s] per ramp."""
        return self.times()["exposure_time"]

    def effective_dark(self, thermal_dark=0.0):
        """dark + roic_glow / t_f + thermal dark [e-/s/px]."""
        return self.dark + self.roic_glow / self.tframe + thermal_dark

    def data_volume(self, nmd=None, nramps=1, bits=16):
        """Raw group-level data volume [GB = 1e9 bytes] of nramps ramps."""
        n = (self.nmd if nmd is None else nmd)[0]
        return nramps * n * self.shape[0] * self.shape[1] * bits / 8e9

    def pixel_variance(self, flux, thermal_dark=0.0, nmd=None, ron=None):
        """Per-pixel variance [ADU²] over one ramp for a rate ``flux`` [e-/s]."""
        model = VARIANCE_MODELS[self.variance_model.lower()]
        return model(flux, self.nmd if nmd is None else nmd, self.tframe,
                     self.ron if ron is None else ron, self.effective_dark(thermal_dark), self.gain)
