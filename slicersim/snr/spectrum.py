"""The noise model of a simulation, as a mixin of :class:`slicersim.simulation.Simulation`:
readout times and data volume, the per-cell variance of the detector terms, the optimally
extracted spectrum and its band SNR, the per-source variance contributions and the readout
search for an SNR goal (``fetch_snr``).

:class:`SpectrumSNRMixin` holds these methods; it reads the model through the attributes a
``Simulation`` has (``detector``, ``spectrograph``, ``scene``, ``lbda``, ``nramps``, ``redshift``,
the cached photon rates and ``_cached``), so nothing here imports the simulation.  The band
helpers :data:`FRAMES`, :func:`resolve_frame` and :func:`check_band` are re-exported by
:mod:`slicersim.simulation`, their historical import path.
"""
from __future__ import annotations

import numpy as np

from slicersim import validation
from slicersim.errors import ETCError, SpectrumError
from slicersim.physics.conventions import detector_pixels_per_cell
from slicersim.physics.readout import check_readout, readout_times
from slicersim.products.components import VARIANCE_SOURCES, as_switched_off, check_switch_off
from slicersim.products.cube import host_photons_block
from slicersim.products.extraction import ExtractionModel
from slicersim.products.psf_profiles import get_psf_profile

__all__ = ["SpectrumSNRMixin", "FRAMES", "resolve_frame", "check_band"]

#: the frames a band can be given in (``frame=None``: "rest" when the object knows a redshift, else "obs")
FRAMES = ("rest", "obs", None)


def resolve_frame(frame, redshift):
    """``"rest"`` or ``"obs"``: ``frame`` checked (ParameterError listing the valid values);
    None is "rest" when ``redshift`` is known (not None), else "obs"."""
    frame = validation.choice("frame", frame, FRAMES)
    if frame is None:
        return "obs" if redshift is None else "rest"
    return frame


