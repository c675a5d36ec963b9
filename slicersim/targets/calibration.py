"""Calibration exposures: continuum (QTH) flats and Fabry–Perot exposures as cubes, detector
images and raw ramps.

A flat's scene has no point source and no host: the lamp (:mod:`slicersim.sources.lamps`)
is a spatially uniform surface brightness S(λ) [erg/s/cm²/Å/arcsec²] filling the field, so it
enters the simulation as a uniform background (each bin gets the lamp's bin average), and with
the default (ideal) instrument the cube is spatially uniform.  Flat-field structure is an
option (:class:`FlatFieldStructure`, off by default; :mod:`slicersim.targets.flatfield`):

* slice-to-slice throughput: each slice s transmits t_s = exp(σ_s z_s − σ_s²/2) of the lamp
  light (the instrument's own thermal light is not scaled), z_s ~ N(0, 1);
* pixel response non-uniformity (PRNU): each detector pixel p multiplies its photo-electrons
  by r_p = exp(σ_p z_p − σ_p²/2) (mean 1; dark current is not affected).  In the cube a cell
  (``pixels_per_cell`` pixels, 2 for the slicer) gets the mean of its pixels' responses,
  drawn per voxel; in the detector image every pixel gets its own.  The two are independent
  draws of the same statistics (the cube is not the inverse projection of the image).

Draws are counter-based Philox keyed by (``seed``, slice id or voxel / pixel index, stream
:data:`FLAT_SLICE_STREAM` / :data:`FLAT_PIXEL_STREAM` + k): reproducible on any backend and
chunking, and independent of the noise seed.

API as slicersim 1.4.2 (``Lazuli3DFlat.from_qth``, ``from_febryperot``, ``Flat3DCalibration``):
``from_fabryperot`` takes an Airy etalon (``fsr`` [cm⁻¹] or ``optical_thickness`` [µm],
``finesse``, ``peak_transmission``) or 1.4.2's tabulated transmission (``fp_throughput``: a
file or a callable); ``from_febryperot`` is its 1.4.2 spelling.  Differences from 1.4.2: the
default band is ``"bessellr"`` (1.4.2's ``"sdssr"`` needs a download), ``temperature`` is
honoured by ``from_febryperot`` (1.4.2 always uses 3000 K), lamp lines are integrated over
each bin (1.4.2 samples them at the bin centres), and ramps exist.
"""
from __future__ import annotations

import numpy as np

from slicersim.assembly import check_field, default_mapper
from slicersim import validation
from slicersim.backends.precision import resolve_precision
from slicersim.errors import ParameterError
from slicersim.instrument.names import check_parameter_names
from slicersim.physics.conventions import DEFAULT_CONVENTIONS, check_conventions
from slicersim.sources.lamps import (DEFAULT_LAMP_BAND, QTH_TEMPERATURE, BlackBodyContinuum, CalibrationLamp,
                                     FabryPerotEtalon, LampIllumination, TabulatedContinuum, as_etalon)
from slicersim.targets.base import Target, build_simulation, config_default_field, lazuli_doc
from slicersim.targets.flatfield import (FLAT_PIXEL_STREAM, FLAT_SLICE_STREAM, MAX_SCATTER,  # noqa: F401
                                         FlatFieldStructure, _check_structure)
from slicersim.targets.state import check_config

__all__ = ["FLAT_SLICE_STREAM", "FLAT_PIXEL_STREAM", "DEFAULT_ETALON_FSR", "DEFAULT_ETALON_FINESSE",
           "FlatFieldStructure", "Flat3DCalibration", "Lazuli3DFlat", "locate_peaks"]

#: default etalon: free spectral range [cm⁻¹] and finesse, close to 1.4.2's tabulated Lazuli
#: etalon (898.8 cm⁻¹, i.e. n·d = 5.563 µm; finesse ≈ 25 near 6500 Å)
DEFAULT_ETALON_FSR, DEFAULT_ETALON_FINESSE = 898.8, 25.0


