"""H4RG-like detector: QE, gain, dark, ROIC glow, read noise, saturation and MACC readout.

The readout physics (MACC times, variance models) lives in :mod:`slicersim.physics.readout`.
"""
from __future__ import annotations

from slicersim.errors import ParameterError, ReadoutError

import numpy as np

from slicersim.io.curves import read_curve
from slicersim.physics.readout import VARIANCE_MODELS, check_readout, readout_times
from slicersim.versioning import Versioned

__all__ = ["Detector"]




class Detector(Versioned):
    """HxRG detector with a MACC readout.

    Parameters
    ----------
    qe : float, (λ[Å], QE) arrays or ECSV/CSV path — QE [e-/ph], 0 outside the table
    gain : ADU/e-;  dark : e-/s/px;  roic_glow : e-/px/frame;  ron : e-/frame
    tframe : s;  pixel_size : µm (gain, tframe, pixel_size finite > 0)
    saturation : ADU, finite > 0 (0, None or inf: no saturation)
    thermal_dark_range : None or (min, max) [Å], 0 < min < max: range of the undispersed thermal dark
    nmd : (n, m, d);  min_group, max_group : allowed n range (max_group an integer ≥ min_group,
    or None: no limit)
    variance_model : "Rauscher07" or "Kubik16"
    """

    mutable_parameters = ("qe", "gain", "dark", "roic_glow", "ron", "tframe", "pixel_size",
                          "saturation", "nmd", "min_group", "max_group", "variance_model", "shape",
                          "thermal_dark_range")

    def __init__(self, qe=0.8, gain=1.0, dark=2.8e-3, roic_glow=3e-3, ron=12.0, tframe=2.83,
                 pixel_size=10.0, saturation=65535.0, nmd=(16, 8, 0), min_group=2, max_group=64,
                 variance_model="Rauscher07", shape=(4096, 4096), thermal_dark_range=None):
        try:
            self.qe = qe
            self.gain = float(gain)
            self.dark = float(dark)
            self.roic_glow = float(roic_glow)
            self.ron = float(ron)
            self.tframe = float(tframe)
            self.pixel_size = float(pixel_size)
            self.saturation = self._check_saturation(saturation)
            self.min_group = int(min_group)
            self.max_group = self._check_max_group(max_group, self.min_group)
            self.variance_model = str(variance_model)
            self.shape = tuple(int(s) for s in shape)
            self.thermal_dark_range = self._check_thermal_dark_range(thermal_dark_range)
            self._check()
            self.nmd, _ = check_readout(nmd, 1, self.min_group, None)
            self._qe_table = self._load_qe(qe)
        except (ParameterError, ReadoutError):
            raise
        except (TypeError, ValueError, OSError) as exc:
            raise ParameterError(f"invalid detector parameter: {exc}") from exc

    @staticmethod
    def _check_saturation(saturation):
        """Saturation [ADU]: finite > 0; None, 0 or +inf mean no saturation (stored as inf)."""
        if saturation is None:
            return np.inf
        sat = float(saturation)
        if sat == 0 or sat == np.inf:
            return np.inf
        if not (np.isfinite(sat) and sat > 0):
            raise ParameterError(f"detector saturation must be finite and > 0 ADU (0 or None: no saturation), "
                                 f"got {saturation!r}")
        return sat

    @staticmethod
    def _check_max_group(max_group, min_group):
        """max_group: None (no limit) or an integer ≥ min_group."""
        if max_group is None:
            return None
        try:
            ok = not isinstance(max_group, (bool, np.bool_, str)) and float(max_group) == int(max_group)
        except (TypeError, ValueError, OverflowError):
            ok = False
        if not ok or int(max_group) < min_group:
            raise ParameterError(f"max_group must be an integer ≥ min_group = {min_group} (None: no limit), "
                                 f"got {max_group!r}")
        return int(max_group)

    @staticmethod
    def _check_thermal_dark_range(rng):
        """None (the simulation's own grid) or (lo, hi) [Å], finite with 0 < lo < hi."""
        if rng is None:
            return None
        try:
            if isinstance(rng, (str, bytes)):
                raise TypeError
            lo, hi = (float(v) for v in rng)
        except (TypeError, ValueError):
            raise ParameterError(f"thermal_dark_range must be None or (min, max) in Å, got {rng!r}") from None
        if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo < hi):
            raise ParameterError(f"thermal_dark_range must be finite with 0 < min < max, got {rng!r}")
        return lo, hi

    def _check(self):
        for name in ("gain", "tframe", "pixel_size"):
            val = getattr(self, name)
            if not (np.isfinite(val) and val > 0):
                raise ParameterError(f"detector {name} must be finite and > 0, got {val}")
        for name in ("dark", "roic_glow", "ron"):
            val = getattr(self, name)
            if not (np.isfinite(val) and val >= 0):
                raise ParameterError(f"detector {name} must be finite and ≥ 0, got {val}")
        if self.variance_model.lower() not in VARIANCE_MODELS:
            raise ParameterError(f"unknown variance model {self.variance_model!r}: "
                             "use 'Rauscher07' or 'Kubik16'")
        if self.min_group < 2:
            raise ParameterError("min_group must be ≥ 2")

    @staticmethod
    def _load_qe(qe):
        """None for a scalar QE (within [0, 1]), else the (λ, QE) table: ≥ 2 points, finite,
        strictly increasing λ, QE within [0, 1]."""
        if isinstance(qe, str):
            lbda, cols = read_curve(qe)
            val = next(iter(cols.values()))
        elif np.isscalar(qe):
            if isinstance(qe, bytes) or not 0 <= float(qe) <= 1:
                raise ParameterError(f"QE must be within [0, 1] e-/ph, got {qe!r}")
            return None
        else:
            try:
                lbda, val = (np.asarray(v, dtype=float) for v in qe)
            except (TypeError, ValueError):
                raise ParameterError(f"QE must be a number, a (λ, QE) pair of arrays or a curve file, "
                                     f"got {qe!r}") from None
        if lbda.ndim != 1 or lbda.shape != val.shape or lbda.size < 2:
            raise ParameterError(f"QE curve: need matching 1-D λ and QE arrays (≥ 2 points), got shapes "
                                 f"{lbda.shape} and {val.shape}")
        if not (np.all(np.isfinite(lbda)) and np.all(np.diff(lbda) > 0)):
            raise ParameterError("QE curve: wavelengths must be finite and strictly increasing")
        if not (np.all(np.isfinite(val)) and np.all((val >= 0) & (val <= 1))):
            raise ParameterError(f"QE curve: values must be finite and within [0, 1] e-/ph "
                                 f"(got {np.nanmin(val):g} to {np.nanmax(val):g})")
        return lbda, val

    def updated(self, **kwargs):
        """A validated copy with ``kwargs`` changed (``self`` untouched); see :meth:`update`."""
        unknown = sorted(set(kwargs) - set(self.mutable_parameters))
        if unknown:
            raise ParameterError(f"unknown detector parameter(s) {unknown}; accepted: "
                                 f"{', '.join(self.mutable_parameters)}")
        params = {k: getattr(self, k) for k in self.mutable_parameters}
        params["saturation"] = 0 if not np.isfinite(self.saturation) else self.saturation
        params.update(kwargs)
        return Detector(**params)

    def update(self, **kwargs):
        """Change mutable parameters, atomically: a copy is built and validated first; on
        error (:class:`ParameterError`, :class:`ReadoutError`) nothing changes."""
        self._adopt(self.updated(**kwargs))

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
    def integration_time_per_ramp(self):
        """(n − 1)(m + d) t_f [s] of one ramp."""
        return self.times()["integration_time_per_ramp"]

    @property
    def exposure_time_per_ramp(self):
        """(n (m + d) − d) t_f [s] of one ramp."""
        return self.times()["exposure_time_per_ramp"]

    def effective_dark(self, thermal_dark=0.0):
        """dark + roic_glow / t_f + thermal dark [e-/s/px]."""
        return self.dark + self.roic_glow / self.tframe + thermal_dark

    def data_volume(self, nmd=None, nramps=1, bits=16):
        """Raw group-level data volume [GB = 1e9 bytes] of nramps ramps."""
        n = (self.nmd if nmd is None else nmd)[0]
        return nramps * n * self.shape[0] * self.shape[1] * bits / 8e9

    def pixel_variance(self, flux, thermal_dark=0.0, nmd=None, ron=None, dark=None, conventions="physical"):
        """Per-pixel variance [ADU²] over one ramp for a rate ``flux`` [e-/s]; ``dark`` [e-/s]
        overrides the effective dark (dark + glow/t_f + ``thermal_dark``)."""
        model = VARIANCE_MODELS[self.variance_model.lower()]
        dark = self.effective_dark(thermal_dark) if dark is None else dark
        return model(flux, self.nmd if nmd is None else nmd, self.tframe,
                     self.ron if ron is None else ron, dark, self.gain, conventions)
