"""H4RG-like detector: QE, gain, dark, ROIC glow, read noise, saturation and MACC readout.

The readout physics (MACC times, variance models) lives in :mod:`slicersim.physics.readout`.
"""
from __future__ import annotations

import numpy as np

from slicersim import validation
from slicersim.errors import ParameterError, ReadoutError  # noqa: F401  (re-exported)
from slicersim.instrument.names import check_parameter_names

from slicersim.io.curves import read_curve
from slicersim.physics.readout import VARIANCE_MODELS, check_readout, readout_times
from slicersim.versioning import Versioned

__all__ = ["Detector"]




class Detector(Versioned):
    """HxRG detector with a MACC readout.

    The numbers with a unit (gain, dark, roic_glow, ron, tframe, pixel_size) are each a plain
    number in that unit or an astropy Quantity (converted).

    Parameters
    ----------
    qe : float, tuple of array_like or str, optional
        QE [e-/ph]: a number, (λ [Å], QE) arrays or an ECSV/CSV path; 0 outside the table.
    gain : float, optional
        Gain [ADU/e-], finite > 0.
    dark : float, optional
        Dark current [e-/s/px], ≥ 0.
    roic_glow : float, optional
        ROIC glow [e-/px/frame], ≥ 0.
    ron : float, optional
        Read noise per frame [electron], ≥ 0.
    tframe : float, optional
        Frame time [s], finite > 0.
    pixel_size : float, optional
        Pixel size [µm], finite > 0.
    saturation : float, optional
        Saturation [ADU], finite > 0 (0, None or inf: no saturation).
    nmd : tuple of int, optional
        The readout (n, m, d).
    min_group, max_group : int, optional
        Allowed n range (max_group an integer ≥ min_group, or None: no limit).
    variance_model : {"Rauscher07", "Kubik16"}, optional
        Variance model of a MACC ramp.
    shape : tuple of int, optional
        (rows, cols) of the detector [px].
    thermal_dark_range : tuple of float, optional
        None or (min, max) [Å], 0 < min < max: range of the undispersed thermal dark.
    """

    mutable_parameters = ("qe", "gain", "dark", "roic_glow", "ron", "tframe", "pixel_size",
                          "saturation", "nmd", "min_group", "max_group", "variance_model", "shape",
                          "thermal_dark_range")

    def __init__(self, qe=0.8, gain=1.0, dark=2.8e-3, roic_glow=3e-3, ron=12.0, tframe=2.83,
                 pixel_size=10.0, saturation=65535.0, nmd=(16, 8, 0), min_group=2, max_group=64,
                 variance_model="Rauscher07", shape=(4096, 4096), thermal_dark_range=None):
        # 14 parameters: the paper's documented constructor (every one a detector property)
        num, top, ok = validation.number, validation.DETECTOR_MAX, validation.PLAUSIBLE
        self.qe = qe
        self.gain = num("gain", gain, low=0.0, low_open=True, high=top["gain"], unit="adu / electron", plausible=ok["gain"])
        self.dark = num("dark", dark, low=0.0, high=top["dark"], unit="electron / s", plausible=ok["dark"])
        self.roic_glow = num("roic_glow", roic_glow, low=0.0, high=top["roic_glow"], unit="electron")
        self.ron = num("ron", ron, low=0.0, high=top["ron"], unit="electron", plausible=ok["ron"])
        self.tframe = num("tframe", tframe, low=0.0, low_open=True, high=top["tframe"], unit="s", plausible=ok["tframe"])
        self.pixel_size = num("pixel_size", pixel_size, low=0.0, low_open=True, unit="um", plausible=ok["pixel_size"])
        self.saturation = self._check_saturation(saturation)
        self.min_group = validation.integer("min_group", min_group, low=2)
        self.max_group = self._check_max_group(max_group, self.min_group)
        self.variance_model = self._check_variance_model(variance_model)
        self.shape = validation.shape("shape", shape)
        self.thermal_dark_range = self._check_thermal_dark_range(thermal_dark_range)
        self.nmd, _ = check_readout(nmd, 1, self.min_group, None)
        try:
            self._qe_table = self._load_qe(qe)
        except (ParameterError, ReadoutError):
            raise
        except (TypeError, ValueError, OSError) as exc:
            raise ParameterError(f"qe: invalid QE {validation.short_repr(qe)}: {exc}") from exc

    @staticmethod
    def _check_variance_model(model):
        """"Rauscher07" or "Kubik16" (any case; kept as given)."""
        if isinstance(model, str) and model.lower() in VARIANCE_MODELS:
            return model
        return validation.choice("variance_model", model, ("Rauscher07", "Rauscher10", "Kubik16"))

    @staticmethod
    def _check_saturation(saturation):
        """Saturation [ADU]: finite > 0; None, 0 or +inf mean no saturation (stored as inf)."""
        if saturation is None:
            return np.inf
        try:
            unlimited = not isinstance(saturation, (str, bytes)) and \
                float(getattr(saturation, "value", saturation)) == np.inf
        except (TypeError, ValueError):
            unlimited = False
        if unlimited:
            return np.inf
        sat = validation.number("saturation", saturation, low=0.0, unit="adu")
        return np.inf if sat == 0 else sat

    @staticmethod
    def _check_max_group(max_group, min_group):
        """max_group: None (no limit) or an integer ≥ min_group."""
        if max_group is None:
            return None
        return validation.integer("max_group", max_group, low=min_group)

    @staticmethod
    def _check_thermal_dark_range(rng):
        """None (the simulation's own grid) or (lo, hi) [Å], finite with 0 < lo < hi."""
        if rng is None:
            return None
        if isinstance(rng, (str, bytes)) or not hasattr(rng, "__len__") or len(rng) != 2:
            raise ParameterError(f"thermal_dark_range must be None or (min, max) in Å, got "
                                 f"{validation.short_repr(rng)}")
        lo, hi = (validation.number(f"thermal_dark_range[{i}]", v, low=0.0, low_open=True, unit="Angstrom")
                  for i, v in enumerate(rng))
        if not lo < hi:
            raise ParameterError(f"thermal_dark_range must have min < max, got {validation.short_repr(rng)}")
        return lo, hi

    @staticmethod
    def _load_qe(qe):
        """None for a scalar QE (within [0, 1]), else the (λ, QE) table: ≥ 2 points, finite,
        strictly increasing λ, QE within [0, 1]."""
        if isinstance(qe, str):
            lbda, cols = read_curve(qe)
            val = next(iter(cols.values()))
        elif np.isscalar(qe):
            validation.fraction("qe", qe)
            return None
        else:
            try:
                lbda, val = (np.asarray(v, dtype=float) for v in qe)
            except (TypeError, ValueError):
                raise ParameterError(f"qe must be a number, a (λ, QE) pair of arrays or a curve file, "
                                     f"got {validation.short_repr(qe)}") from None
        if lbda.ndim != 1 or lbda.shape != val.shape or lbda.size < 2:
            raise ParameterError(f"qe curve: need matching 1-D λ and QE arrays (≥ 2 points), got shapes "
                                 f"{lbda.shape} and {val.shape}")
        if not (np.all(np.isfinite(lbda)) and np.all(np.diff(lbda) > 0)):
            raise ParameterError("qe curve: wavelengths must be finite and strictly increasing")
        if not (np.all(np.isfinite(val)) and np.all((val >= 0) & (val <= 1))):
            raise ParameterError(f"qe curve: values must be finite and within [0, 1] e-/ph "
                                 f"(got {np.nanmin(val):g} to {np.nanmax(val):g})")
        return lbda, val

    def updated(self, **kwargs):
        """A validated copy with ``kwargs`` changed (``self`` untouched); see :meth:`update`.

        Parameters
        ----------
        **kwargs
            As :meth:`update`.

        Returns
        -------
        Detector
            The copy.
        """
        check_parameter_names("detector", kwargs, self.mutable_parameters)
        params = {k: getattr(self, k) for k in self.mutable_parameters}
        params["saturation"] = 0 if not np.isfinite(self.saturation) else self.saturation
        params.update(kwargs)
        return Detector(**params)

    def update(self, **kwargs):
        """Change mutable parameters, atomically: a copy is built and validated first; on
        error (:class:`~slicersim.errors.ParameterError`, :class:`~slicersim.errors.ReadoutError`)
        nothing changes.

        Parameters
        ----------
        **kwargs
            Names of ``mutable_parameters``.

        Returns
        -------
        None
            Changed in place.
        """
        self._adopt(self.updated(**kwargs))

    # -- curves -----------------------------------------------------------------
    def get_qe(self, lbda):
        """QE [e-/ph] at λ [Å]: linear interpolation of the table, 0 outside it.

        Parameters
        ----------
        lbda : array_like
            Wavelengths [Å].

        Returns
        -------
        numpy.ndarray
            The QE [e-/ph], of the shape of ``lbda``.
        """
        lbda = np.asarray(lbda, dtype=float)
        if self._qe_table is None:
            return np.full_like(lbda, float(self.qe))
        tl, tv = self._qe_table
        return np.interp(lbda, tl, tv, left=0.0, right=0.0)

    def show_qe(self, lbda=None, ax=None, savefile=None):
        """Figure of the QE [e-/ph] versus λ [Å]; see :func:`slicersim.plotting.spectra.plot_curves`.

        Parameters
        ----------
        lbda : array_like, optional
            Wavelengths [Å] (default: the table's range, else 4000–17000 Å).
        ax : matplotlib.axes.Axes, optional
            None (new figure) or an Axes.
        savefile : str, os.PathLike or file object, optional
            If given the figure is saved there.

        Returns
        -------
        matplotlib.figure.Figure
            The figure.
        """
        from slicersim.plotting import plot_curves
        if lbda is None:
            lo, hi = (self._qe_table[0][0], self._qe_table[0][-1]) if self._qe_table is not None else (4e3, 1.7e4)
            lbda = np.linspace(lo, hi, 500)
        lbda = validation.array("lbda [AA]", lbda, ndim=1)
        return plot_curves(lbda, {"QE": self.get_qe(lbda)}, "quantum efficiency [e-/ph]", title="detector QE",
                           ax=ax, savefile=savefile, ylim=(0, 1.02))

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
        """dark + roic_glow / t_f + thermal dark [e-/s/px].

        Parameters
        ----------
        thermal_dark : float or numpy.ndarray, optional
            Thermal dark [e-/s/px].

        Returns
        -------
        float or numpy.ndarray
            The effective dark [e-/s/px].
        """
        return self.dark + self.roic_glow / self.tframe + thermal_dark

    def data_volume(self, nmd=None, nramps=1, bits=16):
        """Raw group-level data volume [GB = 1e9 bytes] of nramps ramps.

        Parameters
        ----------
        nmd : tuple of int, optional
            Readout (n, m, d) (default: the detector's).
        nramps : int, optional
            Number of ramps.
        bits : int, optional
            Bits per pixel per group.

        Returns
        -------
        float
            The data volume [GB].
        """
        n = (self.nmd if nmd is None else nmd)[0]
        return nramps * n * self.shape[0] * self.shape[1] * bits / 8e9

    def pixel_variance(self, flux, thermal_dark=0.0, nmd=None, ron=None, dark=None, conventions="physical"):
        """Per-pixel variance [ADU²] over one ramp for a rate ``flux``.

        Parameters
        ----------
        flux : float or numpy.ndarray
            Photo-electron rate [e-/s].
        thermal_dark : float or numpy.ndarray, optional
            Thermal dark [e-/s/px], part of the effective dark.
        nmd : tuple of int, optional
            Readout (n, m, d) (default: the detector's).
        ron : float, optional
            Read noise per frame [electron] (default: the detector's).
        dark : float or numpy.ndarray, optional
            [e-/s]: overrides the effective dark (dark + glow/t_f + ``thermal_dark``).
        conventions : {"physical", "slicersim-1.0"}, optional
            Physics conventions.

        Returns
        -------
        numpy.ndarray
            The variance [ADU²], of the shape of ``flux``.
        """
        model = VARIANCE_MODELS[self.variance_model.lower()]
        dark = self.effective_dark(thermal_dark) if dark is None else dark
        return model(flux, self.nmd if nmd is None else nmd, self.tframe,
                     self.ron if ron is None else ron, dark, self.gain, conventions)
