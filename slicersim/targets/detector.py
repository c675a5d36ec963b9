"""Detector products of a target: both Lazuli fields projected on the H4RG, and raw ramps.

The two Lazuli fields look at neighbouring patches of sky (slicersim 1.4.2's layout,
``VirtualLazuliTarget._get_field_positions``): the narrow field (58 × 116 cells of 0.04″,
2.32″ × 4.64″) sits above the wide field (58 × 116 cells of 0.08″, 4.64″ × 9.28″), their
long sides parallel, with a gap of :data:`FIELD_GAP_ARCSEC`.  In sky coordinates (x along the
slices, y across them, arcsec) the narrow field's centre is therefore at
(0, h_wide/2 + gap + h_narrow/2) = (0, 3.54″) from the wide field's centre
(:func:`field_offset`).  A target's scene is simulated in its own field; for the detector
image the other field sees the same sky: the host and the point source (never inside both
fields: only its PSF wings can cross the gap) at positions converted between the fields, plus
that field's background and thermal light.
"""
from __future__ import annotations

import copy
import math

import numpy as np

from slicersim import validation
from slicersim.assembly import build_simulation, default_mapper
from slicersim.backends.precision import resolve_precision
from slicersim.physics.readout import check_readout

__all__ = ["FIELD_GAP_ARCSEC", "field_offset", "DetectorProducts"]

#: gap between the narrow and the wide field on the sky [arcsec] (slicersim 1.4.2's ``hspace``)
FIELD_GAP_ARCSEC = 0.06
#: a point source farther than this many PSF σ from the other field is left out of it (no light)
PSF_REACH_SIGMA = 10.0


def field_offset(narrow_sim, wide_sim):
    """(dx, dy) [arcsec]: centre of the narrow field minus centre of the wide field on the sky."""
    h_narrow = narrow_sim.spectrograph.shape[0] * narrow_sim.spectrograph.spatial_scale
    h_wide = wide_sim.spectrograph.shape[0] * wide_sim.spectrograph.spatial_scale
    return 0.0, h_wide / 2 + FIELD_GAP_ARCSEC + h_narrow / 2


