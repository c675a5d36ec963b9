"""High-level targets: build a Lazuli (or any configured) simulation around a source.

``LazuliSupernova(redshift=1).setup_to_snr(20)`` is an exposure-time
calculation in one line; :func:`lazuli_etc` / :func:`lazuli_sn_etc` return the
result as a dict.  The ETC, band-SNR, spectrum and cube methods of :class:`Target` come from
:class:`~slicersim.targets.observation.ObservationMixin`, the detector image and raw ramps from
:class:`~slicersim.targets.detector.DetectorProducts`.
"""
from __future__ import annotations

import inspect

from slicersim import validation
from slicersim.assembly import LAZULI_FIELDS, build_simulation, check_field  # noqa: F401
from slicersim.errors import ParameterError, SlicersimError
from slicersim.io.config import load_config
from slicersim.io.curves import read_curve
from slicersim.physics.conventions import DEFAULT_CONVENTIONS, check_conventions, phase_frame
from slicersim.physics.readout import check_readout
from slicersim.instrument.names import check_parameter_names
from slicersim.sources.galaxies import (HOST_PARAMETERS, HostPlacement, check_host_covers, check_host_in_field,
                                        host_offset)
from slicersim.sources.spectra import PointSource, snia_spectrum
from slicersim.targets.detector import DetectorProducts
from slicersim.targets.observation import DEFAULT_BAND, SPECTRUM_NOISE_STREAM, ObservationMixin  # noqa: F401
from slicersim.targets.state import (check_config, check_redshift, _host_centre,  # noqa: F401
                                     _move_host, _TargetUpdate)

__all__ = ["LAZULI_FIELDS", "build_simulation", "config_default_field", "SPECTRUM_NOISE_STREAM", "Target", "lazuli_doc",
           "Supernova", "BlackBody", "LazuliTarget", "LazuliSupernova", "LazuliBlackBody", "lazuli_etc",
           "lazuli_sn_etc"]


def config_default_field(config):
    """Field a target uses when none is given: ``"narrow"`` when the configuration's throughput
    file has Lazuli field columns (``narrow``/``wide``), else None (single-channel instrument)."""
    try:
        cfg = load_config(config)
        thr = cfg.get("spectrograph.throughput", {}).get("throughput")
        if isinstance(thr, str):
            _, cols = read_curve(thr)
            if "narrow" in cols:
                return "narrow"
    except (OSError, ValueError, KeyError):
        return None      # build_simulation reports the problem
    return None


