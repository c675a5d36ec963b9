"""Galaxy targets: a galaxy alone (no point source), its spectrum extracted in an aperture.

``LazuliGalaxy(0.5, model="ngc0628", aperture="2-kpc").setup_to_snr(10)`` is the exposure
needed for SNR 10 per resolution element in the galaxy light within 2 proper kpc.  The galaxy
is the host model of the point-source targets (:mod:`slicersim.sources.galaxies`) rendered at
``redshift``; the extraction follows ``slicersim.products.extraction``.
"""
from __future__ import annotations

import numpy as np

from slicersim import validation
from slicersim.errors import ETCError, ParameterError
from slicersim.physics.conventions import DEFAULT_CONVENTIONS, check_conventions
from slicersim.physics.readout import readout_times
from slicersim.products.extraction import (EXTRACTION_METHODS, aperture_radius, band_snr_table,
                                           check_aperture_in_field, extract_model, parse_aperture)
from slicersim.simulation import VARIANCE_SOURCES
from slicersim.snr.search import check_snr
from slicersim.sources.galaxies import GalaxyModel
from slicersim.sources.spectra import PointSource
from slicersim.targets.base import Target, _Lazuli, lazuli_doc
from slicersim.targets.state import check_redshift

__all__ = ["Galaxy", "LazuliGalaxy"]