class DetectorProducts:
    """Mixin of :class:`~slicersim.targets.base.Target`: detector image and raw ramps."""

    def _other_field_simulation(self, field):
        """The simulation of the other Lazuli field seeing the same sky: host and point source at
        positions converted between the fields (the point source lies outside that field: only
        its PSF wings can reach it, so it is left out beyond :data:`PSF_REACH_SIGMA` σ)."""
        own = self.simulation
        sim = build_simulation(self.config, field, pointsource=None, conventions=self._conventions)
        narrow, wide = (own, sim) if field == "wide" else (sim, own)
        dx, dy = field_offset(narrow, wide)
        sign = 1.0 if field == "wide" else -1.0          # narrow → wide coordinates: + offset
        scale = sim.spectrograph.spatial_scale
        ps = own.scene.pointsource
        if ps is not None:             # outside that field: only its PSF wings can reach it
            x = (ps.position[0] * own.spectrograph.spatial_scale + sign * dx) / scale
            y = (ps.position[1] * own.spectrograph.spatial_scale + sign * dy) / scale
            ny, nx = sim.spectrograph.shape
            gap = math.hypot(max(abs(x) - nx / 2, 0.0), max(abs(y) - ny / 2, 0.0))      # [cells]
            if gap < PSF_REACH_SIGMA * max(float(np.max(s)) for s in sim.psf_sigmas):
                moved = copy.copy(ps)
                moved.position = (x, y)
                sim.scene.pointsource = moved
        host = own.scene.host
        if host is not None:
            from slicersim.sources.galaxies import host_offset, own_copy
            moved = own_copy(host)
            hx, hy = host_offset(host)
            centre = (hx + sign * dx, hy + sign * dy)
            if moved is host:                          # a user object (not Host / CubeSource): left out
                moved = None
            elif hasattr(moved, "profile"):
                moved.profile.offset = centre
            else:
                moved.centre = centre
            sim.scene.host = moved
        return sim

    def get_field_rate_cubes(self):
        """Photo-electron rate cubes [e-/s per cell per bin] of both Lazuli fields: the target's
        field holds its scene; the other field the same sky (host and point source at positions
        converted between the fields, ``field_offset``) with its own background and thermal
        light.  A target without field is taken to be in the narrow one.

        Returns
        -------
        dict
            {field: (cube, simulation)} for "narrow" and "wide", each cube of shape
            (nλ, ny, nx) [e-/s per cell per bin].
        """
        cubes = {}
        for field in ("narrow", "wide"):
            sim = self.simulation if field == (self.field or "narrow") else self._other_field_simulation(field)
            cubes[field] = (sim.get_projected_scene() * sim.qe[:, None, None], sim)
        return cubes

    def get_detector_image(self, mapper=None, backend="auto", precision="auto"):
        """Photo-electron rate on the H4RG [e-/s/px] (both fields, flux-conserving projection).

        Dark current, thermal dark and ROIC glow are not included: :meth:`get_ramps`
        adds them to every pixel.

        Parameters
        ----------
        mapper : SlicerMapper, optional
            The detector mapping (default: the built-in one).
        backend : str, optional
            "auto", "opencl" or "numpy".
        precision : {"auto", "double", "single"}, optional
            Checked first: of the projection's deposit (``slicersim.backends.projection.deposit``;
            single: ≤ 1e-5 of the image peak against double); the scene cubes keep their own
            default.

        Returns
        -------
        numpy.ndarray of shape (rows, cols)
            The rate image [e-/s/px].
        """
        precision = resolve_precision(precision, backend, "projection")[1]
        mapper = default_mapper() if mapper is None else mapper
        cubes = self.get_field_rate_cubes()
        image = np.zeros(mapper.detector_shape)
        for field, (cube, sim) in cubes.items():
            mapper.project_fields(sim.lbda, sim.spectrograph.lbda_edges, out=image, backend=backend,
                                  precision=precision, **{field: cube})
        return image

    def get_ramps(self, out=None, nmd=None, nramps=None, seed=None, mapper=None, backend="auto", **kwargs):
        """Raw MACC ramps of the full detector (see :func:`slicersim.products.ramps.simulate`).

        The detector parameters (dark, thermal dark, ROIC glow, read noise, gain, frame time,
        saturation) come from the configuration.

        Parameters
        ----------
        out : str or path-like, optional
            Output file (HDF5 or level-1b FITS); None: SCI in memory.
        nmd : tuple of int, optional
            Readout (n, m, d); the current readout unless given (validated first).
        nramps : int, optional
            Number of ramps: an integer ≥ 1 (ReadoutError otherwise); the current one unless given.
        seed : int, optional
            An integer in [0, 2⁶⁴) or None (default: a fresh seed, recorded in the file's SEED
            attribute).
        mapper : SlicerMapper, optional
            The detector mapping (default: the built-in one).
        backend : str, optional
            "auto", "opencl" or "numpy".
        **kwargs
            Further keywords of the keyword form of :func:`~slicersim.products.ramps.simulate`
            (they override the configuration's detector parameters), and ``target_meta``: further
            attributes of the target's truth (e.g. a campaign's catalog row: phase, peak_absmag, x1,
            c, source).  A file gets the target's truth, ``truth/target`` (redshift, phase,
            position, input F_λ and expected rate [e-/s per bin]: ``slicersim.targets.truth.target_truth``).

        Returns
        -------
        numpy.ndarray or str
            SCI of shape (nramps, ngroups, rows, cols) [ADU], or the path of ``out`` written.
        """
        from slicersim.products.ramps import simulate
        seed = validation.seed(seed)                 # checked before the (slow) detector image
        sim, det = self.simulation, self.simulation.detector
        nmd = det.nmd if nmd is None else nmd
        nramps = sim.nramps if nramps is None else validation.nramps(nramps)
        nmd, nramps = check_readout(nmd, nramps, det.min_group, det.max_group)
        if "precision" in kwargs:                    # the samplers' precision: refused before the image is built
            from slicersim.backends.precision import resolve_precision
            resolve_precision(kwargs["precision"], backend, "ramp")
        mapper = default_mapper() if mapper is None else mapper
        image = self.get_detector_image(mapper, backend=backend)
        release = getattr(mapper, "release_tables", None)
        if release is not None:         # tables kept in memory (no disk cache): not needed by the ramp
            release()
        _return_free_memory()
        params = dict(tframe=det.tframe, ron=det.ron, dark=det.dark, thermal_dark=sim.thermal_dark,
                      roic_glow=det.roic_glow, gain=det.gain,
                      saturation=min(det.saturation, 65535.0), backend=backend,
                      config={"config": _recorded_config(self.config), "field": self.field,
                              "conventions": sim.conventions, "psf_profile": "gaussian"})
        meta = kwargs.pop("target_meta", None) or {}
        params.update(kwargs)
        if out is not None:
            from slicersim.targets.truth import target_truth
            params["target"] = target_truth(self, nmd, nramps, **meta)
        return simulate(image, nmd, nramps, seed=seed, out=out, **params)

    # -- figures (thin calls of slicersim.plotting) -----------------------------
    def show_spectrum(self, ax=None, seed=None, savefile=None):
        """Figure of the extracted spectrum [ADU] with its ±1σ band and its SNR per bin (the ETC band
        shaded); see :func:`slicersim.plotting.spectra.plot_spectrum`.

        Parameters
        ----------
        ax : matplotlib.axes.Axes or sequence of matplotlib.axes.Axes, optional
            None (new figure), a pair of Axes (spectrum, SNR) or a single Axes.
        seed : int, optional
            If given, a noisy realisation is drawn as points.
        savefile : str, os.PathLike or file object, optional
            If given the figure is saved there.

        Returns
        -------
        matplotlib.figure.Figure
            The figure.
        """
        from slicersim.plotting import plot_spectrum
        return plot_spectrum(self, ax=ax, seed=seed, savefile=savefile)

    def show_variance_contribution(self, ax=None, savefile=None):
        """Figure of the variance budget: each source's contribution [ADU²] and fraction of the
        total versus λ (the paper's figure); see :func:`slicersim.plotting.spectra.plot_variance_budget`.

        Parameters
        ----------
        ax : sequence of matplotlib.axes.Axes, optional
            None (new figure) or a pair of Axes (variance, fraction).
        savefile : str, os.PathLike or file object, optional
            If given the figure is saved there.

        Returns
        -------
        matplotlib.figure.Figure
            The figure.
        """
        from slicersim.plotting import plot_variance_budget
        return plot_variance_budget(self, ax=ax, savefile=savefile)

    def show_cube(self, lbda=None, seed=None, ax=None, savefile=None):
        """Figure of the target's cube at a few wavelengths (:meth:`Simulation.show_cube
        <slicersim.Simulation.show_cube>`).

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
        return self.simulation.show_cube(lbda=lbda, seed=seed, ax=ax, savefile=savefile)


def _recorded_config(config):
    """The configuration as the ramp file records it (CONFIG): built-in names as they are, TOML paths
    absolute (so that the reduction finds them from any directory); a list stays a list."""
    import os
    items = config if isinstance(config, (list, tuple)) else [config]
    out = [c if isinstance(c, str) and c in ("cbe", "eol") else os.path.abspath(os.fspath(c)) for c in items]
    return out if isinstance(config, (list, tuple)) else out[0]


def _return_free_memory():
    """Give the heap's free pages back to the OS (glibc ``malloc_trim``; a no-op elsewhere).

    Building and depositing projection tables leaves ~0.4 GB of freed but fragmented heap
    that the process would otherwise keep resident while the ramp runs."""
    import ctypes
    import ctypes.util
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        trim = libc.malloc_trim
    except (OSError, AttributeError):
        return
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    trim(0)
