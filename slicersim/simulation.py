"""Simulation: scene + telescope + spectrograph + detector → cubes, spectra, SNR, ETC.

Reads as the physics (units in comments).  Noiseless expectations are computed
first; a noise realisation is a separate step with an explicit seed.  The readout, variance,
extraction and band-SNR methods come from :class:`slicersim.snr.spectrum.SpectrumSNRMixin`.
"""
from __future__ import annotations

import numpy as np

from slicersim import validation
from slicersim.constants import HC_ERG_AA
from slicersim.errors import ParameterError, SpectrumError
from slicersim.instrument.names import check_parameter_names
from slicersim.physics.conventions import DEFAULT_CONVENTIONS, check_conventions, instrumental_blur_sigma
from slicersim.physics.psf import aperture_cells, gaussian_psf_fractions, gaussian_psf_sigmas
from slicersim.physics.readout import check_readout
from slicersim.physics.thermal import thermal_dark_rate
from slicersim.products.components import (SCENE_COMPONENTS, VARIANCE_SOURCES, as_switched_off,  # noqa: F401
                                             check_switch_off, uniform_terms_on)
from slicersim.products.cube import build_cube, build_scene_cubes, scene_photon_rates
from slicersim.products.extraction import ExtractionModel
from slicersim.snr.spectrum import FRAMES, SpectrumSNRMixin, check_band, resolve_frame
from slicersim.versioning import Versioned, state_token

__all__ = ["Simulation", "SimulationUpdate", "VARIANCE_SOURCES", "SCENE_COMPONENTS", "ExtractionModel", "CubeTuple",
           "check_band", "resolve_frame", "FRAMES"]


class CubeTuple(tuple):
    """(signal, variance[, noisy]) of :meth:`Simulation.get_cube`, a plain tuple that also
    records the noise ``seed`` (int; None without a noisy cube) so a draw can be repeated."""

    def __new__(cls, items, seed=None):
        obj = super().__new__(cls, items)
        obj.seed = seed
        return obj


class SimulationUpdate:
    """A validated, not yet applied :meth:`Simulation.update`: the new components (built off to
    the side), ``nramps`` and ``aperture_radius_insigma``; ``spectrograph`` / ``telescope`` /
    ``detector`` give the state the simulation will have."""

    def __init__(self, simulation, components, nramps, aperture_radius_insigma):
        self.simulation, self.components = simulation, components
        self.nramps, self.aperture_radius_insigma = nramps, aperture_radius_insigma

    def __getattr__(self, name):
        if name in ("spectrograph", "telescope", "detector"):
            return self.components.get(name, getattr(self.simulation, name))
        raise AttributeError(name)


