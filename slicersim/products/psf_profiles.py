"""PSF profiles of a simulation, in a registry: ``get_psf_profile("airy")``.

A profile turns a simulation (telescope, spectrograph, position, conventions)
into PSF fractions per cell: over a block of wavelengths (cubes), over a list of
cells (the extraction aperture), or in the compact form the fused cube kernel
takes.  Airy blocks are cached across simulations (:mod:`slicersim.backends.psf_cache`, keyed
by the content of every input; read-only results).  Built in: ``"gaussian"`` (Airy-equivalent Gaussian integrated over the
cells with erf; the slicersim 1.0 default, alias ``"default"``) and ``"airy"``
(annular-pupil diffraction, exact sub-cell quadrature, jitter and slice blur).
"""
from __future__ import annotations

import numpy as np

from slicersim.backends.cube import GaussianPSF
from slicersim.backends.psf import auto_oversampling
from slicersim.backends.psf_cache import psf_cells, psf_cube, psf_cube_device
from slicersim.errors import ParameterError
from slicersim.physics.psf import gaussian_psf_cells, gaussian_psf_fractions

__all__ = ["PSFProfile", "GaussianProfile", "AiryProfile", "PSF_PROFILES", "get_psf_profile",
           "register_psf_profile"]


class PSFProfile:
    """Interface of a PSF profile (subclass and :func:`register_psf_profile` to add one)."""

    name = ""

    def block(self, sim, lo, hi, shape, position, backend="auto", options=None, on_device=False,
              precision="auto"):
        """P[λ, y, x] for bins lo … hi − 1 on a (ny, nx) field, source at ``position`` [cells]
        (``precision``: of the kernels, :mod:`slicersim.backends.precision`)."""
        raise NotImplementedError

    def fused(self, sim, lo, hi, backend="auto", options=None, precision="auto"):
        """The PSF of bins lo … hi − 1 in the form the fused cube kernel takes."""
        return self.block(sim, lo, hi, sim.spectrograph.shape, sim.position, backend, options, on_device=True,
                          precision=precision)

    def cells(self, sim, cells, backend="auto"):
        """P restricted to ``cells`` = (iy, ix) of the field: (nλ, ncell)."""
        raise NotImplementedError

    def kernel_shape(self, sim):
        """Odd (ky, kx) of the kernels convolving extended sources (the whole field by default)."""
        ny, nx = sim.spectrograph.shape
        return 2 * (ny // 2) + 1, 2 * (nx // 2) + 1

    def __repr__(self):
        return f"<PSF profile {self.name!r}>"


class GaussianProfile(PSFProfile):
    """Airy-equivalent Gaussian ⊗ jitter ⊗ slice blur, integrated over the cells (erf)."""

    name = "gaussian"

    def block(self, sim, lo, hi, shape, position, backend="auto", options=None, on_device=False,
              precision="auto"):
        sig_y, sig_x = sim.psf_sigmas
        return gaussian_psf_fractions(sig_y[lo:hi], sig_x[lo:hi], shape, position)

    def fused(self, sim, lo, hi, backend="auto", options=None, precision="auto"):
        sig_y, sig_x = sim.psf_sigmas
        return GaussianPSF(sig_y[lo:hi], sig_x[lo:hi], sim.position, sim.spectrograph.shape)

    def cells(self, sim, cells, backend="auto"):
        sig_y, sig_x = sim.psf_sigmas
        return gaussian_psf_cells(sig_y, sig_x, sim.spectrograph.shape, sim.position, cells)

    def kernel_shape(self, sim):
        """±⌈8σ_max⌉ + 1 cells (dropped tail < 1e-15), at most the field."""
        ny, nx = sim.spectrograph.shape
        sig_y, sig_x = sim.psf_sigmas
        hy = min(ny // 2, int(np.ceil(8.0 * np.max(sig_y))) + 1)
        hx = min(nx // 2, int(np.ceil(8.0 * np.max(sig_x))) + 1)
        return 2 * hy + 1, 2 * hx + 1


class AiryProfile(PSFProfile):
    """Annular-pupil Airy pattern (D, ε), exact sub-cell quadrature, jitter and slice blur."""

    name = "airy"

    @staticmethod
    def _common(sim):
        tel, spec = sim.telescope, sim.spectrograph
        return dict(spatial_scale=spec.spatial_scale, guiding_sigma=tel.guiding_sigma,
                    instrumental_sigma=sim.instrumental_sigma, diameter=tel.diameter_ext)

    def block(self, sim, lo, hi, shape, position, backend="auto", options=None, on_device=False,
              precision="auto"):
        tel, common = sim.telescope, self._common(sim)
        # one oversampling for the whole grid (set by its bluest, most undersampled bin), so every
        # wavelength block is computed alike; error < 1e-4 of the peak (benchmarks/psf_speed_accuracy.py)
        oversampling = 3 if (options or {}).get("grid") == "reference" else auto_oversampling(sim.lbda, **common)
        kwargs = dict(sigma_ref_arcsec=tel.psf_sigma_ref, obscuration=tel.obscuration,
                      oversampling=oversampling, backend=backend, **common)
        # slicersim 1.0's grid is NumPy-only, in double: the cube kernels may still run in single
        kwargs["precision"] = "auto" if (options or {}).get("grid") == "reference" else precision
        kwargs.update(options or {})
        return (psf_cube_device if on_device else psf_cube)(sim.lbda[lo:hi], shape, position, profile="airy",
                                                           **kwargs)

    def cells(self, sim, cells, backend="auto"):
        tel, common = sim.telescope, self._common(sim)
        return psf_cells(sim.lbda, sim.spectrograph.shape, sim.position, cells=cells, profile="airy",
                         sigma_ref_arcsec=tel.psf_sigma_ref, obscuration=tel.obscuration,
                         oversampling=auto_oversampling(sim.lbda, **common), backend=backend, **common)


PSF_PROFILES = {}
_ALIASES = {"default": "gaussian"}


def register_psf_profile(profile):
    """Add a :class:`PSFProfile` instance to the registry under ``profile.name``."""
    if not isinstance(profile, PSFProfile) or not profile.name:
        raise ParameterError("register_psf_profile needs a PSFProfile instance with a name")
    PSF_PROFILES[profile.name] = profile
    return profile


def get_psf_profile(name):
    """The registered profile ``name`` (a PSFProfile passes through); the error lists the registry."""
    if isinstance(name, PSFProfile):
        return name
    key = _ALIASES.get(name, name)
    if key not in PSF_PROFILES:
        raise ParameterError(f"unknown psf_profile {name!r}: registered profiles are "
                             f"{', '.join(map(repr, PSF_PROFILES))} (and 'default' = 'gaussian')")
    return PSF_PROFILES[key]


register_psf_profile(GaussianProfile())
register_psf_profile(AiryProfile())
