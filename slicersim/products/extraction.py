"""Spectral extraction: apertures, aperture sums and optimal (PSF-weighted) extraction, units.

Apertures (slicersim 1.4.2 names): ``"core"`` (radius ``aperture_radius_insigma`` σ_ref / s,
optimal extraction by default), ``"<x>-arcsec"`` (radius x″) and ``"<x>-kpc"`` (x proper kpc
at the source redshift); a cell belongs to an aperture when its centre lies inside.  A named
radius aperture must lie entirely inside the field (else its sum silently loses light).

For a cube C [ADU] with variance V [ADU²] over the aperture cells c, per bin:

* aperture:  S = Σ_c C_c,                       Var = Σ_c V_c
* optimal:   S = Σ_c P_c C_c / V_c / Σ_c P_c² / V_c,   Var = 1 / Σ_c P_c² / V_c

with P the PSF fractions of a point source at the aperture centre (Horne 1986).  For an
isolated point source of total ADU F, C = F P: the optimal estimate is F (unbiased) and the
aperture sum is F × EE, EE = Σ_c P_c the enclosed-energy fraction.

:func:`extract_model` applies the same formulas to the noiseless model of a simulation (no cube
is built): the extracted component (point source or host light), and the variance of the whole
scene from ``Simulation.cell_variance``.  Units (:func:`unit_factors`): ``adu`` (all ramps),
``flambda`` [erg/s/cm²/Å] = ADU / (f2p QE g t_int r), ``fphoton`` [ph/s] = ADU / (QE g t_int r),
``rate`` [ADU/s] = ADU / integration time (all ramps: the slope a ramp fit measures, the time the
reduced rates and spectra use), ``framerate`` [ADU/frame] = rate × t_frame.
"""
from __future__ import annotations

import math
import re

import numpy as np

from slicersim.errors import ParameterError
from slicersim.physics.psf import aperture_cells, gaussian_psf_cells
from slicersim.physics.readout import readout_times
from slicersim.products.components import UNIFORM_TERMS, as_switched_off, uniform_terms_on
from slicersim.products.cube import host_photons_block

__all__ = ["parse_aperture", "aperture_radius", "check_aperture_in_field", "named_aperture_cells",
           "extract_aperture", "extract_optimal",
           "extract_model", "unit_factors", "UNITS", "EXTRACTION_METHODS", "ExtractionSetup", "ExtractionModel", "band_snr_table"]

EXTRACTION_METHODS = ("optimal", "aperture")
#: unit names and 1.4.2 aliases
UNITS = {"adu": "adu", "default": "adu", "flambda": "flambda", "erg/s/a/cm2": "flambda",
         "fphoton": "fphoton", "ph/s": "fphoton", "rate": "rate", "adu/s": "rate",
         "framerate": "framerate", "adu/frame": "framerate"}
_APERTURE = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*-\s*(arcsec|kpc)\s*$")


def parse_aperture(aperture):
    """("core", None) or (unit, value) with unit "arcsec" / "kpc" and value > 0."""
    if isinstance(aperture, str) and aperture.strip().lower() == "core":
        return "core", None
    m = _APERTURE.match(aperture.lower()) if isinstance(aperture, str) else None
    if m is None or not float(m.group(1)) > 0:
        raise ParameterError(f"aperture must be 'core', '<x>-arcsec' or '<x>-kpc' with x > 0 "
                             f"(e.g. '1-arcsec', '2-kpc'), got {aperture!r}")
    return m.group(2), float(m.group(1))


def aperture_radius(aperture, spatial_scale, core_radius, redshift=None, cosmology=None):
    """Radius [cells] of a named aperture and whether it is the ``core`` one; ``core_radius``
    [cells] is the point-source extraction radius; kpc apertures need the redshift."""
    kind, value = parse_aperture(aperture)
    if kind == "core":
        return float(core_radius), True
    if kind == "arcsec":
        return value / spatial_scale, False
    if redshift is None:
        raise ParameterError(f"aperture {aperture!r} is in kpc: it needs a source redshift")
    from slicersim.sources.cosmology import arcsec_per_kpc
    return value * arcsec_per_kpc(redshift, cosmology) / spatial_scale, False


def check_aperture_in_field(aperture, shape, centre, radius, spatial_scale):
    """ParameterError unless the circle of ``radius`` [cells] at ``centre`` (x, y) [cells] lies
    inside the (ny, nx) field."""
    ny, nx = shape
    x0, y0 = centre
    room = min(nx / 2 - abs(x0), ny / 2 - abs(y0))
    if radius > room * (1 + 1e-12):
        raise ParameterError(
            f"aperture {aperture!r} (radius {radius * spatial_scale:.4g}″ = {radius:.4g} cells) centred at "
            f"({x0:.4g}, {y0:.4g}) cells extends beyond the field ({nx * spatial_scale:.4g}″ × "
            f"{ny * spatial_scale:.4g}″): at most {max(room, 0) * spatial_scale:.4g}″ fits there; use a "
            "smaller aperture, move it, or use the wide field")


