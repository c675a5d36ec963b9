"""The exposure-time calculation and the products of a target, as a mixin of
:class:`~slicersim.targets.base.Target`: ``setup_to_snr`` (the single-target ETC), the band SNR
and variance contributions in the target's frame, the extracted spectrum (optimal or aperture,
of the point source or of its host), the cubes and the readout times.

:class:`ObservationMixin` reads the target through ``simulation``, ``redshift``, ``position``,
``host_centre``, ``_host`` and ``_redshift`` (:class:`~slicersim.targets.base.Target` has them)
and changes it only through ``change_detector``; the detector image and the raw ramps are the
other mixin, :class:`~slicersim.targets.detector.DetectorProducts`.
"""
from __future__ import annotations

from slicersim import validation
from slicersim.errors import ETCError, ParameterError
from slicersim.products.components import check_switch_off
from slicersim.products.extraction import (EXTRACTION_METHODS, ExtractionSetup, aperture_radius,
                                           check_aperture_in_field, extract_model, unit_factors)
from slicersim.simulation import resolve_frame

__all__ = ["ObservationMixin", "DEFAULT_BAND", "SPECTRUM_NOISE_STREAM"]

#: band [Å] of the ETC and band SNRs when none is given (read in the target's ``frame``)
DEFAULT_BAND = (4000.0, 6800.0)
#: Philox stream of the noise drawn by :meth:`Target.get_spectrum` (cube noise uses stream 0)
SPECTRUM_NOISE_STREAM = 0x53504543