class Galaxy(Target):
    """A galaxy alone observed with a configured instrument (slicersim 1.4.2 ``Galaxy``).

    Parameters
    ----------
    redshift : float
        Redshift > 0; sets the spectrum, the brightness and the angular size (fixed proper
        size).
    model : str, dict or GalaxyModel, optional
        A name ("sersic:bb-5000" default, "ngc0628", "sersic:ngc2403", "ngc4321:bb-6000"),
        a dict with ``refmodel`` or a :class:`~slicersim.GalaxyModel`.
    aperture : str, optional
        "core" (PSF-weighted optimal extraction at the centre), "<x>-arcsec" or "<x>-kpc"
        (plain sums; default "1-arcsec").
    aperture__position : str or tuple of float, optional
        "host" (the galaxy centre, default) or (x, y) [cells] from the field centre.
    method : {"default", "optimal", "aperture"}, optional
        "default" (optimal for "core", else aperture), "optimal" or "aperture".
    config, field, conventions
        As :class:`~slicersim.Target`.
    position : tuple of float, optional
        (x, y) [cells] of the galaxy centre from the field centre.
    **host_params
        Model parameters (``band`` (default "bessellr"), ``magabs`` / ``mag``, ``r_kpc``,
        ``n``, ``ellip``, ``theta``, ``rotation``, ... see :class:`~slicersim.GalaxyModel`).
    """

    own_parameters = Target.own_parameters + ("aperture", "aperture__position", "method")

    def __init__(self, redshift, model="sersic:bb-5000", aperture="1-arcsec", aperture__position="host",
                 method="default", config=None, field="default", position=(0.0, 0.0),
                 conventions=DEFAULT_CONVENTIONS, **host_params):
        self._conventions = check_conventions(conventions)
        self._redshift = check_redshift(redshift)
        if self._redshift is None:
            raise ParameterError("a galaxy needs a redshift")
        self._aperture = _check_aperture_name(aperture)
        self._aperture_position = _check_aperture_position(aperture__position)
        self._method = _check_method(method)
        self.pointsource = None
        self._position = _check_position(position)
        galaxy = GalaxyModel.from_spec(model)
        if host_params:
            galaxy = galaxy.updated(**host_params)
        self._setup(config, field, galaxy)
        self._extraction_setup()                 # the aperture is checked at once

    # ------------------------------------------------------------------ state
    @property
    def position(self):
        """(x, y) [cells] of the galaxy centre relative to the field centre."""
        return self._position

    @position.setter
    def position(self, position):
        self.update(position=position)

    def _move_to(self, position):
        self._position = position

    @property
    def model(self):
        """The galaxy's :class:`~slicersim.sources.galaxies.GalaxyModel`."""
        return self.host_model

    @property
    def aperture(self):
        return self._aperture

    @property
    def method(self):
        """Extraction method used by default: "optimal" for the "core" aperture, else "aperture"."""
        if self._method != "default":
            return self._method
        return "optimal" if self._aperture.strip().lower() == "core" else "aperture"

    def update(self, **params):
        """As :meth:`Target.update <slicersim.Target.update>`, plus ``aperture``,
        ``aperture__position`` and ``method``, atomically: the aperture is checked against the
        field in the new state (redshift, position, host, instrument) before anything changes.

        Parameters
        ----------
        **params
            The parameters to change.

        Returns
        -------
        None
            The target is changed in place.
        """
        params = dict(params)
        aperture = _check_aperture_name(params.pop("aperture")) if "aperture" in params else self._aperture
        centre = _check_aperture_position(params.pop("aperture__position")) if "aperture__position" in params \
            else self._aperture_position
        method = _check_method(params.pop("method")) if "method" in params else self._method
        plan = self._plan_update(params)
        host = plan.new_host or self.host
        host_centre = plan.host_centre
        host_centre = (host_centre[0] / plan.spectrograph.spatial_scale, host_centre[1] / plan.spectrograph.spatial_scale)
        _aperture_geometry(aperture, host_centre if centre == "host" else centre, plan.spectrograph, plan.telescope,
                           plan.aperture_radius_insigma, plan.redshift, host.cosmology)
        self._apply_update(plan)
        self._aperture, self._aperture_position, self._method = aperture, centre, method

    def _spectrum_at(self, redshift):
        return None

    # ------------------------------------------------------------------ extraction
    def _extraction_setup(self, of_host=True, aperture=None):
        """ExtractionSetup of the galaxy light in ``aperture`` (default: the target's) centred on
        ``aperture__position``, and whether the aperture is "core"."""
        from slicersim.products.extraction import ExtractionSetup
        sim = self.simulation
        aperture = self._aperture if aperture is None else _check_aperture_name(aperture)
        centre = self.host_centre() if self._aperture_position == "host" else self._aperture_position
        radius, core = _aperture_geometry(aperture, centre, sim.spectrograph, sim.telescope,
                                          sim.aperture_radius_insigma, self._redshift, self.host.cosmology)
        return ExtractionSetup(sim, centre, radius, of_host=True, aperture=aperture), core

    def _resolve_method(self, method, aperture):
        if method in (None, "default"):
            if aperture is None:
                return self.method
            return "optimal" if aperture.strip().lower() == "core" else "aperture"
        return _check_method(method)

    def _extract(self, method, of_host=True, aperture=None, nmd=None, nramps=None, off=None):
        aperture = None if aperture is None else _check_aperture_name(aperture)
        method = self._resolve_method(method, aperture)
        setup, _ = self._extraction_setup(aperture=aperture)
        signal, variance = extract_model(self.simulation, setup, method, nmd, nramps, off)
        return self.simulation.lbda.copy(), signal, variance

    def get_spectrum(self, incl_error=False, seed=None, method="default", of_host=True, aperture=None,
                     unit="adu", switch_off=None):
        """Spectrum of the galaxy light (λ [Å], signal, variance) in ``aperture`` (default: the
        target's) by ``method`` ("default": the target's), in ``unit``.  A galaxy target has no
        point source: ``of_host`` must stay True.

        Parameters
        ----------
        incl_error, seed, method, aperture, unit, switch_off
            As :meth:`Target.get_spectrum <slicersim.Target.get_spectrum>`.
        of_host : bool, optional
            Must stay True.

        Returns
        -------
        lbda, signal, variance : numpy.ndarray of shape (nλ,)
            As :meth:`Target.get_spectrum <slicersim.Target.get_spectrum>`.
        """
        if validation.flag("of_host", of_host) is False:
            raise ParameterError("a galaxy target has no point source: its spectrum is that of the galaxy "
                                 "(of_host=True)")
        if aperture is None:               # the target's own aperture and method (not Target's defaults)
            aperture = self._aperture
            method = self.method if method in (None, "default") else method
        else:
            method = self._resolve_method(method, _check_aperture_name(aperture))
        return super().get_spectrum(incl_error, seed, method, True, aperture, unit, switch_off)

    # ------------------------------------------------------------------ SNR and ETC
    # a galaxy has a redshift: bands are read in the rest frame by default (frame=None, 4000–6800 Å
    # rest), as for supernovae and 1.4.2; frame="obs" reads them in the observer frame
    def get_band_snr(self, lbda_range=None, frame=None, per_resolution=False, allow_partial=False):
        """Band SNR of the extracted galaxy spectrum: mean(signal) / √mean(variance) over the bins
        of ``lbda_range`` (per resolution element with ``per_resolution``).

        Parameters
        ----------
        lbda_range : tuple of float, optional
            (min, max) of the band [Å], read in ``frame``, as :meth:`Target.setup_to_snr
            <slicersim.Target.setup_to_snr>`.
        frame : {"rest", "obs"} or None, optional
            The frame of ``lbda_range``.
        per_resolution : bool, optional
            SNR per resolution element (else per bin).
        allow_partial : bool, optional
            Band coverage rule.

        Returns
        -------
        float
            The band SNR.
        """
        sim = self.simulation
        mask = sim.band_mask(self._band(lbda_range, frame), allow_partial=allow_partial)
        _, signal, variance = self._extract(None)
        with np.errstate(invalid="ignore", divide="ignore"):
            snr = float(np.nanmean(signal[mask]) / np.sqrt(np.nanmean(variance[mask])))
        return snr * np.sqrt(sim.spectrograph.dispersion_resolution) if per_resolution else snr

    def setup_to_snr(self, snr, lbda_range=None, frame=None, search="exact", per_resolution=True,
                     backend="auto", allow_partial=False):
        """Find and apply the readout with the shortest total exposure reaching ``snr`` in the
        extracted galaxy spectrum (per resolution element by default).  Every candidate
        (n, m, d) × ramps of ``snr.search.candidate_readouts`` is evaluated.

        Parameters
        ----------
        snr : float
            The SNR to reach.
        lbda_range : tuple of float, optional
            (min, max) of the band [Å], read in ``frame``, as :meth:`Target.setup_to_snr
            <slicersim.Target.setup_to_snr>`.
        frame : {"rest", "obs"} or None, optional
            The frame of ``lbda_range``.
        search : {"exact", "reference"}, optional
            Readout search.
        per_resolution : bool, optional
            SNR per resolution element (else per bin).
        backend : str, optional
            "auto", "opencl" or "numpy".
        allow_partial : bool, optional
            Band coverage rule.

        Returns
        -------
        dict
            The ETC result.
        """
        from slicersim.snr.search import candidate_readouts, exact_choice, limit_error, max_frames_for
        snr = check_snr(snr)
        validation.choice("search", search, ("exact",), error=ETCError, what="search (galaxy targets: 'exact' only)")
        sim, det = self.simulation, self.simulation.detector
        band = self._band(lbda_range, frame)
        idx = np.nonzero(sim.band_mask(band, allow_partial=allow_partial))[0]
        dr = sim.spectrograph.dispersion_resolution
        target = snr / np.sqrt(dr) if per_resolution else snr
        setup, _ = self._extraction_setup()
        n, m, d = candidate_readouts(det.min_group, det.max_group or 64, det.nmd[2])
        snr1 = band_snr_table(sim, setup, self.method, (idx[0], idx[-1] + 1), (n, m, d))
        choice = exact_choice(snr1[None, :], n, m, d, np.array([target]), max_frames=max_frames_for(det.tframe))
        if choice["limited"][0]:
            raise limit_error(snr, band, det.tframe)
        if choice["n"][0] == 0:
            raise ETCError(f"target SNR {snr} cannot be reached in {band} Å (no galaxy light in the aperture?)")
        nmd = (int(choice["n"][0]), int(choice["m"][0]), int(choice["d"][0]))
        nramps, reached = int(choice["nramps"][0]), float(choice["snr"][0])
        sim.update(nmd=nmd, nramps=nramps)
        result = {"nmd": nmd, "nramps": nramps, "snr": reached, "snr_target": target,
                  "snr_per_resolution": reached * np.sqrt(dr),
                  "exposure_time": nramps * readout_times(nmd, det.tframe)["exposure_time_per_ramp"],
                  "trace": None, "lbda_range_obs": band}
        self.last_etc = result
        return result

    def get_variance_contribution(self):
        """Per-source variance contribution [ADU²] per bin of the extracted galaxy spectrum:
        Var(all) − Var(source off), for the eight sources of slicersim.

        Returns
        -------
        dict
            ``variance`` (the total) and one entry per source, each of shape (nλ,) [ADU²].
        """
        _, _, total = self._extract(None)
        out = {"variance": total}
        for src in VARIANCE_SOURCES:
            out[src] = total - self._extract(None, off=src)[2]
        return out

    def get_band_variance_contribution(self, lbda_range=None, frame=None, allow_partial=False):
        """Band means of :meth:`get_variance_contribution` (absolute [ADU²] and ``frac_<src>``).

        Parameters
        ----------
        lbda_range : tuple of float, optional
            (min, max) of the band [Å], read in ``frame``, as :meth:`Target.setup_to_snr
            <slicersim.Target.setup_to_snr>`.
        frame : {"rest", "obs"} or None, optional
            The frame of ``lbda_range``.
        allow_partial : bool, optional
            Band coverage rule.

        Returns
        -------
        dict
            The band-mean contributions [ADU²] and their fractions ``frac_<src>``.
        """
        mask = self.simulation.band_mask(self._band(lbda_range, frame), allow_partial=allow_partial)
        _, signal, total = self._extract(None)
        mean_total = float(np.nanmean(total[mask]))
        out = {"signal": float(np.nanmean(signal[mask])), "variance": mean_total,
               "snr": float(np.nanmean(signal[mask]) / np.sqrt(mean_total))}
        for src, var in self.get_variance_contribution().items():
            if src != "variance":
                out[src] = float(np.nanmean(var[mask]))
                out[f"frac_{src}"] = out[src] / mean_total
        return out