class Target(ObservationMixin, DetectorProducts):
    """A point source observed with a configured instrument.

    Parameters
    ----------
    lbda : array_like of shape (n,)
        Wavelengths of the input spectrum [Å].
    flux : array_like of shape (n,)
        F_λ of the input spectrum [erg/s/cm²/Å].
    mag : float, optional
        Renormalisation to an AB magnitude in ``band`` (none by default).
    band : str, optional
        sncosmo band of that renormalisation.
    config : str, path-like or list, optional
        "cbe", "eol", a TOML path or a list of them.
    field : {"narrow", "wide"} or None, optional
        The Lazuli field, or None.  A target has exactly one field: the default is "narrow"
        when the configuration has Lazuli field throughputs (``config_default_field``),
        None for single-channel configurations; None with a several-column throughput raises
        (columns are never multiplied).
    position : tuple of float, optional
        (x, y) of the point source relative to the field centre [cells].
    redshift : float, optional
        Used by ``frame="rest"`` (the spectrum is in the observer frame).  A band
        (``lbda_range``) is read in the rest frame by default when the target has a redshift,
        else in the observer frame (``frame=None``; ``"rest"`` / ``"obs"`` explicit).
    conventions : {"physical", "slicersim-1.0"}, optional
        "physical" (default) or "slicersim-1.0": reproduce slicersim 1.0 exactly (gain in
        the variance, instrumental blur; ``slicersim.physics.conventions``).
    host : str, dict, GalaxyModel, Host or CubeSource, optional
        Host galaxy (see :meth:`~slicersim.Target.set_host`): a model name ("sersic:bb-5000", "ngc0628",
        "sersic:ngc2403", ...), a dict with ``refmodel`` and parameters (1.4.2), a
        :class:`~slicersim.sources.galaxies.GalaxyModel`, a ``Host`` or a ``CubeSource``.
    """

    default_config, default_field = "cbe", "auto"
    #: parameters of the target itself (the simulation adds its own, see ``mutable_parameters``)
    own_parameters = ("redshift", "position", "field", "config")
    #: host in the scene and how it is held (sources.galaxies.HostPlacement); none by default
    _host = _host_state = None

    def __init__(self, lbda, flux, mag=None, band="bessellb", config=None, field="default",
                 position=(0.0, 0.0), redshift=None, conventions=DEFAULT_CONVENTIONS, host=None):
        self._conventions = check_conventions(conventions)
        self._redshift = check_redshift(redshift)
        self._source_args = dict(lbda=lbda, flux=flux, mag=mag, band=band, position=position)
        self.pointsource = PointSource(lbda, flux, position=position, mag=mag, band=band)
        self._setup(config, field, host)

    def _setup(self, config, field, host):
        """Configuration, field, simulation and host (shared by every target kind)."""
        self._host, self._host_state = None, None
        self.config = self.default_config if config is None else check_config(config)
        if field == "default":
            field = config_default_field(self.config) if self.default_field == "auto" else self.default_field
        self._field = check_field(field)
        self.simulation = self._new_simulation(self.config, self._field, keep_readout=False)
        if host is not None:
            self.set_host(host)

    # ------------------------------------------------------------------ state
    @property
    def field(self):
        """Lazuli field ("narrow"/"wide") or None; assigning it rebuilds the simulation."""
        return self._field

    @field.setter
    def field(self, field):
        self.change_field(field)

    @property
    def redshift(self):
        return self._redshift

    @redshift.setter
    def redshift(self, redshift):
        self.update(redshift=redshift)

    @property
    def position(self):
        """(x, y) [cells] of the point source relative to the field centre."""
        return self.pointsource.position

    @position.setter
    def position(self, position):
        self.update(position=position)

    @property
    def host(self):
        """The host in the scene (Host or CubeSource, at the target's redshift) or None."""
        return self._host

    @property
    def host_model(self):
        """:class:`~slicersim.sources.galaxies.GalaxyModel` of a host given by name, else None."""
        return None if self._host_state is None else self._host_state.model

    @host.setter
    def host(self, host):
        self.set_host(host)

    @property
    def conventions(self):
        """"physical" or "slicersim-1.0" (fixed at construction)."""
        return self._conventions

    @property
    def mutable_parameters(self):
        """Every name :meth:`update` accepts: the target's own (redshift, position, field,
        config), ``host__<name>`` for a host given by name (1.4.2; names of
        :class:`~slicersim.sources.galaxies.GalaxyModel`) and those of its
        :class:`~slicersim.simulation.Simulation`."""
        host = () if self.host_model is None else tuple(f"host__{k}" for k in HOST_PARAMETERS)
        return self.own_parameters + host + tuple(p for p in self.simulation.mutable_parameters
                                                  if p not in self.own_parameters)

    def _new_simulation(self, config, field, keep_readout=True, params=None):
        """A new simulation of this target (validated; nothing of self changes)."""
        sim = build_simulation(config, field, self.pointsource, conventions=self._conventions)
        sim.redshift = self._redshift
        upd = dict(params or {})
        if keep_readout:
            old = self.simulation
            upd = {"nmd": old.detector.nmd, "nramps": old.nramps, **upd}    # explicit readout wins
        if upd:
            sim.update(**upd)
        if self._host is not None:      # placed for the new cell size when applied (update)
            sim.scene.host = self._host
        return sim

    def _spectrum_at(self, redshift):
        """(λ, F) of the source at ``redshift``, or None when the spectrum does not depend on
        it (a user spectrum is given in the observer frame: only the label changes)."""
        return None

    # ------------------------------------------------------------------ host
    def set_host(self, host, relative=True):
        """Put a host galaxy in the scene, at the target's redshift; ``None`` removes it.

        Takes effect at once; ``update(redshift=z)`` then moves source and host together.

        Parameters
        ----------
        host : str, dict, GalaxyModel, Host, CubeSource or None
            A model name ("sersic:bb-5000", "ngc0628", "sersic:ngc2403", ...), a dict
            (``refmodel`` + parameters, slicersim 1.4.2), a :class:`~slicersim.GalaxyModel`
            (all rendered at the target's redshift, or the dict's ``redshift`` when the target has
            none), or a ready ``Host`` / ``CubeSource``: one with a different ``redshift`` is moved
            to the target's (:meth:`Host.at_redshift <slicersim.Host.at_redshift>`), one without is
            taken to be at it.
        relative : bool, optional
            Placement: the host centre (``offset`` [arcsec] of a model, ``profile.offset`` /
            ``centre`` of an object) is read relative to the target when ``relative`` (the host
            follows the target; offsets scale with D_A when the redshift changes), else relative to
            the field centre; a model's 1.4.2 ``position`` [cells] is absolute.

        Returns
        -------
        None
            The scene is changed in place.
        """
        if host is None:
            self._host, self._host_state = None, None
            self.simulation.scene.host = None
            return
        relative = validation.flag("relative", relative)
        sim = self.simulation
        state = HostPlacement.resolve(host, self._redshift, relative, sim.spectrograph.spatial_scale)
        placed = state.at(self._redshift)
        check_host_covers(placed, sim.lbda)
        centre = _host_centre(state, self._redshift, self.position, sim.spectrograph.spatial_scale)
        check_host_in_field(placed, centre, sim.spectrograph.shape, sim.spectrograph.spatial_scale)
        self._host_state, self._host = state, placed
        _move_host(placed, centre)
        sim.scene.host = placed

    def _place_host(self, host, position, spatial_scale):
        if self._host_state is not None:
            _move_host(host, _host_centre(self._host_state, self._redshift, position, spatial_scale))

    def host_centre(self):
        """(x, y) [cells] of the host centre in the field (None without host).

        Returns
        -------
        tuple of float or None
            (x, y) [cells].
        """
        if self._host is None:
            return None
        s = self.simulation.spectrograph.spatial_scale
        x, y = host_offset(self._host)
        return (x / s, y / s)

    # ------------------------------------------------------------------ changes
    def update(self, **params):
        """Change any of ``mutable_parameters`` atomically (validated first; on error nothing
        changes).  The readout is kept.

        Parameters
        ----------
        **params
            ``redshift`` recomputes the source spectrum in place (SN Ia: same phase, source and
            peak magnitude; a user spectrum keeps its observer-frame flux and only the label used
            by ``frame="rest"`` changes); ``position=(x, y)`` [cells] moves the point source in
            place (and a host attached relative to it); ``field`` / ``config`` rebuild the
            simulation keeping the readout; the other names go to
            :meth:`Simulation.update <slicersim.Simulation.update>`.

        Returns
        -------
        None
            The target is changed in place.
        """
        self._apply_update(self._plan_update(params))

    def _plan_update(self, params):
        """Validate an :meth:`update` off to the side: a :class:`_TargetUpdate` (nothing changed)."""
        accepted = self.mutable_parameters
        hint = ("; host__<name> needs a host given by name (set_host('sersic:bb-5000', ...))"
                if any(k.startswith("host__") and k not in accepted for k in params) else "")
        check_parameter_names("target", params, accepted, hint)
        plan = _TargetUpdate()
        host_params = {k[len("host__"):]: v for k, v in params.items() if k.startswith("host__")}
        sim_params = {k: v for k, v in params.items() if k not in self.own_parameters and not k.startswith("host__")}
        spectrum = None
        redshift = self._redshift
        if "redshift" in params:
            redshift = check_redshift(params["redshift"])
            spectrum = self._spectrum_at(redshift) if redshift is not None else None
            if spectrum is None and redshift is None and self._spectrum_at(1.0) is not None:
                raise ParameterError("this target's spectrum needs a redshift")
        probe = None
        if spectrum is not None:
            probe = PointSource(*spectrum, position=self.pointsource.position,
                                mag=self.pointsource.mag, band=self.pointsource.band)
        position = self.position
        if "position" in params:
            position = PointSource([1.0, 2.0], [0.0, 0.0], position=params["position"]).position
        config = check_config(params["config"]) if "config" in params else self.config
        field = check_field(params["field"]) if "field" in params else self._field
        if "config" in params or "field" in params:
            saved = self.pointsource
            self.pointsource = probe or saved
            try:
                plan.new_sim = self._new_simulation(config, field, params=sim_params)
            finally:
                self.pointsource = saved
            plan.new_sim._check_aperture_cells(plan.new_sim.spectrograph, plan.new_sim.telescope,
                                               plan.new_sim.aperture_radius_insigma, position)
            state = plan.new_sim
        else:
            if sim_params or "position" in params:
                # validates the components and the aperture at the new position (nothing applied)
                plan.sim_update = self.simulation.plan_update(_position=position, **sim_params)
            state = plan.sim_update or self.simulation
        spec = state.spectrograph
        if probe is not None and not probe.overlap(spec.lbda[0], spec.lbda[-1]):
            raise ParameterError(f"the spectrum at redshift {redshift} does not overlap the instrument range")
        host_state = self._host_state
        if host_state is not None:
            if host_params:
                host_state = host_state.updated(host_params, redshift, spec.spatial_scale)
            if host_params or redshift != self._redshift:
                plan.new_host = host_state.at(redshift)
            host = plan.new_host or self._host
            check_host_covers(host, spec.lbda)
            plan.host_centre = _host_centre(host_state, redshift, position, spec.spatial_scale)
            check_host_in_field(host, plan.host_centre, spec.shape, spec.spatial_scale)
        plan.params = params
        plan.probe, plan.redshift, plan.position, plan.config, plan.field = probe, redshift, position, config, field
        plan.host_state, plan.state = host_state, state
        return plan

    def _apply_update(self, plan):
        """Apply a :meth:`_plan_update` result (nothing here can fail)."""
        if plan.probe is not None:
            probe = plan.probe
            self.pointsource.set_spectrum(probe.lbda_in, probe.flux_in, probe.flux_ratio, probe.native_mag)
        self._redshift = plan.redshift
        if plan.new_sim is not None:
            plan.new_sim.scene.pointsource = self.pointsource
            self.config, self._field, self.simulation = plan.config, plan.field, plan.new_sim
        elif plan.sim_update is not None:
            self.simulation.apply_update(plan.sim_update)
        self.simulation.redshift = plan.redshift
        if plan.position != self.position:
            self._move_to(plan.position)
        self._host_state = plan.host_state
        if plan.new_host is not None:
            self._host = plan.new_host
            self.simulation.scene.host = plan.new_host
        if self._host is not None:
            _move_host(self._host, plan.host_centre)

    def _move_to(self, position):
        """Set the source position [cells] (validated by :meth:`update`)."""
        self.pointsource.position = position

    def set_throughput(self, throughput, column=None, noptics=None):
        """Replace the spectrograph throughput (see :meth:`Spectrograph.set_throughput
        <slicersim.Spectrograph.set_throughput>`); at once.

        Parameters
        ----------
        throughput : float, tuple of array_like, OpticalThroughput or str
            As :class:`~slicersim.Spectrograph`.
        column : str or int, optional
            Column of a throughput curve file.
        noptics : dict or int, optional
            Passes through each component.

        Returns
        -------
        None
            The target is changed in place.
        """
        try:
            self.simulation.spectrograph.set_throughput(throughput, column=column, noptics=noptics)
        except SlicersimError:
            raise
        except (ValueError, TypeError, OSError, KeyError) as exc:
            raise ParameterError(f"throughput: invalid throughput {validation.short_repr(throughput)}: {exc}") from exc

    def change_configuration(self, config):
        """Switch to another configuration; keeps the readout.

        Parameters
        ----------
        config : str, path-like or list
            ``"cbe"``, ``"eol"``, TOML path(s).

        Returns
        -------
        None
            The target is changed in place.
        """
        self.update(config=config)

    def change_field(self, field):
        self.update(field=field)

    def change_spectrograph(self, field=None, **kwargs):
        """Change the field (Lazuli) and/or spectrograph parameters.

        Parameters
        ----------
        field : {"narrow", "wide"}, optional
            The Lazuli field.
        **kwargs
            Spectrograph parameters (see :class:`~slicersim.Spectrograph`).

        Returns
        -------
        None
            The target is changed in place.
        """
        if field is not None:
            kwargs["field"] = field
        if kwargs:
            self.update(**kwargs)

    def change_detector(self, nmd=None, nramps=None, max_group=None, **kwargs):
        """Set the readout (n, m, d), number of ramps, max_group or other detector parameters.

        Parameters
        ----------
        nmd : tuple of int, optional
            The readout (n, m, d).
        nramps : int, optional
            Number of ramps.
        max_group : int, optional
            Largest n allowed.
        **kwargs
            Other detector parameters (see :class:`~slicersim.Detector`).

        Returns
        -------
        None
            The target is changed in place.
        """
        params = dict(kwargs)
        if max_group is not None:
            params["max_group"] = validation.integer("max_group", max_group, low=1)
        if nmd is not None:
            check_readout(nmd, self.simulation.nramps if nramps is None else nramps,
                          self.simulation.detector.min_group,
                          params.get("max_group", self.simulation.detector.max_group))
            params["nmd"] = tuple(int(v) for v in nmd)
        if nramps is not None:
            params["nramps"] = nramps
        self.simulation.update(**params)