class Simulation(SpectrumSNRMixin, Versioned):
    """An IFS observation of a scene.

    Parameters
    ----------
    scene : Scene
        The sources (point source, background, host).
    telescope : Telescope
        The telescope.
    spectrograph : Spectrograph
        The spectrograph (:class:`SlicerSpectrograph` or :class:`MLASpectrograph`).
    detector : Detector
        The detector and its readout.
    nramps : int, optional
        Number of identical ramps (summed).
    aperture_radius_insigma : float, optional
        Extraction radius in units of σ_ref / s.
    conventions : {"physical", "slicersim-1.0"}, optional
        "physical" (default) or "slicersim-1.0" (``slicersim.physics.conventions``).
    redshift : float, optional
        Redshift of the observed source (set by targets; used by ``frame="rest"`` bands).

    Notes
    -----
    Every derived quantity is cached, keyed on the versions of the scene, its
    sources and the instrument components (``slicersim.versioning``): any
    ``update``, ``set_throughput``, ``scene.host = ...`` or attribute assignment
    invalidates it at once.
    """

    #: parameters of the simulation itself (the components add theirs)
    own_parameters = ("nramps", "aperture_radius_insigma")

    def __init__(self, scene, telescope, spectrograph, detector, nramps=1,
                 aperture_radius_insigma=10.0, redshift=None, conventions=DEFAULT_CONVENTIONS):
        self._conventions = check_conventions(conventions)
        self.scene, self.telescope = scene, telescope
        self.spectrograph, self.detector = spectrograph, detector
        _, self.nramps = check_readout(detector.nmd, _check_nramps(nramps), detector.min_group,
                                       detector.max_group)
        self.aperture_radius_insigma = _check_aperture(aperture_radius_insigma)
        self.redshift = None if redshift is None else validation.redshift("redshift", redshift)
        self._cache = {}
        object.__setattr__(self, "_cache_token", None)
        self._check_overlap()
        self._check_aperture_cells(spectrograph, telescope, self.aperture_radius_insigma, self.position)

    @property
    def conventions(self):
        """"physical" or "slicersim-1.0" (fixed at construction: build a new Simulation to change it)."""
        return self._conventions

    @property
    def instrumental_sigma(self):
        """Spectrograph aberration blur σ along the slice [cells] under this simulation's conventions."""
        spec = self.spectrograph
        return instrumental_blur_sigma(spec.dispersion_resolution, spec.anamorphosis, self._conventions)

    def _state_parts(self):
        return (self.scene, self.telescope, self.spectrograph, self.detector)

    # ------------------------------------------------------------------ updates
    @property
    def mutable_parameters(self):
        """Every name :meth:`update` accepts: the simulation's own, then the detector's,
        the spectrograph's and the telescope's (routed in that order)."""
        names = list(self.own_parameters)
        for comp in (self.detector, self.spectrograph, self.telescope):
            names += [n for n in comp.mutable_parameters if n not in names]
        return tuple(names)

    def update(self, _position=None, **kwargs):
        """Change any mutable parameter of the simulation or its components (see
        ``mutable_parameters``), atomically: the new components are built and validated
        off to the side first; on any error (:class:`~slicersim.errors.ParameterError`, ReadoutError)
        nothing changes.  Caches follow automatically (version keyed).

        The extraction aperture is validated for the new state: a point source outside the
        field or an aperture containing no cell centre raises ParameterError.

        Parameters
        ----------
        _position : tuple of float, optional
            Internal, used by targets: validates the aperture for a point-source position
            [cells] about to be set.
        **kwargs
            The parameters to change (names of ``mutable_parameters``).

        Returns
        -------
        None
            The simulation is changed in place.
        """
        self.apply_update(self.plan_update(_position, **kwargs))

    def plan_update(self, _position=None, **kwargs):
        """The validated new state of :meth:`update`, nothing changed: targets validate their
        own parts against it before :meth:`apply_update`.

        Parameters
        ----------
        _position : tuple of float, optional
            As :meth:`update`.
        **kwargs
            As :meth:`update`.

        Returns
        -------
        SimulationUpdate
            The new state, for :meth:`apply_update`.
        """
        check_parameter_names("simulation", kwargs, self.mutable_parameters)
        groups = {"detector": {}, "spectrograph": {}, "telescope": {}}
        own = {}
        for key, val in kwargs.items():
            if key in self.own_parameters:
                own[key] = val
            else:
                name = next(n for n in groups if key in getattr(self, n).mutable_parameters)
                groups[name][key] = val
        new = {name: getattr(self, name).updated(**params) for name, params in groups.items() if params}
        det = new.get("detector", self.detector)
        nramps = _check_nramps(own["nramps"]) if "nramps" in own else self.nramps
        _, nramps = check_readout(det.nmd, nramps, det.min_group, det.max_group)
        aperture = _check_aperture(own.get("aperture_radius_insigma", self.aperture_radius_insigma))
        spec = new.get("spectrograph", self.spectrograph)
        self._check_overlap(spec.lbda)
        self._check_aperture_cells(spec, new.get("telescope", self.telescope), aperture,
                                   self.position if _position is None else _position)
        return SimulationUpdate(self, new, nramps, aperture)

    def apply_update(self, plan):
        """Apply a :meth:`plan_update` result of this simulation (nothing here can fail).

        Parameters
        ----------
        plan : object
            The validated new state (a ``SimulationUpdate``).

        Returns
        -------
        None
            The simulation is changed in place.
        """
        if plan.simulation is not self:
            raise ParameterError("plan: this update was planned for another simulation (apply_update takes the "
                                 "plan_update result of the same simulation)")
        for name, obj in plan.components.items():
            getattr(self, name)._adopt(obj)
        self.nramps, self.aperture_radius_insigma = plan.nramps, plan.aperture_radius_insigma
        self._cache.clear()

    def _check_overlap(self, lbda=None):
        ps = self.scene.pointsource
        lbda = self.lbda if lbda is None else lbda
        lo, hi = lbda[0], lbda[-1]
        if ps is not None and not ps.overlap(lo, hi):
            raise SpectrumError(f"point-source spectrum ({ps.lbda_in[0]:g}–{ps.lbda_in[-1]:g} Å) does "
                                f"not overlap the instrument range ({lo:.0f}–{hi:.0f} Å)")

    def _check_aperture_cells(self, spec, telescope, aperture_insigma, position):
        """ParameterError unless ``position`` [cells] is inside the field and the extraction
        aperture (``aperture_insigma`` σ_ref / s) contains at least one cell centre."""
        if self.scene.pointsource is None:
            return
        radius = aperture_insigma * telescope.psf_sigma_ref / spec.spatial_scale
        aperture_cells(spec.shape, position, radius)

    def _cached(self, key, func):
        token = state_token(self)
        if token != self._cache_token:
            self._cache.clear()
            object.__setattr__(self, "_cache_token", token)
        if key not in self._cache:
            self._cache[key] = func()
        return self._cache[key]

    # ------------------------------------------------------------------ spectral terms
    @property
    def lbda(self):
        """Bin centres [Å]."""
        return self.spectrograph.lbda

    @property
    def qe(self):
        """Detector QE at the bin centres [e-/ph]."""
        return self._cached("qe", lambda: self.detector.get_qe(self.lbda))

    @property
    def flambda_to_photon(self):
        """f2p = A_tel[cm²] T(λ) Δλ λ / hc: photons/s per erg/s/cm²/Å in each bin."""
        def f2p():
            area_cm2 = self.telescope.area * 1e4
            return area_cm2 * self.spectrograph.throughput * self.spectrograph.dlbda * self.lbda / HC_ERG_AA
        return self._cached("f2p", f2p)

    @property
    def pointsource_flambda(self):
        """F(λ) of the point source [erg/s/cm²/Å] (NaN outside its input range)."""
        ps = self.scene.pointsource
        return self._cached("ps_flambda", lambda: np.zeros_like(self.lbda) if ps is None
                            else ps.flambda(self.lbda))

    @property
    def background_photons(self):
        """Background photons per cell B(λ) f2p s² [ph/s/cell] (before LSF)."""
        bkg = self.scene.background
        return self._cached("bkg_ph", lambda: np.zeros_like(self.lbda) if bkg is None else
                            bkg.flambda(self.lbda) * self.flambda_to_photon * self.spectrograph.spatial_scale**2)

    def _thermal_photons(self, which):
        """Dispersed thermal photons per cell A_tel Ω Δλ B(λ̄) [ph/s/cell] (no throughput)."""
        edges = self.spectrograph.lbda_edges
        lbda_mid = 0.5 * (edges[1:] + edges[:-1])
        radiance = (self.telescope.thermal_radiance(lbda_mid) if which == "telescope"
                    else self.spectrograph.dispersed_thermal_radiance(lbda_mid))
        return self.telescope.area * self.spectrograph.cell_solid_angle * self.spectrograph.dlbda * radiance

    def thermal_photons_of(self, which):
        """Thermal photons per cell [ph/s/cell] (before LSF).

        Parameters
        ----------
        which : {"telescope", "optics"}
            "telescope" (mirrors) or "optics" (the dispersed internal optics).

        Returns
        -------
        numpy.ndarray of shape (nλ,)
            The thermal photons [ph/s/cell].
        """
        return self._thermal_photons(validation.choice("which", which, ("telescope", "optics")))

    @property
    def thermal_photons(self):
        """Telescope + dispersed optics thermal photons per cell [ph/s/cell] (before LSF)."""
        return self._cached("th_ph", lambda: self._thermal_photons("telescope")
                            + self._thermal_photons("optics"))

    def uniform_photons(self, switch_off=None):
        """(background, thermal) photons per cell, before the LSF, with the terms ``switch_off``
        removes set to 0 (rule: ``slicersim.products.components``).

        Parameters
        ----------
        switch_off : str or sequence of str, optional
            Components left out.

        Returns
        -------
        background, thermal : numpy.ndarray of shape (nλ,)
            Photons per cell [ph/s/cell].
        """
        on = uniform_terms_on(as_switched_off(switch_off))
        zero = np.zeros_like(self.lbda)
        background = self.background_photons if "background" in on else zero
        if "thermal_telescope" in on and "thermal_optics" in on:
            return background, self.thermal_photons
        thermal = zero
        for which in ("telescope", "optics"):
            if f"thermal_{which}" in on:
                thermal = thermal + self._thermal_photons(which)
        return background, thermal

    @property
    def thermal_dark(self):
        """Undispersed optics emission reaching each pixel [e-/s/px]."""
        def dth():
            rows = self.spectrograph.undispersed_optics()
            lrange = self.detector.thermal_dark_range or (self.lbda[0], self.lbda[-1])
            if not rows:
                return 0.0
            qe_nodes = self.detector._qe_table[0] if self.detector._qe_table is not None else None
            return thermal_dark_rate(*zip(*rows), self.detector.pixel_area, self.detector.get_qe, lrange,
                                     breakpoints=qe_nodes)
        return self._cached("thermal_dark", dth)

    # ------------------------------------------------------------------ PSF
    @property
    def psf_sigmas(self):
        """Gaussian PSF (σ_y, σ_x) [cells] per bin."""
        spec = self.spectrograph
        return self._cached("psf_sig", lambda: gaussian_psf_sigmas(
            self.lbda, self.telescope.psf_sigma_ref, spec.spatial_scale,
            self.telescope.guiding_sigma, self.instrumental_sigma))

    @property
    def position(self):
        ps = self.scene.pointsource
        return (0.0, 0.0) if ps is None else ps.position

    @property
    def aperture_radius(self):
        """Extraction radius [cells] = aperture_radius_insigma σ_ref / s."""
        return self.aperture_radius_insigma * self.telescope.psf_sigma_ref / self.spectrograph.spatial_scale

    @property
    def aperture(self):
        """(iy, ix) of the cells used by the extraction."""
        return self._cached("aperture", lambda: aperture_cells(self.spectrograph.shape, self.position,
                                                               self.aperture_radius))

    def get_psf(self):
        """PSF cube P[λ, y, x] (fraction of the point-source flux per cell).

        Returns
        -------
        numpy.ndarray of shape (nλ, ny, nx)
            The PSF cube.
        """
        sig_y, sig_x = self.psf_sigmas
        return gaussian_psf_fractions(sig_y, sig_x, self.spectrograph.shape, self.position)

    # ------------------------------------------------------------------ cubes
    def get_projected_scene(self, switch_off=None, psf_profile="gaussian", backend="auto"):
        """Photon cube C[λ, y, x] = LSF[F f2p P] + LSF[host] + LSF[B f2p s² + N_th] [ph/s/cell]:
        the sum of the scene components (:meth:`get_scene_cubes`) left on by ``switch_off``.

        Parameters
        ----------
        switch_off : str or sequence of str, optional
            Components left out, as :meth:`get_cube`.
        psf_profile : {"gaussian", "airy"}, optional
            The PSF profile.
        backend : str, optional
            "auto", "opencl" or "numpy".

        Returns
        -------
        numpy.ndarray of shape (nλ, ny, nx)
            The photon cube [ph/s/cell].
        """
        rates = scene_photon_rates(self, check_switch_off(switch_off), psf_profile, backend)
        cube = np.broadcast_to((rates["background"] + rates["thermal"])[:, None, None],
                               (self.lbda.size, *self.spectrograph.shape)).copy()
        for name in ("pointsource", "host"):
            if rates[name] is not None:
                cube += rates[name]
        return cube

    def get_scene_cubes(self, unit="adu", nmd=None, nramps=None, per_ramp=False, psf_profile="gaussian",
                        switch_off=None, backend="auto", as_dict=True):
        """Noise-free cube (nλ, ny, nx) of each scene component.

        In ADU their sum is the signal of :meth:`get_cube` (same readout, PSF and
        ``switch_off``), to rounding, where no cell saturates (the cube is NaN there).

        Parameters
        ----------
        unit : str, optional
            ``"adu"`` (signal: × QE t_int g, × nramps unless ``per_ramp``), ``"electron"``
            [e-/s/cell], ``"photon"`` [ph/s/cell] or ``"flambda"`` (÷ f2p: erg/s/cm²/Å per cell);
            1.4.2's ``"default"``, ``"ph"``, ``"photons"`` are accepted.
        nmd : tuple of int, optional
            Readout (n, m, d) (default: the detector's).
        nramps : int, optional
            Number of ramps (default: the simulation's).
        per_ramp : bool, optional
            ADU of one ramp (else all ramps).
        psf_profile : {"gaussian", "airy"}, optional
            The PSF.
        switch_off : str or sequence of str, optional
            As :meth:`get_cube`.
        backend : str, optional
            "auto", "opencl" or "numpy".
        as_dict : bool, optional
            False: one (4, nλ, ny, nx) array in the order below (1.4.2).

        Returns
        -------
        SceneCubes or numpy.ndarray
            Dict ``pointsource``, ``background``, ``host``, ``thermal`` (absent or switched-off
            components are zeros; 1.4.2's keys ``host_cube`` / ``thermal_cube`` read the same
            arrays, ``slicersim.products.cube.SceneCubes``), each of shape (nλ, ny, nx) [``unit``].
        """
        validation.flag("as_dict", as_dict)
        cubes = build_scene_cubes(self, unit=unit, nmd=nmd, nramps=nramps, per_ramp=per_ramp,
                                  psf_profile=psf_profile, switch_off=switch_off, backend=backend)
        return cubes if as_dict else cubes.stack()

    def get_cube(self, nmd=None, nramps=None, seed=None, psf_profile="gaussian", backend="auto",
                 switch_off=None, **options):
        """Signal [ADU] and variance [ADU²] cubes summed over the ramps, plus a noisy
        realisation when ``seed`` (an int in [0, 2⁶⁴)) is given: a ``CubeTuple``
        whose ``.seed`` records it.  ``seed=None`` (default) gives the noiseless pair only
        (the seed is the noise switch of cubes); a numpy Generator is deprecated (an integer seed
        is drawn from it, with a DeprecationWarning, and recorded in ``.seed``).

        Parameters
        ----------
        nmd : tuple of int, optional
            Readout (n, m, d) (default: the detector's).
        nramps : int, optional
            Number of ramps (default: the simulation's).
        seed : int, optional
            Integer in [0, 2⁶⁴) of the noisy realisation; None: noiseless pair only.
        psf_profile : {"gaussian", "airy"}, optional
            The PSF (``"gaussian"``, reference default).
        backend : str, optional
            "auto", "opencl" or "numpy".
        switch_off : str or sequence of str, optional
            A name or names of ``VARIANCE_SOURCES``, or ``"effective_dark"``: removes scene
            components from the signal and variance and detector terms from the variance
            (``slicersim.products.components``).
        **options
            Options of the cube builder (``max_bytes``, ``progress``, ``psf_options``,
            ``precision``, ``dtype``, ...), see Notes.

        Returns
        -------
        CubeTuple
            (signal, variance) of shape (nλ, ny, nx) [ADU, ADU²], then the noisy cube [ADU]
            when ``seed`` is given; ``.seed`` records the seed.

        Notes
        -----
        Noise: ``noisy = signal + √variance · z`` with z the Philox/Box–Muller normal keyed
        by (seed, flat voxel index, stream 0), ``slicersim.backends.noise.noisy_cube``.
        For the same signal and variance the NumPy twin and the OpenCL kernel give
        bit-identical noisy cubes (same Philox words, same correctly rounded √, no FMA
        contraction).  Between ``backend="numpy"`` and ``"opencl"`` the *expectation and
        variance* cubes themselves may differ by a few ulp (different summation order of the
        PSF/LSF contractions), so noisy cubes agree to
        abs(Δ) ≤ 1e-13 · (abs(signal) + √variance) per voxel, not bit for bit.

        See ``slicersim.products.cube.build_cube`` for the chunked OpenCL builder, the
        computation path of each scene component and the options
        (``max_bytes``, ``progress``, ``psf_options``, ``precision``: "auto", "double" or
        "single" kernels, ``slicersim.backends.precision``).
        """
        seed = validation.seed(seed)
        for key in options:
            validation.choice("keyword", key, ("max_bytes", "progress", "psf_options", "dtype", "precision", "seed",
                                               "nmd", "nramps", "psf_profile", "backend", "switch_off"),
                              what="keyword of get_cube")
        return CubeTuple(build_cube(self, nmd, nramps, psf_profile=psf_profile, seed=seed, backend=backend,
                                    switch_off=switch_off, **options), seed)

    def show_cube(self, lbda=None, seed=None, ax=None, savefile=None):
        """Figure of the cube [ADU, all ramps] at a few wavelengths: the signal cube, or a noisy
        one drawn with ``seed``; see :func:`slicersim.plotting.images.plot_cube_slices`.

        Parameters
        ----------
        lbda : array_like, optional
            Wavelengths of the panels [Å] (default: four spread over the grid).
        seed : int, optional
            Seed of a noisy cube (None: the signal cube).
        ax : sequence of matplotlib.axes.Axes, optional
            None (new figure) or one Axes per wavelength.
        savefile : str, os.PathLike or file object, optional
            If given the figure is saved there.

        Returns
        -------
        matplotlib.figure.Figure
            The figure.
        """
        from slicersim.plotting import plot_cube_slices
        signal, _, *noisy = self.get_cube(seed=seed)
        return plot_cube_slices(self, noisy[0] if noisy else signal, lbda=lbda, ax=ax, savefile=savefile)


def _check_aperture(value):
    """aperture_radius_insigma: a finite number > 0 [σ_ref / cell]."""
    return validation.number("aperture_radius_insigma", value, low=0.0, low_open=True)


#: nramps as an int ≥ 1 (kept for targets/detector.py; use :func:`slicersim.validation.nramps`)
_check_nramps = validation.nramps
