"""High-level targets: build a Lazuli (or any configured) simulation around a source.

``LazuliSupernova(redshift=1).setup_to_snr(20)`` is an exposure-time
calculation in one line; :func:`lazuli_etc` / :func:`lazuli_sn_etc` return the
result as a dict.
"""
from __future__ import annotations

import math

import numpy as np

from slicersim.assembly import LAZULI_FIELDS, build_simulation, check_field, default_mapper  # noqa: F401
from slicersim.errors import ETCError
from slicersim.physics.readout import check_readout
from slicersim.sources.scene import PointSource, snia_spectrum

__all__ = ["LAZULI_FIELDS", "build_simulation", "Target", "Supernova", "BlackBody", "LazuliTarget",
           "LazuliSupernova", "LazuliBlackBody", "lazuli_etc", "lazuli_sn_etc"]

class Target:
    """A point source observed with a configured instrument.

    Parameters
    ----------
    lbda, flux : input spectrum [Å], [erg/s/cm²/Å]
    mag, band : optional renormalisation to an AB magnitude in an sncosmo band
    config : "cbe", "eol", a TOML path or a list of them
    field : "narrow", "wide" (Lazuli) or None
    position : (x, y) [cells] relative to the field centre
    """

    default_config, default_field = "cbe", None

    def __init__(self, lbda, flux, mag=None, band="bessellb", config=None, field="default",
                 position=(0.0, 0.0), redshift=None):
        self.redshift = redshift
        self._source_args = dict(lbda=lbda, flux=flux, mag=mag, band=band, position=position)
        self.pointsource = PointSource(lbda, flux, position=position, mag=mag, band=band)
        self.config = self.default_config if config is None else config
        self.field = self.default_field if field == "default" else check_field(field)
        self._build()

    def _build(self, keep_readout=False):
        old = (self.simulation.detector.nmd, self.simulation.nramps) if keep_readout else None
        self.simulation = build_simulation(self.config, self.field, self.pointsource)
        if old:
            self.simulation.update(nmd=old[0], nramps=old[1])

    # ------------------------------------------------------------------ changes
    def change_configuration(self, config):
        """Switch to another configuration (``"cbe"``, ``"eol"``, TOML path(s)); keeps the readout."""
        old = self.config, self.simulation
        self.config = config
        try:
            self._build(keep_readout=True)
        except Exception:       # a refused configuration leaves the old one in place
            self.config, self.simulation = old
            raise

    def change_field(self, field):
        self.field = check_field(field)
        self._build(keep_readout=True)

    def change_spectrograph(self, field=None, **kwargs):
        """Change the field (Lazuli) and/or spectrograph parameters."""
        if field is not None:
            self.change_field(field)
        if kwargs:
            self.simulation.update(**kwargs)

    def change_detector(self, nmd=None, nramps=None, max_group=None, **kwargs):
        """Set the readout (n, m, d), number of ramps, max_group or other detector parameters."""
        params = dict(kwargs)
        if max_group is not None:
            params["max_group"] = int(max_group)
        if nmd is not None:
            check_readout(nmd, nramps or self.simulation.nramps, self.simulation.detector.min_group,
                          params.get("max_group", self.simulation.detector.max_group))
            params["nmd"] = tuple(int(v) for v in nmd)
        if nramps is not None:
            params["nramps"] = nramps
        self.simulation.update(**params)

    # ------------------------------------------------------------------ ETC
    def _band(self, lbda_range, frame):
        if lbda_range is None:
            lbda_range = (4000.0, 6800.0)
        lo, hi = (float(v) for v in lbda_range)
        if not hi > lo:
            raise ETCError(f"lbda_range must be (lo, hi) with lo < hi, got {lbda_range}")
        if frame == "rest":
            if self.redshift is None:
                raise ETCError("frame='rest' needs a target redshift")
            return lo * (1 + self.redshift), hi * (1 + self.redshift)
        if frame != "obs":
            raise ETCError(f"frame must be 'obs' or 'rest', got {frame!r}")
        return lo, hi

    def setup_to_snr(self, snr, lbda_range=None, frame="obs", search="exact", per_resolution=True,
                     backend="auto"):
        """Find and apply the readout reaching ``snr`` (per resolution element by default)
        in ``lbda_range``; returns the ETC result dict."""
        band = self._band(lbda_range, frame)
        result = self.simulation.fetch_snr(snr, band, per_resolution=per_resolution, search=search,
                                           backend=backend)
        self.simulation.update(nmd=result["nmd"], nramps=result["nramps"])
        result["lbda_range_obs"] = band
        self.last_etc = result
        return result

    def get_readout_config(self):
        return {"nmd": tuple(self.simulation.detector.nmd), "nramps": self.simulation.nramps}

    def get_exposure_time(self):
        """Total exposure time of all ramps [s]."""
        return self.simulation.get_times()["total_exposure_time"]

    def get_times(self):
        return self.simulation.get_times()

    def get_data_volume(self):
        return self.simulation.get_data_volume()

    def get_band_snr(self, lbda_range=None, frame="obs", per_resolution=False):
        return self.simulation.get_band_snr(self._band(lbda_range, frame), per_resolution=per_resolution)

    def get_spectrum(self, incl_error=False, seed=None):
        """(λ [Å], signal [ADU], variance [ADU²]); ``incl_error`` adds a Gaussian noise draw."""
        lbda, signal, variance = self.simulation.get_spectrum()
        if incl_error:
            rng = np.random.default_rng(seed)
            signal = signal + rng.standard_normal(signal.shape) * np.sqrt(variance)
        return lbda, signal, variance

    def get_cube(self, seed=None):
        return self.simulation.get_cube(seed=seed)

    # ------------------------------------------------------------------ detector
    def get_field_rate_cubes(self):
        """Photo-electron rate cubes [e-/s per cell per bin] of both Lazuli fields:
        the target's field holds the scene, the other field background and thermal light only."""
        cubes = {}
        for field in ("narrow", "wide"):
            sim = self.simulation if field == (self.field or "narrow") else \
                build_simulation(self.config, field, pointsource=None)
            cubes[field] = (sim.get_projected_scene() * sim.qe[:, None, None], sim)
        return cubes

    def get_detector_image(self, mapper=None, backend="auto"):
        """Photo-electron rate on the H4RG [e-/s/px] (both fields, flux-conserving projection).

        Dark current, thermal dark and ROIC glow are not included: :meth:`get_ramps`
        adds them to every pixel."""
        mapper = default_mapper() if mapper is None else mapper
        cubes = self.get_field_rate_cubes()
        image = np.zeros(mapper.detector_shape)
        for field, (cube, sim) in cubes.items():
            kwargs = {"narrow": cube} if field == "narrow" else {"wide": cube}
            mapper.project_fields(sim.lbda, sim.spectrograph.lbda_edges, out=image, backend=backend,
                                  **kwargs)
        return image

    def get_ramps(self, out=None, nmd=None, nramps=None, seed=0, mapper=None, backend="auto", **kwargs):
        """Raw MACC ramps of the full detector (see :func:`slicersim.ramps.simulate`).

        Uses the current readout unless ``nmd`` / ``nramps`` are given; the detector
        parameters (dark, thermal dark, ROIC glow, read noise, gain, frame time,
        saturation) come from the configuration.  Returns SCI or writes ``out`` (HDF5)."""
        from slicersim.products.ramps import simulate
        sim, det = self.simulation, self.simulation.detector
        check_readout(nmd or det.nmd, nramps or sim.nramps, det.min_group, det.max_group)
        image = self.get_detector_image(mapper, backend=backend)
        params = dict(tframe=det.tframe, ron=det.ron, dark=det.dark, thermal_dark=sim.thermal_dark,
                      roic_glow=det.roic_glow, gain=det.gain,
                      saturation=min(det.saturation, 65535.0), backend=backend,
                      config={"config": str(self.config), "field": self.field})
        params.update(kwargs)
        return simulate(image, nmd or det.nmd, nramps or sim.nramps, seed=seed, out=out, **params)

    def get_variance_contribution(self):
        return self.simulation.get_variance_contribution()

    def get_band_variance_contribution(self, lbda_range=None, frame="obs"):
        return self.simulation.get_band_variance_contribution(self._band(lbda_range, frame))


