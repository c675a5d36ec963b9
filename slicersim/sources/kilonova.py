"""Kilonova spectra from user-provided POSSIS model files (Bulla 2019, MNRAS 489, 5037; Bulla 2023).

POSSIS models are spectral time series on a grid of viewing angles.  None ships with
slicersim (slicersim 1.4.2 downloads two of them); public grids are at
https://github.com/mbulla/kilonova_models.  Two layouts are read:

* text (POSSIS output): line 1 the number of viewing angles N_obs (equally spaced in
  cos θ from 0, equator, to 1, pole), line 2 the number of wavelengths N_λ, line 3
  ``N_t t_start t_end`` [days], then N_obs blocks of N_λ rows ``λ [Å]  F(t_1) … F(t_Nt)``;
* FITS: extensions ``MODEL`` (N_cos, N_t, N_λ), ``PHASE`` [days], ``LBDA`` [Å], ``COSTHETA``.

:class:`AngularTimeSeriesSource` wraps a model as a ``sncosmo.Source`` (parameters
``amplitude`` and ``theta`` [deg]), so the observer-frame spectrum and its normalisation go
through :func:`slicersim.sources.spectra.sncosmo_spectrum` like every sncosmo source.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import sncosmo
from scipy.interpolate import RegularGridInterpolator

from slicersim import validation
from slicersim.errors import SpectrumError

__all__ = ["MODEL_URL", "read_possis", "AngularTimeSeriesSource", "kilonova_source"]

#: public POSSIS model grids
MODEL_URL = "https://github.com/mbulla/kilonova_models"
#: relative floor of the normalised model flux (log interpolation needs F > 0)
FLUX_FLOOR = 1e-10


def read_possis(path):
    """(phase [days], λ [Å], cos θ, F (N_t, N_λ, N_cos) [arbitrary units]) of a POSSIS file
    (``.txt``/``.dat`` text or ``.fits``/``.fits.gz``).  SpectrumError naming the file when it
    is missing or not in one of the two layouts."""
    path = Path(path)
    if os.path.lexists(path):
        validation.regular_file("kilonova model file", path, error=SpectrumError)   # a FIFO, device, directory
    else:
        raise SpectrumError(f"kilonova model file {str(path)!r} not found: kilonova models (POSSIS, Bulla 2019/2023) "
                            f"are not shipped with slicersim; download one (e.g. from {MODEL_URL}) and pass "
                            "its path (.txt POSSIS output or .fits with MODEL/PHASE/LBDA/COSTHETA)")
    try:
        if path.name.lower().endswith((".fits", ".fits.gz", ".fit")):
            return _read_possis_fits(path)
        return _read_possis_text(path)
    except SpectrumError:
        raise
    except (OSError, ValueError, KeyError, IndexError) as exc:
        raise SpectrumError(f"kilonova model file {str(path)!r} is not a POSSIS model "
                            f"({type(exc).__name__}: {exc})") from exc


def _read_possis_fits(path):
    from astropy.io import fits
    with fits.open(path) as hdus:
        model = np.array(hdus["MODEL"].data, dtype=float)
        phase, lbda = np.array(hdus["PHASE"].data, dtype=float), np.array(hdus["LBDA"].data, dtype=float)
        cos_theta = np.array(hdus["COSTHETA"].data, dtype=float)
    if model.shape != (cos_theta.size, phase.size, lbda.size):
        raise SpectrumError(f"{path}: MODEL has shape {model.shape}, expected (COSTHETA, PHASE, LBDA) = "
                            f"{(cos_theta.size, phase.size, lbda.size)}")
    return phase, lbda, cos_theta, np.moveaxis(model, 0, -1)


def _read_possis_text(path):
    with open(path, encoding="utf-8") as fh:
        nobs, nwave = int(fh.readline()), int(fh.readline())
        ntime, t_start, t_end = fh.readline().split()[:3]
        data = np.loadtxt(fh, ndmin=2)
    ntime = int(ntime)
    if data.shape != (nobs * nwave, 1 + ntime):
        raise SpectrumError(f"{path}: {data.shape[0]} rows × {data.shape[1]} columns, the header announces "
                            f"{nobs} × {nwave} rows of 1 + {ntime} columns (POSSIS text layout)")
    lbda = data[:nwave, 0]
    flux = data[:, 1:].reshape(nobs, nwave, ntime).transpose(2, 1, 0)
    return np.linspace(float(t_start), float(t_end), ntime), lbda, np.linspace(0.0, 1.0, nobs), flux


def _increasing(name, values, minimum=2):
    values = np.asarray(values, dtype=float)
    if values.ndim != 1 or values.size < minimum or not np.all(np.isfinite(values)) \
            or np.any(np.diff(values) <= 0):
        raise SpectrumError(f"kilonova model: {name} must be ≥ {minimum} finite, strictly increasing values")
    return values


class AngularTimeSeriesSource(sncosmo.Source):
    """Spectral time series on a viewing-angle grid: F(t, λ; θ) = A exp(L(t, λ, |cos θ|)).

    L is log M interpolated linearly in cos θ between the grid angles, then bilinearly in
    (t, λ); t outside the grid takes the flux of the nearest grid phase.  M is the model
    normalised to a maximum of 1, negative values set to 0 and floored at
    :data:`FLUX_FLOOR`.  Parameters: ``amplitude`` A and ``theta`` [deg] (0 pole-on, 90
    edge-on; models are symmetric about the equator, so θ and 180° − θ agree).
    """

    _param_names = ["amplitude", "theta"]
    param_names_latex = ["A", r"\theta"]

    def __init__(self, phase, wave, cos_theta, flux, name=None, version=None):
        self._phase, self._wave = _increasing("phase", phase), _increasing("wavelength", wave)
        self._cos_theta = _increasing("cos θ", cos_theta, minimum=1)
        if self._cos_theta[0] < 0 or self._cos_theta[-1] > 1:
            raise SpectrumError("kilonova model: cos θ must lie in [0, 1]")
        flux = np.array(flux, dtype=float)
        if flux.shape != (self._phase.size, self._wave.size, self._cos_theta.size) or not np.all(np.isfinite(flux)):
            raise SpectrumError(f"kilonova model: flux must be finite with shape (phase, wavelength, cos θ) = "
                                f"{(self._phase.size, self._wave.size, self._cos_theta.size)}, got {flux.shape}")
        peak = flux.max()
        if not peak > 0:
            raise SpectrumError("kilonova model: the flux is nowhere positive")
        self._log_flux = np.log(np.maximum(np.clip(flux, 0.0, None) / peak, FLUX_FLOOR))
        self.name, self.version = name, version
        self._parameters = np.array([1.0, 0.0])
        self._interp_theta, self._interp = None, None

    def _log_interpolator(self):
        """(t, λ) interpolator of log M at the current θ (rebuilt when θ changes)."""
        theta = float(self._parameters[1])
        if self._interp_theta != theta:
            grid = self._cos_theta
            cos = np.clip(abs(np.cos(np.radians(theta))), grid[0], grid[-1])
            if grid.size == 1:
                log_flux = self._log_flux[..., 0]
            else:
                i = int(np.clip(np.searchsorted(grid, cos, side="right") - 1, 0, grid.size - 2))
                w = (cos - grid[i]) / (grid[i + 1] - grid[i])
                log_flux = (1 - w) * self._log_flux[..., i] + w * self._log_flux[..., i + 1]
            self._interp = RegularGridInterpolator((self._phase, self._wave), log_flux)
            self._interp_theta = theta
        return self._interp

    def _flux(self, phase, wave):
        phase = np.clip(np.atleast_1d(np.asarray(phase, dtype=float)), self._phase[0], self._phase[-1])
        wave = np.clip(np.atleast_1d(np.asarray(wave, dtype=float)), self._wave[0], self._wave[-1])
        grid_t, grid_l = np.meshgrid(phase, wave, indexing="ij")
        log_flux = self._log_interpolator()(np.stack([grid_t, grid_l], axis=-1))
        return self._parameters[0] * np.exp(log_flux)


def kilonova_source(path):
    """:class:`AngularTimeSeriesSource` of a POSSIS file (see :func:`read_possis`)."""
    phase, lbda, cos_theta, flux = read_possis(path)
    return AngularTimeSeriesSource(phase, lbda, cos_theta, flux, name=Path(path).name)