class ObservationMixin:
    """ETC, band SNR, spectra and cubes of a :class:`~slicersim.targets.base.Target` (a base
    class of it, whose page documents these methods)."""

    # ------------------------------------------------------------------ ETC
    def _band(self, lbda_range, frame):
        """(lo, hi) [Å, observer frame] of ``lbda_range`` (default 4000–6800 Å) read in ``frame``
        (None: "rest" when the target has a redshift, else "obs")."""
        if lbda_range is None:
            lbda_range = DEFAULT_BAND
        if resolve_frame(frame, self.redshift) == "rest" and self.redshift is None:
            shown = validation.shown("frame")          # --frame within the CLI
            rest, obs = ("frame='rest'", "frame='obs'") if shown == "frame" else (f"{shown} rest", f"{shown} obs")
            raise ETCError(f"{rest} needs a target redshift and this target has none; give the band in the "
                           f"observer frame ({obs})")
        return self.simulation.band_range(lbda_range, resolve_frame(frame, self.redshift))

    def setup_to_snr(self, snr, lbda_range=None, frame=None, search="exact", per_resolution=True,
                     backend="auto", allow_partial=False):
        """Find and apply the readout reaching ``snr`` (per resolution element by default)
        in a band.

        The band must lie inside the instrument grid and the source spectrum, else
        SpectrumError naming the covered fraction; ``allow_partial=True`` solves on the
        covered part with a BandCoverageWarning (``slicersim.snr.bands``).

        Parameters
        ----------
        snr : float
            The SNR to reach.
        lbda_range : tuple of float, optional
            (min, max) of the band [Å] (default 4000–6800 Å), read in ``frame``.
        frame : {"rest", "obs"} or None, optional
            "rest", "obs", or None: "rest" when the target has a redshift, else "obs".
        search : {"exact", "reference"}, optional
            The readout search.
        per_resolution : bool, optional
            SNR per resolution element (else per bin).
        backend : str, optional
            "auto", "opencl" or "numpy".
        allow_partial : bool, optional
            Solve on the covered part of the band.

        Returns
        -------
        dict
            The ETC result: ``nmd``, ``nramps``, ``snr`` (reached, per bin), ``snr_target``,
            ``snr_per_resolution``, ``exposure_time`` [s], ``trace`` and ``lbda_range_obs`` [Å];
            also kept as ``last_etc``.
        """
        band = self._band(lbda_range, frame)
        result = self.simulation.fetch_snr(snr, band, per_resolution=per_resolution, search=search,
                                           backend=backend, allow_partial=allow_partial, frame="obs")
        self.simulation.update(nmd=result["nmd"], nramps=result["nramps"])
        result["lbda_range_obs"] = band
        self.last_etc = result
        return result

    def get_readout_config(self):
        return {"nmd": tuple(self.simulation.detector.nmd), "nramps": self.simulation.nramps}

    def get_exposure_time(self):
        """Total exposure time of all ramps [s].

        Returns
        -------
        float
            The exposure time [s].
        """
        return self.simulation.get_times()["exposure_time"]

    def get_exptime(self):
        """Total exposure time of all ramps [s] (paper name of :meth:`get_exposure_time`).

        Returns
        -------
        float
            The exposure time [s].
        """
        return self.get_exposure_time()

    def get_times(self):
        return self.simulation.get_times()

    def get_data_volume(self):
        return self.simulation.get_data_volume()

    def get_band_snr(self, lbda_range=None, frame=None, per_resolution=False, allow_partial=False):
        """Band SNR (per bin; per resolution element when ``per_resolution``).

        Parameters
        ----------
        lbda_range : tuple of float, optional
            (min, max) of the band [Å] (default 4000–6800 Å), read in ``frame``.
        frame : {"rest", "obs"} or None, optional
            "rest", "obs", or None: "rest" when the target has a redshift, else "obs".
        per_resolution : bool, optional
            SNR per resolution element (else per bin).
        allow_partial : bool, optional
            Band coverage rule, as :meth:`setup_to_snr`.

        Returns
        -------
        float
            The band SNR.
        """
        return self.simulation.get_band_snr(self._band(lbda_range, frame), per_resolution=per_resolution,
                                            allow_partial=allow_partial, frame="obs")

    def get_spectrum(self, incl_error=False, seed=None, method="default", of_host=False, aperture=None,
                     unit="adu", switch_off=None):
        """(λ [Å], signal, variance) extracted from the noiseless model, all ramps.

        Parameters
        ----------
        incl_error : bool, optional
            Add a Gaussian noise draw (in ADU, before the unit conversion):
            signal + √variance · z with z the counter-based Philox / Box–Muller
            normal of ``slicersim.rng`` keyed by (seed, bin index,
            stream ``SPECTRUM_NOISE_STREAM``) — the same generator and arithmetic as the
            noisy cubes (``slicersim.backends.noise.noisy_cube``): the same seed gives the same
            draw on every machine and backend; bins with zero variance keep the signal,
            non-finite variance gives NaN.
        seed : int, optional
            Integer in [0, 2⁶⁴) of that draw; None draws a fresh seed
            (:func:`slicersim.validation.new_seed`), recorded in ``last_spectrum_seed``.
        method : {"default", "optimal", "aperture"}, optional
            "optimal" (PSF-weighted; the point source's true LSF-convolved spectrum and
            the optimal variance of :meth:`Simulation.get_spectrum <slicersim.Simulation.get_spectrum>`),
            "aperture" (plain sum over the aperture cells, no aperture correction) or "default"
            (slicersim 1.4.2's rule: optimal for the "core" aperture, a plain sum otherwise).
        of_host : bool, optional
            Extract the host light instead, in an aperture centred on the host.
        aperture : str, optional
            "core" (the point-source extraction radius), "<x>-arcsec" or "<x>-kpc"
            (``slicersim.products.extraction``); None: "core", or "1-arcsec" (1.4.2's) for
            the host (``of_host``) and for ``method="aperture"``.
        unit : str, optional
            "adu" (default), "flambda" [erg/s/cm²/Å], "fphoton" [ph/s], "rate" [ADU/s of
            integration time: the slope, as the reduced rates and spectra] or "framerate"
            [ADU/frame] (1.4.2 names accepted: ``slicersim.products.extraction.UNITS``).
        switch_off : str or sequence of str, optional
            Components left out of the signal and variance (a name or names:
            ``slicersim.products.components.check_switch_off``, the rule of cubes and spectra;
            switching off the extracted component gives zero signal).

        Returns
        -------
        lbda : numpy.ndarray of shape (nλ,)
            Wavelengths [Å].
        signal : numpy.ndarray of shape (nλ,)
            The signal [``unit``].
        variance : numpy.ndarray of shape (nλ,)
            Its variance [(``unit``)²].
        """
        seed = validation.seed(seed)
        incl_error = validation.flag("incl_error", incl_error)
        of_host = validation.flag("of_host", of_host)
        off = check_switch_off(switch_off)
        factor = unit_factors(self.simulation, unit)                  # validates the unit first
        method, aperture = _default_extraction(method, of_host, aperture)
        lbda, signal, variance = self._extract(method, of_host, aperture, off=off)
        if incl_error:
            from slicersim.backends.noise import noisy_cube
            seed = validation.new_seed() if seed is None else seed
            self.last_spectrum_seed = seed          # recorded: get_spectrum(seed=...) repeats the draw
            signal = noisy_cube(signal, variance, seed, backend="numpy", stream=SPECTRUM_NOISE_STREAM)
        return lbda, signal * factor, variance * factor**2

    def _extraction_setup(self, of_host=False, aperture=None):
        """(:class:`~slicersim.products.extraction.ExtractionSetup`, optimal-by-default) of an
        aperture centred on the point source, or on the host with ``of_host``."""
        sim = self.simulation
        if of_host and self._host is None:
            raise ParameterError("of_host=True: this target has no host")
        centre = self.host_centre() if of_host else self.position
        aperture = "core" if aperture is None else aperture
        cosmo = getattr(self._host, "cosmology", None)
        radius, core = aperture_radius(aperture, sim.spectrograph.spatial_scale, sim.aperture_radius,
                                       self._redshift, cosmo)
        if not core:
            check_aperture_in_field(aperture, sim.spectrograph.shape, centre, radius,
                                    sim.spectrograph.spatial_scale)
        return ExtractionSetup(sim, centre, radius, of_host=of_host, aperture=aperture), core

    def _extract(self, method, of_host=False, aperture=None, off=None):
        if method not in EXTRACTION_METHODS:
            raise ParameterError(f"method must be one of {EXTRACTION_METHODS}, got {method!r}")
        if method == "optimal" and not of_host and aperture in (None, "core"):
            return self.simulation.get_spectrum(switch_off=off)
        setup, _ = self._extraction_setup(of_host, aperture)
        signal, variance = extract_model(self.simulation, setup, method, off=off)
        return self.simulation.lbda.copy(), signal, variance

    def get_cube(self, seed=None, switch_off=None, psf_profile="gaussian", **options):
        """Cube [ADU] of the scene (noisy with ``seed``).

        Parameters
        ----------
        seed : int, optional
            Integer in [0, 2⁶⁴) of the noisy realisation; None: noiseless.
        switch_off : str or sequence of str, optional
            Components left out (``slicersim.products.components.check_switch_off``).
        psf_profile : {"gaussian", "airy"}, optional
            The PSF.
        **options
            The other options (``nmd``, ``nramps``, ``max_bytes``, ``progress``, ``backend``,
            ``dtype``, ...) as :meth:`Simulation.get_cube <slicersim.Simulation.get_cube>`.

        Returns
        -------
        CubeTuple
            (signal, variance) of shape (nλ, ny, nx) [ADU, ADU²], then the noisy cube with
            ``seed``, as :meth:`Simulation.get_cube <slicersim.Simulation.get_cube>`.
        """
        return self.simulation.get_cube(seed=seed, switch_off=switch_off, psf_profile=psf_profile, **options)

    def get_scene_cubes(self, unit="adu", switch_off=None, **kwargs):
        """Noise-free cube of each scene component.

        Parameters
        ----------
        unit : str, optional
            As :meth:`Simulation.get_scene_cubes <slicersim.Simulation.get_scene_cubes>`.
        switch_off : str or sequence of str, optional
            Components left out.
        **kwargs
            The other options of
            :meth:`Simulation.get_scene_cubes <slicersim.Simulation.get_scene_cubes>`.

        Returns
        -------
        SceneCubes or numpy.ndarray
            As :meth:`Simulation.get_scene_cubes <slicersim.Simulation.get_scene_cubes>`.
        """
        return self.simulation.get_scene_cubes(unit=unit, switch_off=switch_off, **kwargs)

    def get_variance_contribution(self):
        return self.simulation.get_variance_contribution()

    def get_band_variance_contribution(self, lbda_range=None, frame=None, allow_partial=False):
        """Band-mean variance contributions.

        Parameters
        ----------
        lbda_range : tuple of float, optional
            (min, max) of the band [Å] (default 4000–6800 Å), read in ``frame``.
        frame : {"rest", "obs"} or None, optional
            "rest", "obs", or None: "rest" when the target has a redshift, else "obs".
        allow_partial : bool, optional
            Band coverage rule, as :meth:`setup_to_snr`.

        Returns
        -------
        dict
            As :meth:`Simulation.get_band_variance_contribution
            <slicersim.Simulation.get_band_variance_contribution>`.
        """
        return self.simulation.get_band_variance_contribution(self._band(lbda_range, frame),
                                                              allow_partial=allow_partial, frame="obs")


def _default_extraction(method, of_host, aperture):
    """(method, aperture) with slicersim 1.4.2's defaults: "1-arcsec" for the host and for plain
    sums, optimal extraction only for the "core" aperture."""
    if aperture is None and (of_host or method == "aperture"):
        aperture = "1-arcsec"
    if method in (None, "default"):
        core = aperture is None or (isinstance(aperture, str) and aperture.strip().lower() == "core")
        method = "optimal" if core else "aperture"
    return method, aperture
