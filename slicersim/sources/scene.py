"""The astrophysical scene: point source, uniform background and host.

Spectra are flux densities F(λ) [erg/s/cm²/Å] (per arcsec² for backgrounds),
evaluated on the spectrograph's wavelength grid.
"""
from __future__ import annotations

import numpy as np

from slicersim import validation
from slicersim.errors import ParameterError
from slicersim.versioning import Versioned

__all__ = ["Background", "Scene", "zodiacal_light"]

def zodiacal_light(lbda, scale=2.0):
    """Zodiacal light, Aldering (2001) 5800 K black-body fit [erg/s/cm²/Å/arcsec²]."""
    lbda = np.asarray(lbda, dtype=float)
    return scale * 1e-17 * (lbda / 1e4) ** -4.64 / np.expm1(24806.498 / lbda)


class Background(Versioned):
    """Spatially uniform background (zodiacal light by default) [erg/s/cm²/Å/arcsec²].

    Parameters
    ----------
    model : {"zodi", "Aldering01.BB5800"} or callable, optional
        The surface brightness: the zodiacal light (Aldering 2001, 5800 K black-body fit;
        both names select it) or a function of the wavelength [Å] returning
        F_λ [erg/s/cm²/Å/arcsec²].
    scale : float, optional
        Factor (≥ 0) applied to the model.
    name : str, optional
        Label of the background in reports and figures.
    """

    def __init__(self, model="zodi", scale=2.0, name="zodi"):
        if not callable(model):
            validation.choice("model", model, ("zodi", "Aldering01.BB5800"), what="background model")
        self.model, self.name = model, name
        self.scale = validation.number("background scale", scale, low=0.0)

    def flambda(self, lbda):
        if callable(self.model):
            return self.scale * np.asarray(self.model(lbda), dtype=float)
        return zodiacal_light(lbda, self.scale)


class Scene(Versioned):
    """Container of the point source, background and host (any may be None).

    Assigning any of them (``scene.host = Host(...)``) takes effect at once: the
    Simulation's cache is keyed on the versions of the scene and of its parts.

    Parameters
    ----------
    pointsource : PointSource, optional
        The point source (spectrum at a position).
    background : Background, optional
        The spatially uniform background.
    host : Host or CubeSource, optional
        The extended source: anything with ``flux_cube(lbda, shape, spatial_scale)``
        (:class:`~slicersim.errors.ParameterError` otherwise).
    """

    def __init__(self, pointsource=None, background=None, host=None):
        self.pointsource, self.background, self.host = pointsource, background, host

    @property
    def host(self):
        return self._host

    @host.setter
    def host(self, host):
        if host is not None and not callable(getattr(host, "flux_cube", None)):
            raise ParameterError("host must provide flux_cube(lbda, shape, spatial_scale) "
                            "(slicersim.Host or slicersim.CubeSource)")
        self._host = host

    def _state_parts(self):
        return (self.pointsource, self.background, self._host)