class Supernova(Target):
    """SN Ia at ``redshift`` from sncosmo (default ``hsiao-subsampled``, offline), peak
    absolute magnitude ``peak_absmag`` in Bessell B (AB, Planck18), at ``phase`` days."""

    def __init__(self, redshift, phase=0.0, source="hsiao-subsampled", peak_absmag=-19.3, config=None,
                 field="default", position=(0.0, 0.0), **kwargs):
        lbda, flux = snia_spectrum(redshift, phase, source, peak_absmag, **kwargs)
        super().__init__(lbda, flux, config=config, field=field, position=position, redshift=redshift)
        self.phase, self.source = phase, source

    def setup_to_snr(self, snr, lbda_range=None, frame="rest", **kwargs):
        return super().setup_to_snr(snr, lbda_range, frame, **kwargs)


class BlackBody(Target):
    """Black body of ``temperature`` [K] normalised to ``mag`` (AB) in ``band``."""

    def __init__(self, temperature, mag, band="bessellb", config=None, field="default", position=(0.0, 0.0)):
        src = PointSource.from_blackbody(temperature, mag, band)
        super().__init__(src.lbda_in, src.flux_in, mag=mag, band=band, config=config, field=field,
                         position=position)
        self.temperature = temperature


class _Lazuli:
    default_config, default_field = "cbe", "narrow"


class LazuliTarget(_Lazuli, Target):
    """Target observed with the Lazuli IFS (``config`` "cbe"/"eol", ``field`` "narrow"/"wide")."""


class LazuliSupernova(_Lazuli, Supernova):
    """SN Ia observed with the Lazuli IFS."""


class LazuliBlackBody(_Lazuli, BlackBody):
    """Black body observed with the Lazuli IFS."""


def _result(target, etc):
    sim = target.simulation
    return {"nmd": etc["nmd"], "nramps": etc["nramps"], "exposure_time": etc["exposure_time"],
            "snr": etc["snr_per_resolution"], "snr_per_bin": etc["snr"], "snr_target_per_bin": etc["snr_target"],
            "lbda_range_obs": etc["lbda_range_obs"], "data_volume": sim.get_data_volume(),
            "config": target.config, "field": target.field, "target": target}


def lazuli_etc(lbda, flux, snr=20, mag=None, band="bessellb", lbda_range=(4000, 6800), frame="obs",
               config="cbe", field="narrow", search="exact", redshift=None):
    """Exposure time for any spectrum with the Lazuli IFS; returns a dict
    (nmd, nramps, exposure_time [s], snr per resolution element, data_volume [GB], target)."""
    target = LazuliTarget(lbda, flux, mag=mag, band=band, config=config, field=field, redshift=redshift)
    return _result(target, target.setup_to_snr(snr, lbda_range, frame, search=search))


def lazuli_sn_etc(redshift, snr=20, lbda_range=(4000, 6800), frame="rest", config="cbe", field="narrow",
                  search="exact", phase=0.0, source="hsiao-subsampled"):
    """Exposure time for a SN Ia at ``redshift`` (band in the rest frame by default)."""
    target = LazuliSupernova(redshift, phase=phase, source=source, config=config, field=field)
    return _result(target, target.setup_to_snr(snr, lbda_range, frame, search=search))