class Flat3DCalibration(Target):
    """A calibration exposure: a lamp filling the field uniformly, observed with an instrument.

    Products: :meth:`~slicersim.Flat3DCalibration.get_cube` (signal [ADU], variance [ADU²],
    noisy with a seed), :meth:`~slicersim.Flat3DCalibration.get_detector_image` (e-/s/px, both
    fields lit), :meth:`~slicersim.Target.get_ramps` (raw MACC ramps),
    :meth:`~slicersim.Flat3DCalibration.get_scene_cube` (the lamp before the instrument),
    :meth:`~slicersim.Flat3DCalibration.get_lamp_spectrum`.  The readout is set with
    :meth:`~slicersim.Target.change_detector` (default: the configuration's).

    Parameters
    ----------
    lamp : CalibrationLamp
        The lamp (:class:`~slicersim.CalibrationLamp`; see the ``from_*`` constructors).
    config : str, path-like or list, optional
        "cbe", "eol", a TOML path or a list of them.
    field : {"narrow", "wide"} or None, optional
        The field (default: as :class:`~slicersim.Target`).
    conventions : {"physical", "slicersim-1.0"}, optional
        Physics conventions ("physical" by default).
    structure : FlatFieldStructure or dict, optional
        None (ideal instrument), a :class:`~slicersim.FlatFieldStructure` or a dict of its
        arguments.
    """

    default_config, default_field = "cbe", "auto"
    own_parameters = ("field", "config")

    def __init__(self, lamp, config=None, field="default", conventions=DEFAULT_CONVENTIONS, structure=None):
        if field != "default":
            check_field(field)
        self._conventions = check_conventions(conventions)
        if not isinstance(lamp, CalibrationLamp):
            raise ParameterError(f"lamp must be a slicersim.sources.lamps.CalibrationLamp, got {lamp!r}")
        self.structure = _check_structure(structure)
        self.config = self.default_config if config is None else check_config(config)
        self._redshift, self.pointsource, self._host, self._host_offset = None, None, None, None
        self._lamp = lamp
        if field == "default":
            field = config_default_field(self.config) if self.default_field == "auto" else self.default_field
        self._field = check_field(field)
        self.simulation = self._new_simulation(self.config, self._field, keep_readout=False)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_lamp(cls, lamp, **kwargs):
        return cls(lamp, **kwargs)

    @classmethod
    def from_spectrum(cls, lbda, flux, mag=None, band="bessellb", magsys="ab", **kwargs):
        """Uniform lamp of tabulated surface brightness, optionally renormalised to ``mag`` per
        arcsec² in ``band``.

        Parameters
        ----------
        lbda : array_like of shape (n,)
            Wavelengths [Å].
        flux : array_like of shape (n,)
            Surface brightness S [erg/s/cm²/Å/arcsec²].
        mag : float, optional
            Magnitude per arcsec² in ``band`` the lamp is renormalised to [AB mag/arcsec²].
        band : str, optional
            sncosmo band of that magnitude.
        magsys : str, optional
            sncosmo magnitude system.
        **kwargs
            The parameters of :class:`~slicersim.Flat3DCalibration` (``config``, ``field``,
            ``conventions``, ``structure``).

        Returns
        -------
        Flat3DCalibration
            The calibration exposure (an instance of the class it is called on).
        """
        return cls(CalibrationLamp(TabulatedContinuum(lbda, flux, mag, band, magsys)), **kwargs)

    @classmethod
    def from_blackbody(cls, temperature, mag=15.0, band=DEFAULT_LAMP_BAND, magsys="ab", **kwargs):
        """Black-body lamp of ``temperature`` [K], ``mag`` per arcsec² (AB) in ``band``.

        Parameters
        ----------
        temperature : float
            Black-body temperature [K].
        mag : float, optional
            Magnitude of the lamp per arcsec² in ``band`` [AB mag/arcsec²].
        band : str, optional
            sncosmo band of that magnitude.
        magsys : str, optional
            sncosmo magnitude system.
        **kwargs
            The parameters of :class:`~slicersim.Flat3DCalibration` (``config``, ``field``,
            ``conventions``, ``structure``).

        Returns
        -------
        Flat3DCalibration
            The calibration exposure (an instance of the class it is called on).
        """
        return cls(CalibrationLamp(BlackBodyContinuum(temperature, mag, band, magsys)), **kwargs)

    @classmethod
    def from_qth(cls, temperature=None, mag=12.0, band=DEFAULT_LAMP_BAND, magsys="ab", **kwargs):
        """The QTH lamp: a black body of ``temperature`` (default 3000 K), ``mag`` per arcsec².

        Parameters
        ----------
        temperature : float, optional
            Black-body temperature [K] (default 3000).
        mag : float, optional
            Magnitude of the lamp per arcsec² in ``band`` [AB mag/arcsec²].
        band : str, optional
            sncosmo band of that magnitude.
        magsys : str, optional
            sncosmo magnitude system.
        **kwargs
            The parameters of :class:`~slicersim.Flat3DCalibration` (``config``, ``field``,
            ``conventions``, ``structure``).

        Returns
        -------
        Flat3DCalibration
            The calibration exposure (an instance of the class it is called on).
        """
        temperature = QTH_TEMPERATURE if temperature is None else temperature
        return cls.from_blackbody(temperature, mag, band, magsys, **kwargs)

    @classmethod
    def from_fabryperot(cls, fsr=None, finesse=None, optical_thickness=None, peak_transmission=None,
                        fp_throughput=None, temperature=None, mag=12.0, band=DEFAULT_LAMP_BAND, magsys="ab",
                        **kwargs):
        """The QTH lamp through a Fabry–Perot etalon (``mag``: the lamp's, before the etalon).

        Parameters
        ----------
        fsr : float, optional
            Airy etalon: free spectral range [cm⁻¹] (default ``DEFAULT_ETALON_FSR``).
        finesse : float, optional
            Airy etalon finesse (default ``DEFAULT_ETALON_FINESSE``).
        optical_thickness : float, optional
            Airy etalon: n·d [µm], instead of ``fsr``.
        peak_transmission : float, optional
            Airy etalon peak transmission (default 1).
        fp_throughput : str, callable or object, optional
            Or 1.4.2's tabulated form: a CSV/ECSV with a ``transmission`` column, a callable
            T(λ [Å]) or an etalon object.
        temperature : float, optional
            QTH temperature [K] (default 3000).
        mag : float, optional
            Magnitude of the lamp per arcsec² in ``band`` [AB mag/arcsec²].
        band : str, optional
            sncosmo band of that magnitude.
        magsys : str, optional
            sncosmo magnitude system.
        **kwargs
            The parameters of :class:`~slicersim.Flat3DCalibration` (``config``, ``field``,
            ``conventions``, ``structure``).

        Returns
        -------
        Flat3DCalibration
            The calibration exposure (an instance of the class it is called on).
        """
        airy = dict(fsr=fsr, finesse=finesse, optical_thickness=optical_thickness,
                    peak_transmission=peak_transmission)
        if fp_throughput is not None:
            given = sorted(k for k, v in airy.items() if v is not None)
            if given:
                raise ParameterError(f"give either fp_throughput or the Airy etalon's {given}, not both")
            etalon = as_etalon(fp_throughput)
        else:
            if fsr is None and optical_thickness is None:
                fsr = DEFAULT_ETALON_FSR
            etalon = FabryPerotEtalon(fsr, DEFAULT_ETALON_FINESSE if finesse is None else finesse,
                                      optical_thickness, 1.0 if peak_transmission is None else peak_transmission)
        continuum = BlackBodyContinuum(QTH_TEMPERATURE if temperature is None else temperature, mag, band, magsys)
        return cls(CalibrationLamp(continuum, etalon), **kwargs)

    @classmethod
    def from_febryperot(cls, fp_throughput=None, temperature=None, mag=12.0, band=DEFAULT_LAMP_BAND, **kwargs):
        """slicersim 1.4.2's spelling of :meth:`from_fabryperot` (same first argument,
        ``fp_throughput``; None: the default Airy etalon).

        Parameters
        ----------
        fp_throughput, temperature, mag, band
            As :meth:`from_fabryperot`.
        **kwargs
            The parameters of :class:`~slicersim.Flat3DCalibration` (``config``, ``field``,
            ``conventions``, ``structure``).

        Returns
        -------
        Flat3DCalibration
            The calibration exposure (an instance of the class it is called on).
        """
        return cls.from_fabryperot(fp_throughput=fp_throughput, temperature=temperature, mag=mag, band=band,
                                   **kwargs)

    # ------------------------------------------------------------------ state
    @property
    def lamp(self):
        """The :class:`~slicersim.sources.lamps.CalibrationLamp`; assigning one takes effect at once."""
        return self._lamp

    @lamp.setter
    def lamp(self, lamp):
        if not isinstance(lamp, CalibrationLamp):
            raise ParameterError(f"lamp must be a CalibrationLamp, got {lamp!r}")
        edges = self.simulation.spectrograph.lbda_edges
        lamp.check_coverage(edges[0], edges[-1])
        self._lamp = lamp
        self.simulation.scene.background.lamp = lamp

    @property
    def position(self):
        """A flat has no point source: None."""
        return None

    def _new_simulation(self, config, field, keep_readout=True, params=None):
        sim = build_simulation(config, field, pointsource=None, background=None, conventions=self._conventions)
        edges = sim.spectrograph.lbda_edges
        self._lamp.check_coverage(edges[0], edges[-1])
        sim.scene.background = LampIllumination(self._lamp, sim.spectrograph)
        upd = dict(params or {})
        if keep_readout:
            upd = {"nmd": self.simulation.detector.nmd, "nramps": self.simulation.nramps, **upd}
        if upd:
            sim.update(**upd)
        return sim

    def update(self, **params):
        """Change ``field``, ``config`` or any simulation parameter (``Simulation.mutable_parameters``)
        atomically; the readout is kept.

        Parameters
        ----------
        **params
            The parameters to change.

        Returns
        -------
        None
            The exposure is changed in place.
        """
        check_parameter_names("calibration", params, self.mutable_parameters)
        sim_params = {k: v for k, v in params.items() if k not in self.own_parameters}
        config = check_config(params["config"]) if "config" in params else self.config
        field = check_field(params["field"]) if "field" in params else self._field
        if "config" in params or "field" in params:
            new_sim = self._new_simulation(config, field, params=sim_params)
            self.config, self._field, self.simulation = config, field, new_sim
            return
        spec = self.simulation.spectrograph
        spec_params = {k: v for k, v in sim_params.items()
                       if k in spec.mutable_parameters and k not in self.simulation.detector.mutable_parameters}
        if spec_params:
            edges = spec.updated(**spec_params).lbda_edges
            self._lamp.check_coverage(edges[0], edges[-1])
        if sim_params:
            self.simulation.update(**sim_params)

    def _simulation_for(self, field):
        """The simulation of ``field`` (this one, or a copy in the other Lazuli field, same readout)."""
        if field == self._field:
            return self.simulation
        return self._new_simulation(self.config, check_field(field))

    # ------------------------------------------------------------------ products
    def get_lamp_spectrum(self):
        """The lamp averaged over each instrument bin.

        Returns
        -------
        lbda : numpy.ndarray of shape (nλ,)
            Wavelengths [Å].
        flux : numpy.ndarray of shape (nλ,)
            S̄ [erg/s/cm²/Å/arcsec²].
        """
        sim = self.simulation
        return sim.lbda.copy(), sim.scene.background.flambda(sim.lbda)

    def get_scene_cube(self):
        """Lamp flux per cell before the instrument: S̄(λ) s².

        Returns
        -------
        numpy.ndarray of shape (nλ, ny, nx)
            [erg/s/cm²/Å per cell].
        """
        sim = self.simulation
        ny, nx = sim.spectrograph.shape
        per_cell = sim.scene.background.flambda(sim.lbda) * sim.spectrograph.spatial_scale ** 2
        return np.repeat(np.repeat(per_cell[:, None, None], ny, axis=1), nx, axis=2)

    def _which(self, which):
        if which in (None, "current"):
            return [self._field]
        if which == "both":
            if self._field is None:
                raise ParameterError("which='both' needs a Lazuli configuration (narrow and wide fields)")
            return ["narrow", "wide"]
        if which in ("narrow", "wide"):
            if self._field is None:
                raise ParameterError(f"which={which!r} needs a Lazuli configuration")
            return [which]
        raise ParameterError(f"which must be 'current', 'narrow', 'wide' or 'both', got {which!r}")

    def get_cube(self, seed=None, which="current", nmd=None, nramps=None, backend="auto", switch_off=None,
                 **options):
        """Signal [ADU] and variance [ADU²] cubes (+ a noisy one with ``seed``), all ramps summed.

        One computation with or without flat-field structure: QE · (t_row LSF[lamp] + LSF[thermal])
        per row, × the cell response with pixel structure, then ``Simulation.cell_variance``
        (saturated cells NaN / +inf); noise as every cube (Philox, stream 0, voxel index).

        Parameters
        ----------
        seed : int, optional
            Integer in [0, 2⁶⁴) of the noisy cube; None: noiseless.
        which : {"current", "narrow", "wide", "both"}, optional
            "current" (this field), "narrow", "wide" or "both" (a tuple (narrow, wide), as 1.4.2).
        nmd : tuple of int, optional
            Readout (n, m, d) (default: the current one).
        nramps : int, optional
            Number of ramps (default: the current one).
        backend : str, optional
            "auto", "opencl" or "numpy".
        switch_off : str or sequence of str, optional
            Components left out, the rule of every cube (``slicersim.products.components``:
            "background" is the lamp, "thermal" the instrument's light, detector terms leave the
            variance; "pointsource" / "host" are absent anyway).
        **options
            ``dtype`` (float64 / float32); ``precision`` ("auto", "double" or "single": of the
            noise draw, ``slicersim.backends.noise.noisy_cube``; the cubes themselves are NumPy,
            double); ``psf_profile``, ``max_bytes``, ``progress``, ``psf_options`` are accepted as
            for any cube and unused (a uniform scene needs no PSF).

        Returns
        -------
        CubeTuple or tuple
            (signal, variance[, noisy]) of shape (nλ, ny, nx) [ADU, ADU²]; with ``which="both"``
            a tuple (narrow, wide) of them.
        """
        from slicersim.backends.precision import check_precision, resolve_precision
        from slicersim.products.components import check_switch_off
        from slicersim.simulation import CubeTuple
        seed = validation.seed(seed)
        off = check_switch_off(switch_off)
        fields = self._which(which)
        unknown = sorted(set(options) - {"dtype", "psf_profile", "max_bytes", "progress", "psf_options",
                                         "precision"})
        if unknown:
            raise ParameterError(f"unknown cube option(s) {unknown}")
        precision = check_precision(options.get("precision", "auto"))
        noise = None if seed is None else resolve_precision(precision, backend, "noise")   # before any work
        dtype = np.dtype(options.get("dtype", np.float64))
        if dtype not in (np.float64, np.float32):
            raise ParameterError(f"dtype must be float64 or float32, got {dtype}")
        if "psf_profile" in options:
            from slicersim.products.psf_profiles import get_psf_profile
            get_psf_profile(options["psf_profile"])
        out = tuple(CubeTuple(self._field_cube(self._simulation_for(f), f, nmd, nramps, seed, backend, dtype, off,
                                               noise), seed) for f in fields)
        return out if which == "both" else out[0]

    def _field_cube(self, sim, field, nmd, nramps, seed, backend, dtype, off, noise):
        """One field's CubeResult; ``noise``: the noise draw's resolved (backend, precision) (with a seed)."""
        from slicersim.backends.noise import noisy_cube, seed_from
        from slicersim.products.cube import PATH_ABSENT, PATH_OFF, CubeResult
        times = sim.get_times(nmd, nramps)
        nmd, nramps, tint = times["nmd"], times["nramps"], times["integration_time_per_ramp"]
        spec = sim.spectrograph
        (ny, nx), nl = spec.shape, sim.lbda.size
        electrons = self._rate_cube(sim, field, off)                                     # e-/s/cell (nλ, ny, 1)
        if self.structure.pixel_scatter:
            electrons = electrons * self.structure.cell_response((nl, ny, nx), field,
                                                                 getattr(spec, "pixels_per_cell", 1), backend)
        variance, saturated = sim.cell_variance(electrons, nmd, off)                      # ADU² per ramp
        signal = np.where(saturated, np.nan, electrons * tint * sim.detector.gain) * nramps
        del electrons
        shape = (nl, ny, nx)
        signal = np.broadcast_to(signal, shape).astype(dtype)
        variance = np.broadcast_to(variance * nramps, shape).astype(dtype)
        noisy = None
        if seed is not None:
            seed = seed_from(seed)
            noise_backend, noise_precision = noise
            noisy = noisy_cube(signal, variance, seed, backend=noise_backend, precision=noise_precision,
                               out=np.empty(shape, dtype) if noise_precision == "single" else None
                               ).astype(dtype, copy=False)
        lamp = "lamp: uniform" + ("" if self.structure.is_ideal else ", × flat-field structure")
        paths = {"pointsource": PATH_OFF if "pointsource" in off else PATH_ABSENT,
                 "host": PATH_OFF if "host" in off else PATH_ABSENT,
                 "background": PATH_OFF if "background" in off else lamp,
                 "thermal": PATH_OFF if "thermal" in off else "uniform",
                 "detector": "NumPy: spectrum per row" + (", per voxel (pixel structure)"
                                                          if self.structure.pixel_scatter else ", broadcast")}
        return tuple(CubeResult(signal, variance, noisy, paths, 1, sim.lbda.copy(), "uniform", seed))

    def _rate_cube(self, sim, field, off=frozenset()):
        """Photo-electron rate [e-/s/cell] of a field as (nλ, ny, 1) (uniform along the slices):
        slice throughputs t_row applied to the lamp light, not to the instrument's thermal light
        (no pixel response), components ``off`` removed: QE · (t_row LSF[lamp] + LSF[thermal])."""
        spec = sim.spectrograph
        lamp_ph, thermal_ph = sim.uniform_photons(off)
        lamp = spec.apply_lsf(lamp_ph) * sim.qe                                          # e-/s/cell
        thermal = spec.apply_lsf(thermal_ph) * sim.qe
        rows = self.structure.row_throughput(field, spec.shape[0])
        return lamp[:, None, None] * rows[None, :, None] + thermal[:, None, None]

    def get_field_rate_cubes(self):
        """Photo-electron rate cubes [e-/s per cell per bin] of both Lazuli fields, both lit by the lamp.

        Returns
        -------
        dict
            {field: (cube, simulation)} for "narrow" and "wide", each cube of shape
            (nλ, ny, nx) [e-/s per cell per bin].
        """
        if self._field is None:
            raise ParameterError("detector images need a Lazuli configuration (narrow and wide fields)")
        return {f: (np.ascontiguousarray(np.broadcast_to(self._rate_cube(sim, f), (sim.lbda.size,
                                                                                 *sim.spectrograph.shape))), sim)
                for f in ("narrow", "wide") for sim in [self._simulation_for(f)]}

    def get_detector_image(self, mapper=None, backend="auto", precision="auto"):
        """Photo-electron rate on the H4RG [e-/s/px] with both fields lit (flux-conserving
        projection), times the pixel response when ``structure`` has one.  Dark current, thermal
        dark and ROIC glow are added by :meth:`~slicersim.Target.get_ramps`.

        Parameters
        ----------
        mapper : SlicerMapper, optional
            The detector mapping (default: the built-in one).
        backend : str, optional
            "auto", "opencl" or "numpy".
        precision : {"auto", "double", "single"}, optional
            Of the projection's deposit, checked first (as
            :meth:`Target.get_detector_image <slicersim.Target.get_detector_image>`).

        Returns
        -------
        numpy.ndarray of shape (rows, cols)
            The rate image [e-/s/px].
        """
        precision = resolve_precision(precision, backend, "projection")[1]
        mapper = default_mapper() if mapper is None else mapper
        image = np.zeros(mapper.detector_shape)
        for field, (cube, sim) in self.get_field_rate_cubes().items():
            mapper.project_fields(sim.lbda, sim.spectrograph.lbda_edges, out=image, backend=backend,
                                  precision=precision, **{field: cube})
        if self.structure.pixel_scatter:
            image *= self.structure.pixel_response(image.shape, backend)
        return image

    # get_ramps: Target.get_ramps (raw MACC ramps of get_detector_image + the detector's dark terms)

    # ------------------------------------------------------------------ not for a flat
    def _no_point_source(self, *args, **kwargs):
        raise NotImplementedError("a calibration flat has no point source: no extracted spectrum, SNR or "
                                  "ETC; use get_cube / get_detector_image / get_ramps (the readout is set "
                                  "with change_detector)")

    get_spectrum = setup_to_snr = get_band_snr = _no_point_source
    get_variance_contribution = get_band_variance_contribution = _no_point_source

    def set_host(self, host, relative=True):
        """A flat takes no host: ParameterError (``None``, no host, is accepted).

        Parameters
        ----------
        host : None
            Only None (no host) is accepted.
        relative : bool, optional
            Unused.

        Returns
        -------
        None
            Nothing changes.
        """
        if host is not None:
            raise ParameterError("a calibration flat takes no host: its scene is the lamp filling the field "
                                 "(put hosts on astronomical targets: LazuliSupernova(..., host=...), set_host)")