class LazuliGalaxy(_Lazuli, Galaxy):
    __doc__ = lazuli_doc(Galaxy, "A galaxy alone observed with the Lazuli IFS (slicersim 1.4.2 ``LazuliGalaxy``).")


def _aperture_geometry(aperture, centre, spec, telescope, aperture_insigma, redshift, cosmology):
    """(radius [cells], is_core) of ``aperture`` centred at ``centre`` [cells] for an instrument
    state (spectrograph, telescope, core radius in σ); ParameterError unless a named aperture
    lies inside the field and holds a cell centre."""
    from slicersim.products.extraction import named_aperture_cells
    core_radius = aperture_insigma * telescope.psf_sigma_ref / spec.spatial_scale
    radius, core = aperture_radius(aperture, spec.spatial_scale, core_radius, redshift, cosmology)
    if not core:
        check_aperture_in_field(aperture, spec.shape, centre, radius, spec.spatial_scale)
        named_aperture_cells(aperture, spec.shape, centre, radius, spec.spatial_scale)
    return radius, core


def _check_aperture_name(aperture):
    parse_aperture(aperture)
    return aperture


def _check_aperture_position(position):
    if isinstance(position, str):
        return validation.choice("aperture__position", position, ("host",),
                                 what="aperture__position ('host' or (x, y) [cells])")
    return _check_position(position)


def _check_position(position):
    return PointSource([1.0, 2.0], [0.0, 0.0], position=position).position


def _check_method(method):
    return validation.choice("method", method, ("default", *EXTRACTION_METHODS))