class Supernova(Target):
    """SN Ia at ``redshift`` from sncosmo (default ``hsiao-subsampled``, offline), peak
    absolute magnitude ``peak_absmag`` in Bessell B (AB, Planck18), at ``phase`` days from
    B-band maximum in the SN's rest frame (the frame of populations, campaigns, survey plans,
    the CLI and every file that records it; observer-frame days under
    ``conventions="slicersim-1.0"``, as in slicersim 1.0: ``slicersim.physics.conventions.phase_frame``).

    Parameters
    ----------
    redshift : float
        Redshift z, 0 < z ≤ 50.
    phase : float
        Days from B-band maximum [d] (rest frame; see above).
    source : str, tuple or sncosmo.Source
        sncosmo SN Ia source (``"salt2"``/``"salt3"`` offline where their files are installed).
    peak_absmag : float
        Peak absolute magnitude in rest-frame Bessell B, AB [mag].
    config, field, position, conventions, host
        As :class:`Target`.
    **kwargs
        The SN model's keywords of ``slicersim.sources.spectra.snia_spectrum`` (``band``,
        ``magsys``, ``lbda``, ``x1``, ``c``, ``cosmology``).
    """

    def __init__(self, redshift, phase=0.0, source="hsiao-subsampled", peak_absmag=-19.3, config=None,
                 field="default", position=(0.0, 0.0), conventions=DEFAULT_CONVENTIONS, host=None, **kwargs):
        model_keywords = [k for k in inspect.signature(snia_spectrum).parameters
                          if k not in ("redshift", "phase", "source", "peak_absmag", "phase_frame")]
        for key in kwargs:          # the SN model's keywords; a misspelt target keyword is named, with a did-you-mean
            validation.choice("keyword", key, model_keywords + ["config", "field", "position", "conventions", "host"],
                              what=f"keyword of {type(self).__name__}")
        self.phase, self.source, self.peak_absmag = phase, source, peak_absmag
        self._sn_kwargs = {**kwargs, "phase_frame": phase_frame(conventions)}
        redshift = check_redshift(redshift)
        if redshift is None:
            raise ParameterError("a supernova needs a redshift")
        lbda, flux = snia_spectrum(redshift, phase, source, peak_absmag, **self._sn_kwargs)
        super().__init__(lbda, flux, config=config, field=field, position=position, redshift=redshift,
                         conventions=conventions, host=host)

    def _spectrum_at(self, redshift):
        return snia_spectrum(redshift, self.phase, self.source, self.peak_absmag, **self._sn_kwargs)

    # A supernova has a redshift: its bands are read in the rest frame by default (frame=None,
    # 4000–6800 Å rest), in setup_to_snr, get_band_snr and get_band_variance_contribution alike,
    # and so are those of its simulation (Simulation.get_band_snr), so that
    # ``get_band_snr(per_resolution=True)`` after ``setup_to_snr(snr)`` reports the SNR the ETC reached.