class Lazuli3DFlat(Flat3DCalibration):
    __doc__ = lazuli_doc(Flat3DCalibration, "Lazuli calibration exposure (slicersim 1.4.2 ``Lazuli3DFlat``).")

    default_config, default_field = "cbe", "narrow"


def locate_peaks(lbda, spectrum, guesses, half_window=3):
    """Positions of spectral peaks: (fractional bin index, λ [Å]) of each peak near ``guesses`` [Å].

    The maximum within ±``half_window`` bins of each guess, refined by the vertex of the
    parabola through the logarithms of the three bins around it (exact for a Gaussian line);
    bin index → λ by linear interpolation of the bin centres ``lbda``.  NaN where the maximum
    sits on the window's or the grid's edge."""
    lbda, spectrum = np.asarray(lbda, float), np.asarray(spectrum, float)
    guess_idx = np.interp(np.asarray(guesses, float), lbda, np.arange(lbda.size))
    out = np.full(guess_idx.size, np.nan)
    for n, g in enumerate(guess_idx):
        lo, hi = max(0, int(round(g)) - half_window), min(lbda.size, int(round(g)) + half_window + 1)
        i = lo + int(np.argmax(spectrum[lo:hi]))
        if i in (lo, hi - 1) or i == 0 or i == lbda.size - 1 or np.any(spectrum[i - 1:i + 2] <= 0):
            continue
        a, b, c = np.log(spectrum[i - 1:i + 2])
        out[n] = i + 0.5 * (a - c) / (a - 2 * b + c)
    return out, np.interp(out, np.arange(lbda.size), lbda, left=np.nan, right=np.nan)