def named_aperture_cells(aperture, shape, centre, radius, spatial_scale):
    """Cells (iy, ix) of an aperture; ParameterError with the fix that applies when it holds no
    cell centre: a larger named aperture, or a larger ``aperture_radius_insigma`` for "core"."""
    try:
        return aperture_cells(shape, centre, radius)
    except ParameterError as exc:
        if aperture is None or parse_aperture(aperture)[0] == "core" or "no cell centre" not in str(exc):
            raise
        raise ParameterError(f"aperture {aperture!r} (radius {radius * spatial_scale:.3g}″ = {radius:.3g} cells) "
                             f"centred at ({centre[0]:.4g}, {centre[1]:.4g}) cells contains no cell centre: use a "
                             f"larger aperture (cells are {spatial_scale:g}″; a radius ≥ "
                             f"{spatial_scale / math.sqrt(2):.3g}″ always holds one)") from None


def extract_aperture(cube, variance, cells):
    """Aperture sum of (nλ, ny, nx) cubes over ``cells`` = (iy, ix): (S, Var) per bin."""
    iy, ix = cells
    return np.sum(cube[:, iy, ix], axis=1), np.sum(variance[:, iy, ix], axis=1)


def extract_optimal(cube, variance, weights, cells):
    """Optimal extraction with PSF weights ``weights`` (nλ, ncell) over ``cells``: (S, Var)."""
    iy, ix = cells
    return _optimal(cube[:, iy, ix], variance[:, iy, ix], weights)


def _optimal(values, var, weights):
    with np.errstate(divide="ignore", invalid="ignore"):
        norm = np.sum(weights**2 / var, axis=1)
        return np.sum(weights * values / var, axis=1) / norm, 1.0 / norm


def unit_factors(sim, unit, nmd=None, nramps=None):
    """Per-bin factor turning an extracted spectrum in ADU (all ramps) into ``unit``
    (variances take the factor squared); see the module docstring."""
    name = UNITS.get(unit.lower() if isinstance(unit, str) else unit)
    if name is None:
        raise ParameterError(f"unknown unit {unit!r}; known: {', '.join(UNITS)}")
    times = sim.get_times(nmd, nramps)
    if name == "adu":
        return np.ones_like(sim.lbda)
    if name in ("rate", "framerate"):
        frame = sim.detector.tframe if name == "framerate" else 1.0
        return np.full_like(sim.lbda, frame / times["integration_time"])
    ph_to_adu = sim.qe * sim.detector.gain * times["integration_time"]      # ADU per ph/s (all ramps)
    if name == "fphoton":
        return 1.0 / ph_to_adu
    return 1.0 / (ph_to_adu * sim.flambda_to_photon)


class ExtractionModel:
    """Everything the optimal extraction of one point source needs, restricted to the aperture.

    Attributes (nλ bins, nc aperture cells)
    ----------
    psf2 : (nλ, nc)  squared PSF weights P²
    pointsource_ph : (nλ, nc)  LSF[F f2p P]  [ph/s/cell]
    uniform_ph : dict name → (nλ,)  LSF of background / telescope / optics thermal [ph/s/cell]
    qe : (nλ,)  [e-/ph];  signal_rate : (nλ,)  LSF[F f2p QE] g  [ADU/s of t_int]
    """

    def __init__(self, psf2, pointsource_ph, uniform_ph, qe, signal_rate, host_ph=None):
        self.psf2, self.pointsource_ph, self.uniform_ph = psf2, pointsource_ph, uniform_ph
        self.qe, self.signal_rate, self.host_ph = qe, signal_rate, host_ph

    def cell_rate(self, off=None):
        """Electron rate per aperture cell QE · C [e-/s/cell] with the sources ``off`` removed
        (a name or names; rule: :mod:`slicersim.products.components`)."""
        off = as_switched_off(off)
        on = uniform_terms_on(off)
        uniform = np.zeros_like(self.qe)
        for name, arr in self.uniform_ph.items():
            if name in on:
                uniform = uniform + arr
        point = 0.0 if "pointsource" in off else self.pointsource_ph
        if self.host_ph is not None and "host" not in off:
            point = point + self.host_ph
        return self.qe[:, None] * (point + uniform[:, None])