class BlackBody(Target):
    """Black body of ``temperature`` [K] normalised to ``mag`` (AB) in ``band``.

    Parameters
    ----------
    temperature : float
        Black-body temperature [K].
    mag : float
        AB magnitude of the source in ``band`` [mag].
    band : str, optional
        sncosmo band of that normalisation.
    config, field, position, conventions, redshift, host
        As :class:`Target`.
    """

    def __init__(self, temperature, mag, band="bessellb", config=None, field="default", position=(0.0, 0.0),
                 conventions=DEFAULT_CONVENTIONS, redshift=None, host=None):
        src = PointSource.from_blackbody(temperature, mag, band)
        super().__init__(src.lbda_in, src.flux_in, mag=mag, band=band, config=config, field=field,
                         position=position, conventions=conventions, redshift=redshift, host=host)
        self.temperature = temperature


class _Lazuli:
    default_config, default_field = "cbe", "narrow"


def lazuli_doc(parent, summary):
    """Docstring of a Lazuli variant of ``parent``: ``summary``, the Lazuli defaults, then the
    parent's whole documentation (so ``help()`` of the variant lists every parameter)."""
    body = inspect.cleandoc(parent.__doc__ or "")
    return (f"{summary}\n\nLazuli defaults: ``config=\"cbe\"`` (current best estimate; or \"eol\", TOML "
            f"paths), ``field=\"narrow\"`` (or \"wide\").  Otherwise as :class:`{parent.__name__}`:\n\n{body}")