class SpectrumSNRMixin:
    """Readout, variance, extracted spectrum and band SNR of a :class:`~slicersim.simulation.Simulation`
    (a base class of it, whose page documents these methods)."""

    # ------------------------------------------------------------------ readout
    def _readout(self, nmd=None, nramps=None):
        nmd = self.detector.nmd if nmd is None else nmd
        nramps = self.nramps if nramps is None else validation.nramps(nramps)
        return check_readout(nmd, nramps, self.detector.min_group, self.detector.max_group)

    def get_times(self, nmd=None, nramps=None):
        """Readout times [s] of a readout.

        Parameters
        ----------
        nmd : tuple of int, optional
            Readout (n, m, d) (default: the detector's).
        nramps : int, optional
            Number of ramps (default: the simulation's).

        Returns
        -------
        dict
            ``frame_time``, ``group_time``, ``exposure_time_per_ramp``,
            ``integration_time_per_ramp`` [s] and the totals over the ``nramps`` ramps,
            ``exposure_time`` and ``integration_time`` [s] (plus ``nmd``, ``nramps``,
            ``nframes`` per ramp).
        """
        nmd, nramps = self._readout(nmd, nramps)
        t = readout_times(nmd, self.detector.tframe)
        return {"nmd": nmd, "nramps": nramps, "nframes": t["nframes"], "frame_time": self.detector.tframe,
                "group_time": t["group_time"], "exposure_time_per_ramp": t["exposure_time_per_ramp"],
                "integration_time_per_ramp": t["integration_time_per_ramp"],
                "exposure_time": nramps * t["exposure_time_per_ramp"],
                "integration_time": nramps * t["integration_time_per_ramp"]}

    def get_data_volume(self, nmd=None, nramps=None):
        """Raw group-level data volume [GB] (16 bit per pixel per group, all ramps).

        Parameters
        ----------
        nmd : tuple of int, optional
            Readout (n, m, d) (default: the detector's).
        nramps : int, optional
            Number of ramps (default: the simulation's).

        Returns
        -------
        float
            The data volume [GB].
        """
        nmd, nramps = self._readout(nmd, nramps)
        return self.detector.data_volume(nmd, nramps)

    def effective_dark(self, off=None):
        """Dark + ROIC glow / t_f + thermal dark [e-/s/px], with the sources ``off`` removed.

        Parameters
        ----------
        off : str or sequence of str, optional
            Components switched off (names of ``VARIANCE_SOURCES``).

        Returns
        -------
        float or numpy.ndarray
            The effective dark [e-/s/px].
        """
        det, off = self.detector, as_switched_off(off)
        dark = 0.0 if "dark" in off else det.dark
        glow = 0.0 if "roic_glow" in off else det.roic_glow
        dth = 0.0 if "thermal_dark" in off else self.thermal_dark
        return dark + glow / det.tframe + dth

    def read_noise(self, off=None):
        """Read noise per frame [electron]: the detector's, 0 when ``"ron"`` is switched off.

        Parameters
        ----------
        off : str or sequence of str, optional
            Components switched off (names of ``VARIANCE_SOURCES``).

        Returns
        -------
        float
            The read noise per frame [electron].
        """
        return 0.0 if "ron" in as_switched_off(off) else self.detector.ron

    @property
    def detector_pixels_per_cell(self):
        """Pixels whose read noise, dark and full well a cell carries under this simulation's
        conventions (``slicersim.physics.conventions.detector_pixels_per_cell``)."""
        return detector_pixels_per_cell(self.spectrograph, self._conventions)

    def cell_variance(self, cell_rate, nmd, off=None):
        """Per-cell variance [ADU²] over one ramp for a cell electron rate, with the detector
        terms ``off`` removed; saturated cells get +inf.

        Parameters
        ----------
        cell_rate : numpy.ndarray
            Electron rate per cell [e-/s/cell].
        nmd : tuple of int
            Readout (n, m, d).
        off : str or sequence of str, optional
            Components switched off (names of ``VARIANCE_SOURCES``).

        Returns
        -------
        variance : numpy.ndarray
            The variance [ADU²], of the shape of ``cell_rate`` (+inf where saturated).
        saturated : numpy.ndarray
            bool, the saturated cells.
        """
        det, ppc = self.detector, self.detector_pixels_per_cell
        dark = self.effective_dark(off)
        ron = self.read_noise(off)
        pixel_rate = cell_rate / ppc
        var = ppc * det.pixel_variance(pixel_rate, nmd=nmd, ron=ron, dark=dark, conventions=self.conventions)
        tint = readout_times(nmd, det.tframe)["integration_time_per_ramp"]
        saturated = (pixel_rate + dark) * tint * det.gain > det.saturation
        return np.where(saturated, np.inf, var), saturated

    # ------------------------------------------------------------------ extraction
    @property
    def extraction_model(self):
        """``ExtractionModel`` of the current configuration, Gaussian PSF (cached)."""
        return self.get_extraction_model("gaussian")

    def aperture_psf(self, psf_profile="gaussian", backend="auto"):
        """PSF fractions of the aperture cells of a registered profile
        (``slicersim.products.psf_profiles``: "gaussian", "airy").

        Parameters
        ----------
        psf_profile : {"gaussian", "airy"}, optional
            The PSF profile.
        backend : str, optional
            "auto", "opencl" or "numpy".

        Returns
        -------
        numpy.ndarray of shape (nλ, ncell)
            Fraction of the point-source flux in each aperture cell.
        """
        return get_psf_profile(psf_profile).cells(self, self.aperture, backend)

    def get_extraction_model(self, psf_profile="gaussian"):
        """``ExtractionModel`` with the cube's PSF model as extraction weights (cached).

        Parameters
        ----------
        psf_profile : {"gaussian", "airy"}, optional
            The PSF profile.

        Returns
        -------
        ExtractionModel
            The extraction model.
        """
        def build():
            psf = self.aperture_psf(psf_profile)
            lsf = self.spectrograph.apply_lsf
            flux_ph = self.pointsource_flambda * self.flambda_to_photon        # ph/s
            uniform = {"background": lsf(self.background_photons),
                       "thermal_telescope": lsf(self._thermal_photons("telescope")),
                       "thermal_optics": lsf(self._thermal_photons("optics"))}
            signal_rate = lsf(flux_ph * self.qe) * self.detector.gain           # ADU/s
            host_ph = None
            if self.scene.host is not None:                                     # host light: photon noise
                iy, ix = self.aperture
                host_cube = host_photons_block(self, psf_profile, 0, self.lbda.size)  # ph/s/cell, before LSF
                host_ph = lsf(host_cube[:, iy, ix], axis=0)
            return ExtractionModel(psf**2, lsf(flux_ph[:, None] * psf, axis=0), uniform, self.qe,
                                   signal_rate, host_ph)
        return self._cached(("extraction", psf_profile), build)

    def _spectrum(self, nmd, nramps, off=None, psf_profile="gaussian"):
        model = self.get_extraction_model(psf_profile)
        tint = readout_times(nmd, self.detector.tframe)["integration_time_per_ramp"]
        var_cell, _ = self.cell_variance(model.cell_rate(off), nmd, off)   # ADU² per ramp
        with np.errstate(divide="ignore", invalid="ignore"):
            weight = np.sum(model.psf2 / var_cell, axis=1)
            variance = nramps / weight                                      # ADU²
        signal = np.zeros_like(variance) if "pointsource" in as_switched_off(off) \
            else model.signal_rate * tint * nramps
        return signal, variance

    def get_spectrum(self, nmd=None, nramps=None, psf_profile="gaussian", switch_off=None):
        """Optimally extracted spectrum: (λ [Å], signal [ADU], variance [ADU²]), all ramps.

        The extraction weights are the cube's PSF.

        Parameters
        ----------
        nmd : tuple of int, optional
            Readout (n, m, d) (default: the detector's).
        nramps : int, optional
            Number of ramps (default: the simulation's).
        psf_profile : {"gaussian", "airy"}, optional
            The PSF of the cube and of the weights.
        switch_off : str or sequence of str, optional
            As :meth:`get_cube` (a switched-off point source has zero signal).

        Returns
        -------
        lbda : numpy.ndarray of shape (nλ,)
            Wavelengths [Å].
        signal : numpy.ndarray of shape (nλ,)
            Extracted signal [ADU].
        variance : numpy.ndarray of shape (nλ,)
            Its variance [ADU²].
        """
        off = check_switch_off(switch_off)
        nmd, nramps = self._readout(nmd, nramps)
        signal, variance = self._spectrum(nmd, nramps, off, psf_profile=psf_profile)
        return self.lbda.copy(), signal, variance

    def band_mask(self, lbda_range, allow_partial=False):
        """Bins whose centres lie in [lo, hi] Å (inclusive).

        The band must lie entirely inside the instrument grid and be entirely covered by
        the point-source spectrum, else SpectrumError naming the covered fraction;
        ``allow_partial=True`` accepts a partly covered band (≥ 50 % inside the grid) with
        a BandCoverageWarning, the SNR being that of the covered part
        (``slicersim.snr.bands``).

        Parameters
        ----------
        lbda_range : tuple of float
            (lo, hi) [Å, observer frame].
        allow_partial : bool, optional
            Accept a partly covered band.

        Returns
        -------
        numpy.ndarray of shape (nλ,)
            bool, True for the bins of the band.
        """
        lo, hi = check_band(lbda_range)
        mask = (self.lbda >= lo) & (self.lbda <= hi)
        if not mask.any():
            raise SpectrumError(f"band ({lo}, {hi}) Å contains no bin of the instrument grid "
                                f"({self.lbda[0]:.0f}–{self.lbda[-1]:.0f} Å)")
        from slicersim.snr.bands import check_band_coverage
        check_band_coverage(self, (lo, hi), allow_partial=allow_partial)
        return mask

    def band_range(self, lbda_range, frame=None):
        """(lo, hi) [Å, observer frame] of a band given in the ``"obs"`` or ``"rest"`` frame.

        Parameters
        ----------
        lbda_range : tuple of float or astropy.units.Quantity
            (lo, hi) [Å] (Quantities are converted to Å).
        frame : {"rest", "obs"} or None, optional
            rest: ×(1 + redshift), needs ``redshift``; None (default) is "rest" when ``redshift``
            is known, else "obs" (``resolve_frame``).

        Returns
        -------
        tuple of float
            (lo, hi) [Å, observer frame].
        """
        lo, hi = check_band(lbda_range)
        if resolve_frame(frame, self.redshift) == "rest":
            if self.redshift is None:
                raise ETCError("frame='rest' needs a redshift (Simulation.redshift is None)")
            return lo * (1 + self.redshift), hi * (1 + self.redshift)
        return lo, hi

    def get_band_snr(self, lbda_range, nmd=None, nramps=None, per_resolution=False, frame=None,
                     allow_partial=False, switch_off=None):
        """Band SNR = mean(signal) / √mean(variance) over the bins in ``lbda_range``
        (per bin; ×√dispersion_resolution when ``per_resolution``).

        A band not entirely inside the grid and the source spectrum raises SpectrumError
        unless ``allow_partial=True`` (then a BandCoverageWarning, and the means run over
        the covered bins only); see :meth:`band_mask`.

        Parameters
        ----------
        lbda_range : tuple of float
            (min, max) of the band [Å], in ``frame``.
        nmd : tuple of int, optional
            Readout (n, m, d) (default: the detector's).
        nramps : int, optional
            Number of ramps (default: the simulation's).
        per_resolution : bool, optional
            SNR per resolution element (else per bin).
        frame : {"rest", "obs"} or None, optional
            The frame ``lbda_range`` is given in: "rest" (needs ``redshift``), "obs", or None
            (default: "rest" when ``redshift`` is known, else "obs"; :meth:`band_range`).
        allow_partial : bool, optional
            Answer on the covered part of the band.
        switch_off : str or sequence of str, optional
            As :meth:`get_cube`.

        Returns
        -------
        float
            The band SNR.
        """
        off = check_switch_off(switch_off)
        nmd, nramps = self._readout(nmd, nramps)
        mask = self.band_mask(self.band_range(lbda_range, frame), allow_partial=allow_partial)
        signal, variance = self._spectrum(nmd, nramps, off)
        snr = _band_snr(signal[mask], variance[mask])
        return snr * np.sqrt(self.spectrograph.dispersion_resolution) if per_resolution else snr

    def get_variance_contribution(self, nmd=None, nramps=None):
        """Per-source variance contribution [ADU²] per bin: Var(all) − Var(source off).

        Parameters
        ----------
        nmd : tuple of int, optional
            Readout (n, m, d) (default: the detector's).
        nramps : int, optional
            Number of ramps (default: the simulation's).

        Returns
        -------
        dict
            ``variance`` (the total) and one entry per source of ``VARIANCE_SOURCES`` (dark,
            roic_glow, thermal_dark, ron, pointsource, background, host, thermal), each of
            shape (nλ,) [ADU²].
        """
        nmd, nramps = self._readout(nmd, nramps)
        _, total = self._spectrum(nmd, nramps)
        out = {"variance": total}
        for src in VARIANCE_SOURCES:
            if src == "host" and self.scene.host is None:
                out[src] = np.zeros_like(total)
                continue
            _, var_off = self._spectrum(nmd, nramps, off=src)
            out[src] = total - var_off
        return out

    def get_band_variance_contribution(self, lbda_range, nmd=None, nramps=None, allow_partial=False, frame=None):
        """Band-mean variance contributions: absolute [ADU²] and fractions ``frac_<src>``.

        Parameters
        ----------
        lbda_range : tuple of float
            (min, max) of the band [Å], in ``frame``.
        nmd : tuple of int, optional
            Readout (n, m, d) (default: the detector's).
        nramps : int, optional
            Number of ramps (default: the simulation's).
        allow_partial : bool, optional
            Band coverage rule: :meth:`band_mask`.
        frame : {"rest", "obs"} or None, optional
            As :meth:`get_band_snr`.

        Returns
        -------
        dict
            The band means of the total variance and of each source's contribution [ADU²],
            their fractions ``frac_<src>`` of the total, the band ``snr`` and the exposure and
            integration times [s].
        """
        nmd, nramps = self._readout(nmd, nramps)
        mask = self.band_mask(self.band_range(lbda_range, frame), allow_partial=allow_partial)
        signal, total = self._spectrum(nmd, nramps)
        mean_total = np.nanmean(total[mask])
        times = self.get_times(nmd, nramps)
        out = {"signal": np.nanmean(signal[mask]), "variance": mean_total,
               "snr": _band_snr(signal[mask], total[mask]),
               "exposure_time_per_ramp": times["exposure_time_per_ramp"],
               "integration_time_per_ramp": times["integration_time_per_ramp"],
               "exposure_time": times["exposure_time"]}
        for src in VARIANCE_SOURCES:
            if src == "host" and self.scene.host is None:
                val = 0.0
            else:
                val = mean_total - np.nanmean(self._spectrum(nmd, nramps, off=src)[1][mask])
            out[src] = val
            out[f"frac_{src}"] = val / mean_total
        return out

    # ------------------------------------------------------------------ ETC
    def fetch_snr(self, snr, lbda_range, per_resolution=True, search="exact", allow_partial=False, frame=None,
                  backend="auto"):
        """Readout (n, m, d) × nramps reaching a band SNR (see ``slicersim.snr.search``).

        Parameters
        ----------
        snr : float
            The SNR to reach.
        lbda_range : tuple of float
            (min, max) of the band [Å].
        per_resolution : bool, optional
            SNR per resolution element (else per bin).
        search : {"exact", "reference"}, optional
            The readout search.
        allow_partial : bool, optional
            Band coverage rule: :meth:`band_mask`.
        frame : {"rest", "obs"} or None, optional
            As :meth:`get_band_snr` (None: "rest" when ``redshift`` is known).
        backend : str, optional
            "auto", "opencl" or "numpy".

        Returns
        -------
        dict
            ``nmd``, ``nramps``, ``snr`` (reached, per bin), ``snr_target`` (per bin),
            ``snr_per_resolution``, ``exposure_time`` [s], ``trace`` and ``lbda_range_obs``
            [Å].
        """
        from slicersim.snr.search import check_snr, solve_readout
        return solve_readout(self, check_snr(snr), lbda_range, per_resolution=per_resolution, search=search,
                             allow_partial=allow_partial, frame=frame, backend=backend)


def check_band(lbda_range, name="lbda_range"):
    """(lo, hi) [Å] as finite floats with 0 < lo < hi (ETCError otherwise); astropy Quantities
    (a Quantity pair or two Quantities) are converted to Å."""
    name = validation.shown(name)
    if isinstance(lbda_range, (str, bytes)) or not hasattr(lbda_range, "__len__") or len(lbda_range) != 2:
        raise ETCError(f"{name} must be (lo, hi) in Å, got {validation.short_repr(lbda_range)}")
    lo, hi = (validation.number(f"{name}[{i}]", v, low=0.0, low_open=True, unit="Angstrom", error=ETCError)
              for i, v in enumerate(lbda_range))
    if not hi > lo:
        raise ETCError(f"{name} must be (lo, hi) in Å with lo < hi, got {validation.short_repr(lbda_range)}")
    return lo, hi


def _band_snr(signal, variance):
    with np.errstate(invalid="ignore", divide="ignore"):
        return float(np.nanmean(signal) / np.sqrt(np.nanmean(variance)))