class ExtractionSetup:
    """Noiseless photon rates of one aperture [ph/s/cell, after the LSF], per bin × cell.

    cells : (iy, ix); centre : (x, y) [cells]; weights : PSF fractions at the centre (nλ, nc);
    qe : (nλ, 1) [e-/ph];
    parts : rate of each scene component in the aperture cells ("pointsource", "host",
    "background", "thermal_telescope", "thermal_optics"); ``source`` names the extracted one
    ("host" with ``of_host``, else "pointsource")."""

    def __init__(self, sim, centre, radius, of_host=False, psf_profile="gaussian", aperture=None):
        spec = sim.spectrograph
        if of_host and sim.scene.host is None:
            raise ParameterError("of_host=True: this target has no host")
        self.centre, self.radius = (float(centre[0]), float(centre[1])), float(radius)
        self.cells = named_aperture_cells(aperture, spec.shape, self.centre, self.radius, spec.spatial_scale)
        sig_y, sig_x = sim.psf_sigmas
        self.weights = gaussian_psf_cells(sig_y, sig_x, spec.shape, self.centre, self.cells)
        iy, ix = self.cells
        zero = np.zeros((sim.lbda.size, iy.size))
        self.parts = {"pointsource": zero, "host": zero}
        if sim.scene.pointsource is not None:
            flux_ph = np.nan_to_num(sim.pointsource_flambda) * sim.flambda_to_photon
            psf = gaussian_psf_cells(sig_y, sig_x, spec.shape, sim.position, self.cells)
            self.parts["pointsource"] = spec.apply_lsf(flux_ph[:, None] * psf, axis=0)
        if sim.scene.host is not None:
            self.parts["host"] = host_light(sim, psf_profile)[:, iy, ix]
        self.parts["background"] = zero + spec.apply_lsf(sim.background_photons)[:, None]
        for which in ("telescope", "optics"):
            self.parts[f"thermal_{which}"] = zero + spec.apply_lsf(sim._thermal_photons(which))[:, None]
        self.source = "host" if of_host else "pointsource"
        self.qe = sim.qe[:, None]                                                   # e-/ph

    def total(self, off=None):
        """Scene rate [ph/s/cell] with the sources ``off`` (a name or names) removed: the rule of
        :mod:`slicersim.products.components` ("thermal" removes both thermal parts,
        "thermal_dark" the optics emission)."""
        off = as_switched_off(off)
        on = uniform_terms_on(off)
        out = 0.0
        for name, rate in self.parts.items():
            if (name in UNIFORM_TERMS and name not in on) or name in off:
                continue
            out = out + rate
        return out

    def band(self, i0, i1):
        """The same setup restricted to bins i0 … i1 − 1."""
        sub = ExtractionSetup.__new__(ExtractionSetup)
        sub.centre, sub.radius, sub.cells, sub.source = self.centre, self.radius, self.cells, self.source
        sub.weights, sub.qe = self.weights[i0:i1], self.qe[i0:i1]
        sub.parts = {k: v[i0:i1] for k, v in self.parts.items()}
        return sub


def host_light(sim, psf_profile="gaussian"):
    """Host photons per cell after the PSF and the LSF, (nλ, ny, nx) [ph/s/cell] (cached on
    the simulation's state)."""
    def build():
        return sim.spectrograph.apply_lsf(host_photons_block(sim, psf_profile, 0, sim.lbda.size), axis=0)
    return sim._cached(("host_light", psf_profile), build)


def extract_model(sim, setup, method, nmd=None, nramps=None, off=None):
    """(S [ADU], Var [ADU²]) per bin of the noiseless model extracted with ``setup``
    (:class:`ExtractionSetup`) by ``method`` ("aperture" or "optimal"), all ramps; ``off``
    (a name or names, valid ``switch_off`` names) removes those sources (and the signal when
    the extracted component is one of them)."""
    if method not in EXTRACTION_METHODS:
        raise ParameterError(f"method must be one of {EXTRACTION_METHODS}, got {method!r}")
    times = sim.get_times(nmd, nramps)
    s, v = _extract_rates(sim, setup, method, times["nmd"], times["integration_time_per_ramp"], off)
    return times["nramps"] * s, times["nramps"] * v


def _extract_rates(sim, setup, method, nmd, tint, off=None):
    qe, off = setup.qe, as_switched_off(off)
    var, _ = sim.cell_variance(setup.total(off) * qe, nmd, off)                   # ADU² per ramp
    component = 0.0 if setup.source in off else setup.parts[setup.source]
    signal = component * qe * sim.detector.gain * tint + np.zeros_like(var)        # ADU per ramp
    if method == "aperture":
        return np.sum(signal, axis=1), np.sum(var, axis=1)
    return _optimal(signal, var, setup.weights)


def band_snr_table(sim, setup, method, band, candidates):
    """Single-ramp band SNR per bin (mean S / √mean Var over the bins ``band`` = [i0, i1)) of
    every candidate readout (n, m, d arrays): the input of ``snr.search.exact_choice``."""
    if method not in EXTRACTION_METHODS:
        raise ParameterError(f"method must be one of {EXTRACTION_METHODS}, got {method!r}")
    i0, i1 = (int(v) for v in band)
    sub = setup.band(i0, i1)
    out = np.zeros(len(candidates[0]))
    for k, nmd in enumerate(zip(*candidates)):
        nmd = tuple(int(v) for v in nmd)
        s, v = _extract_rates(sim, sub, method, nmd, readout_times(nmd, sim.detector.tframe)
                              ["integration_time_per_ramp"])
        with np.errstate(invalid="ignore", divide="ignore"):
            mean_v = np.nanmean(v)
            if np.isfinite(mean_v) and mean_v > 0:
                out[k] = np.nanmean(s) / math.sqrt(mean_v)
    return out