class LazuliTarget(_Lazuli, Target):
    __doc__ = lazuli_doc(Target, "Target observed with the Lazuli IFS.")


class LazuliSupernova(_Lazuli, Supernova):
    __doc__ = lazuli_doc(Supernova, "SN Ia observed with the Lazuli IFS.")


class LazuliBlackBody(_Lazuli, BlackBody):
    __doc__ = lazuli_doc(BlackBody, "Black body observed with the Lazuli IFS.")


def _result(target, etc):
    sim = target.simulation
    return {"nmd": etc["nmd"], "nramps": etc["nramps"], "exposure_time": etc["exposure_time"],
            "snr": etc["snr_per_resolution"], "snr_per_bin": etc["snr"], "snr_target_per_bin": etc["snr_target"],
            "lbda_range_obs": etc["lbda_range_obs"], "data_volume": sim.get_data_volume(),
            "config": target.config, "field": target.field, "conventions": target.conventions, "target": target}


def lazuli_etc(lbda, flux, snr=20, mag=None, band="bessellb", lbda_range=(4000, 6800), frame=None,
               config="cbe", field="narrow", search="exact", redshift=None, **options):
    """Exposure time for any spectrum with the Lazuli IFS.

    Parameters
    ----------
    lbda : array_like of shape (n,)
        Wavelengths of the spectrum [Å].
    flux : array_like of shape (n,)
        F_λ [erg/s/cm²/Å].
    snr : float, optional
        SNR to reach, per resolution element.
    mag : float, optional
        Renormalisation to an AB magnitude in ``band``.
    band : str, optional
        sncosmo band of that renormalisation.
    lbda_range : tuple of float, optional
        (min, max) of the band where the SNR is reached [Å].
    frame : {"rest", "obs"} or None, optional
        Frame of ``lbda_range`` (None: "rest" with a ``redshift``, else "obs"), as
        :meth:`Target.setup_to_snr`.
    config : str, path-like or list, optional
        Configuration ("cbe", "eol", TOML path(s)).
    field : {"narrow", "wide"}, optional
        Lazuli field.
    search : str, optional
        Readout search of the ETC, as :meth:`Target.setup_to_snr`.
    redshift : float, optional
        Redshift of the target (the spectrum is in the observer frame).
    **options
        ``conventions`` (default "physical") and ``allow_partial`` (band coverage rule of
        :meth:`Target.setup_to_snr`, default False).

    Returns
    -------
    dict
        ``nmd``, ``nramps``, ``exposure_time`` [s], ``snr`` (per resolution element),
        ``snr_per_bin``, ``snr_target_per_bin``, ``lbda_range_obs`` [Å], ``data_volume``
        [GB], ``config``, ``field``, ``conventions`` and ``target`` (the
        :class:`LazuliTarget` set to that readout).
    """
    check_parameter_names("lazuli_etc", options, ("conventions", "allow_partial"))
    target = LazuliTarget(lbda, flux, mag=mag, band=band, config=config, field=field, redshift=redshift,
                          conventions=options.get("conventions", DEFAULT_CONVENTIONS))
    return _result(target, target.setup_to_snr(snr, lbda_range, frame, search=search,
                                               allow_partial=options.get("allow_partial", False)))


