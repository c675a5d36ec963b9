"""Telescope: collecting area, diffraction scale and mirror thermal emission."""
from __future__ import annotations

import numpy as np

from slicersim.constants import AIRY_SIGMA_FACTOR, ARCSEC, LBDA_REF_AA
from slicersim import validation
from slicersim.errors import ParameterError
from slicersim.instrument.names import check_parameter_names
from slicersim.physics.thermal import photon_radiance
from slicersim.versioning import Versioned

__all__ = ["Telescope"]


class Telescope(Versioned):
    """An (annular) telescope aperture with warm mirrors.

    Parameters
    ----------
    diameter_ext, diameter_int : float or astropy.units.Quantity
        Outer / central-obscuration diameter [m].
    temperature : float or sequence of float
        Mirror temperature [K], or one value per mirror group.
    emissivity, nelements : sequence
        Per mirror group emissivity and count (a scalar applies to every group).
    guiding_sigma : float or astropy.units.Quantity
        Achromatic Gaussian jitter [arcsec].
    """

    mutable_parameters = ("diameter_ext", "diameter_int", "temperature", "emissivity",
                          "nelements", "guiding_sigma")

    def __init__(self, diameter_ext=3.0, diameter_int=0.0, temperature=293.0,
                 emissivity=(0.05, 0.02, 0.02, 0.02), nelements=(1, 1, 1, 1), guiding_sigma=0.010):
        try:
            self.diameter_ext = validation.number("diameter_ext", diameter_ext, low=0.0, low_open=True, unit="m",
                                                  plausible=validation.PLAUSIBLE["diameter_ext"])
            self.diameter_int = validation.number("diameter_int", diameter_int, low=0.0, unit="m",
                                                  plausible=validation.PLAUSIBLE["diameter_int"])
            emissivity = np.atleast_1d(np.asarray(emissivity, dtype=float))
            nelements = np.atleast_1d(np.asarray(nelements, dtype=float))
            if not np.all(np.isfinite(nelements)) or np.any(nelements != np.round(nelements)):
                raise ParameterError(f"telescope nelements must be integers, got {nelements.tolist()}")
            nelements = nelements.astype(int)
            if emissivity.ndim != 1 or nelements.ndim != 1:
                raise ParameterError("telescope emissivity and nelements must be scalars or 1-D lists")
            if emissivity.size == 1 and nelements.size > 1:
                emissivity = np.full(nelements.size, emissivity[0])
            elif nelements.size == 1 and emissivity.size > 1:
                nelements = np.full(emissivity.size, nelements[0])
            self.emissivity = list(emissivity)
            self.nelements = list(nelements)
            temperature = validation.array("telescope temperature [K]", temperature, ndim=(0, 1), unit="K")
            if np.ndim(temperature) == 0:
                self.temperature = float(temperature)
            else:
                temps = [float(t) for t in np.asarray(temperature, dtype=float).ravel()]
                if len(temps) != len(self.emissivity):
                    raise ParameterError(f"telescope temperature needs one value per mirror group: "
                                         f"expected length {len(self.emissivity)}, got {len(temps)}")
                self.temperature = temps
            self.guiding_sigma = validation.number("guiding_sigma", guiding_sigma, low=0.0, unit="arcsec",
                                                   plausible=validation.PLAUSIBLE["guiding_sigma"])
        except ParameterError:
            raise
        except (TypeError, ValueError) as exc:
            raise ParameterError(f"invalid telescope parameter: {exc}") from exc
        self._check()

    def _check(self):
        if not (np.isfinite(self.diameter_ext) and self.diameter_ext > 0) \
                or not (0 <= self.diameter_int < self.diameter_ext):
            raise ParameterError("telescope needs a finite diameter_ext > 0 and 0 <= diameter_int < diameter_ext, "
                                 f"got {self.diameter_ext}, {self.diameter_int}")
        if len(self.emissivity) != len(self.nelements):
            raise ParameterError("telescope emissivity and nelements must have the same length")
        temps = np.atleast_1d(self.temperature)
        if not (np.all(np.isfinite(temps)) and np.all(temps >= 0)):
            raise ParameterError(f"telescope temperature must be finite and ≥ 0 K, got {self.temperature}")
        eps = np.asarray(self.emissivity, dtype=float)
        if not (np.all(np.isfinite(eps)) and np.all((eps >= 0) & (eps <= 1))):
            raise ParameterError(f"telescope emissivity must be within [0, 1], got {self.emissivity}")
        if np.any(np.asarray(self.nelements) < 0):
            raise ParameterError(f"telescope nelements must be ≥ 0, got {self.nelements}")
        if not (np.isfinite(self.guiding_sigma) and self.guiding_sigma >= 0):
            raise ParameterError("guiding_sigma must be >= 0")

    @property
    def nmirrors(self):
        """Number of mirror groups (length of the per-mirror lists)."""
        return len(self.emissivity)

    def updated(self, **kwargs):
        """A validated copy with ``kwargs`` changed (``self`` untouched); see :meth:`update`.

        Parameters
        ----------
        **kwargs
            As :meth:`update`.

        Returns
        -------
        Telescope
            The copy.
        """
        check_parameter_names("telescope", kwargs, self.mutable_parameters)
        # the mirror set is redefined only when emissivity and nelements change together
        redefine = "emissivity" in kwargs and "nelements" in kwargs
        nexp = len(np.atleast_1d(kwargs["emissivity"])) if redefine else self.nmirrors
        for key in ("temperature", "emissivity", "nelements"):
            if key in kwargs and np.ndim(kwargs[key]) > 0 and len(np.ravel(kwargs[key])) != nexp:
                raise ParameterError(f"telescope {key} needs one value per mirror group: expected length "
                                     f"{nexp}, got {len(np.ravel(kwargs[key]))}")
        params = {k: getattr(self, k) for k in self.mutable_parameters}
        if not redefine and "temperature" not in kwargs and np.ndim(self.temperature) > 0 \
                and nexp != len(self.temperature):
            raise ParameterError("telescope temperature list no longer matches the mirror groups")
        params.update(kwargs)
        return Telescope(**params)

    def update(self, **kwargs):
        """Change mutable parameters (see ``mutable_parameters``), atomically: everything is
        validated on a copy first; on error (:class:`~slicersim.errors.ParameterError`) nothing
        changes.

        Parameters
        ----------
        **kwargs
            The parameters; ``temperature``, ``emissivity`` and ``nelements`` accept one value per
            mirror group.

        Returns
        -------
        None
            Changed in place.
        """
        self._adopt(self.updated(**kwargs))

    @property
    def area(self):
        """Collecting area π/4 (D_ext² − D_int²) [m²]."""
        return np.pi / 4.0 * (self.diameter_ext**2 - self.diameter_int**2)

    @property
    def obscuration(self):
        """Central obscuration ratio ε = D_int / D_ext."""
        return self.diameter_int / self.diameter_ext

    def airy_radius(self, lbda):
        """Radius of the first Airy dark ring 1.22 λ/D [arcsec] at λ [Å].

        Parameters
        ----------
        lbda : array_like
            Wavelengths [Å].

        Returns
        -------
        numpy.ndarray
            The radius [arcsec].
        """
        return 1.22 * np.asarray(lbda, dtype=float) * 1e-10 / self.diameter_ext / ARCSEC

    @property
    def psf_sigma_ref(self):
        """Airy-equivalent Gaussian σ at 1 µm [arcsec] (R_Airy × 0.8/2.35)."""
        return float(self.airy_radius(LBDA_REF_AA)) * AIRY_SIGMA_FACTOR

    @property
    def effective_emissivity(self):
        """Σ εᵢ nᵢ of the mirrors."""
        return float(np.dot(self.emissivity, self.nelements))

    def thermal_radiance(self, lbda):
        """Mirror photon radiance ε_eff B_ph(λ, T) [ph/s/m²/sr/Å]; with one temperature per
        mirror group Σ εᵢ nᵢ B_ph(λ, Tᵢ).

        Parameters
        ----------
        lbda : array_like
            Wavelengths [Å].

        Returns
        -------
        numpy.ndarray
            The radiance [ph/s/m²/sr/Å].
        """
        if np.ndim(self.temperature) == 0:
            return self.effective_emissivity * photon_radiance(lbda, self.temperature)
        total = np.zeros_like(np.asarray(lbda, dtype=float))
        for temp, eps, n in zip(self.temperature, self.emissivity, self.nelements):
            if eps * n:
                total = total + eps * n * photon_radiance(lbda, temp)
        return total

    def show_thermal_radiance(self, lbda=None, ax=None, savefile=None):
        """Figure of the mirrors' photon radiance [ph/s/m²/sr/Å] versus λ [Å] (log scale); see
        :func:`slicersim.plotting.spectra.plot_curves`.

        Parameters
        ----------
        lbda : array_like, optional
            Wavelengths [Å] (default 4000–17000 Å).
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
        lbda = validation.array("lbda [AA]", np.linspace(4e3, 1.7e4, 500) if lbda is None else lbda, ndim=1)
        fig = plot_curves(lbda, {"mirrors": self.thermal_radiance(lbda)}, "thermal radiance [ph/s/m²/sr/Å]",
                          title=f"telescope thermal emission (T = {self.temperature} K, ε_eff = "
                                f"{self.effective_emissivity:.3g})", ax=ax, savefile=savefile, yscale="log")
        return fig

