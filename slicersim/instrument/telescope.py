"""Telescope: collecting area, diffraction scale and mirror thermal emission."""
from __future__ import annotations

import numpy as np

from slicersim.constants import AIRY_SIGMA_FACTOR, ARCSEC, LBDA_REF_AA
from slicersim.physics.thermal import photon_radiance

__all__ = ["Telescope"]


class Telescope:
    """An (annular) telescope aperture with warm mirrors.

    Parameters
    ----------
    diameter_ext, diameter_int : float  outer / central-obscuration diameter [m]
    temperature : float  mirror temperature [K]
    emissivity, nelements : sequence  per mirror group emissivity and count
    guiding_sigma : float  achromatic Gaussian jitter [arcsec]
    """

    mutable_parameters = ("diameter_ext", "diameter_int", "temperature", "emissivity",
                          "nelements", "guiding_sigma")

    def __init__(self, diameter_ext=3.0, diameter_int=0.0, temperature=293.0,
                 emissivity=(0.05, 0.02, 0.02, 0.02), nelements=(1, 1, 1, 1), guiding_sigma=0.010):
        self.diameter_ext = float(diameter_ext)
        self.diameter_int = float(diameter_int)
        self.temperature = float(temperature)
        self.emissivity = list(np.atleast_1d(emissivity).astype(float))
        self.nelements = list(np.atleast_1d(nelements).astype(int))
        self.guiding_sigma = float(guiding_sigma)
        self._check()

    def _check(self):
        if not self.diameter_ext > 0 or not (0 <= self.diameter_int < self.diameter_ext):
            raise ValueError("telescope needs diameter_ext > 0 and 0 <= diameter_int < diameter_ext")
        if len(self.emissivity) != len(self.nelements):
            raise ValueError("telescope emissivity and nelements must have the same length")
        if self.guiding_sigma < 0:
            raise ValueError("guiding_sigma must be >= 0")

    def update(self, **kwargs):
        """Change mutable parameters (see ``mutable_parameters``)."""
        for key, val in kwargs.items():
            if key not in self.mutable_parameters:
                raise ValueError(f"unknown telescope parameter {key!r}")
            setattr(self, key, val)
        self.__init__(**{k: getattr(self, k) for k in self.mutable_parameters})

    @property
    def area(self):
        """Collecting area π/4 (D_ext² − D_int²) [m²]."""
        return np.pi / 4.0 * (self.diameter_ext**2 - self.diameter_int**2)

    @property
    def obscuration(self):
        """Central obscuration ratio ε = D_int / D_ext."""
        return self.diameter_int / self.diameter_ext

    def airy_radius(self, lbda):
        """Radius of the first Airy dark ring 1.22 λ/D [arcsec] at λ [Å]."""
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
        """Mirror photon radiance ε_eff B_ph(λ, T) [ph/s/m²/sr/Å]."""
        return self.effective_emissivity * photon_radiance(lbda, self.temperature)