def lazuli_sn_etc(redshift, snr=20, lbda_range=(4000, 6800), frame=None, config="cbe", field="narrow",
                  search="exact", phase=0.0, source="hsiao-subsampled", conventions=DEFAULT_CONVENTIONS,
                  allow_partial=False):
    """Exposure time for a SN Ia at ``redshift`` (band in the rest frame by default).

    Parameters
    ----------
    redshift : float
        Redshift z of the SN Ia.
    snr : float, optional
        SNR to reach, per resolution element.
    lbda_range : tuple of float, optional
        (min, max) of the band [Å], in the rest frame by default.
    frame : {"rest", "obs"} or None, optional
        Frame of ``lbda_range`` (None: "rest").
    config : str, path-like or list, optional
        Configuration ("cbe", "eol", TOML path(s)).
    field : {"narrow", "wide"}, optional
        Lazuli field.
    search : str, optional
        Readout search of the ETC, as :meth:`Target.setup_to_snr`.
    phase : float, optional
        Days from B-band maximum [d], as :class:`Supernova`.
    source : str, optional
        sncosmo SN Ia source.
    conventions : {"physical", "slicersim-1.0"}, optional
        Physics conventions, as :class:`Target`.
    allow_partial : bool, optional
        Band coverage rule of :meth:`Target.setup_to_snr`.

    Returns
    -------
    dict
        As :func:`lazuli_etc`: ``nmd``, ``nramps``, ``exposure_time`` [s], ``snr`` (per
        resolution element), ``data_volume`` [GB], ``target`` (a :class:`LazuliSupernova`), ...
    """
    target = LazuliSupernova(redshift, phase=phase, source=source, config=config, field=field,
                             conventions=conventions)
    return _result(target, target.setup_to_snr(snr, lbda_range, frame, search=search, allow_partial=allow_partial))
