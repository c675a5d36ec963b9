"""Calibration lamps: QTH continuum, Fabry–Perot etalon combs, and the uniform illumination they give.

Surface brightnesses S(λ) are in erg/s/cm²/Å/arcsec², wavelengths λ in Å, wavenumbers
σ = 10⁸/λ in cm⁻¹.

* :class:`BlackBodyContinuum` — the QTH lamp: a black body of temperature T (3000 K, as
  slicersim 1.4.2) normalised so that its AB magnitude per arcsec² in a band is ``mag``.
* :class:`TabulatedContinuum` — any tabulated surface brightness (linear interpolation).
* :class:`FabryPerotEtalon` — the Airy transmission
  T(σ) = T_max / (1 + F sin²(π σ / FSR_σ)),  F = (2𝓕/π)²,
  with free spectral range FSR_σ [cm⁻¹] = 1 / (2 n d) (normal incidence, optical thickness
  n·d) and finesse 𝓕 ≈ FSR/FWHM; the peaks are at σ_k = k·FSR_σ (interference order k).
* :class:`TabulatedEtalon` — a tabulated transmission (slicersim 1.4.2's form:
  a CSV ``lbda, transmission`` or any callable of λ).
* :class:`CalibrationLamp` — continuum × optional etalon: S(λ) = S_c(λ) T(λ); the
  normalisation applies to the continuum, before the etalon (as 1.4.2).
* :class:`LampIllumination` — the lamp as a spatially uniform scene background whose value in
  each spectral bin is the lamp's light deposited on the bin grid (cloud-in-cell, see
  :meth:`CalibrationLamp.bin_average`): integrated, not sampled at the bin centre (which would
  miss or double lines narrower than a bin), and a line keeps its wavelength.
"""
from __future__ import annotations

import math

import numpy as np

from slicersim import validation
from slicersim.errors import ParameterError, SpectrumError
from slicersim.sources.scene import Background
from slicersim.sources.spectra import blackbody_flambda, normalise_to_mag, validate_spectrum
from slicersim.versioning import Versioned

__all__ = ["QTH_TEMPERATURE", "DEFAULT_LAMP_BAND", "BlackBodyContinuum", "TabulatedContinuum",
           "FabryPerotEtalon", "TabulatedEtalon", "CalibrationLamp", "LampIllumination", "qth_lamp",
           "fabry_perot_lamp", "as_etalon", "bin_edges_from_centres"]

#: temperature of the on-board QTH lamp [K] (slicersim 1.4.2's ``_QTH_TEMPERATURE``)
QTH_TEMPERATURE = 3000.0
#: band of the lamp normalisation (1.4.2 uses "sdssr", which sncosmo must download: not offline)
DEFAULT_LAMP_BAND = "bessellr"
#: wavelength grid [Å] on which an analytic continuum is normalised to its magnitude
_NORM_GRID = np.arange(1000.0, 30000.5, 1.0)
#: 8-point Gauss–Legendre nodes/weights on [−1, 1] (bin averages)
_GL_X, _GL_W = np.polynomial.legendre.leggauss(8)
#: quadrature panels are at most this fraction of the finest spectral structure
PANEL_FRACTION = 0.5
#: largest number of quadrature nodes of one bin average (guards against absurd finesses)
MAX_NODES = 50_000_000
_NODES_PER_CHUNK = 1 << 20


def _number(name, value, *, positive=True, allow_zero=False, upper=None):
    """``value`` as a finite float (> 0, or ≥ 0 with ``allow_zero``; ≤ ``upper``), else ParameterError."""
    if not positive:
        return validation.number(name, value)
    return validation.number(name, value, low=0.0, low_open=not allow_zero,
                             high=math.inf if upper is None else upper)


def bin_edges_from_centres(lbda):
    """Bin edges [Å] halfway between centres (the end bins mirrored): n + 1 edges for n ≥ 2 centres."""
    lbda = np.asarray(lbda, dtype=float)
    mid = 0.5 * (lbda[1:] + lbda[:-1])
    return np.concatenate([[lbda[0] - (mid[0] - lbda[0])], mid, [lbda[-1] + (lbda[-1] - mid[-1])]])


# --------------------------------------------------------------------------- continua
class BlackBodyContinuum(Versioned):
    """QTH-like continuum: S(λ) = k B_λ(T) [erg/s/cm²/Å/arcsec²], k such that the AB (``magsys``)
    magnitude per arcsec² of S in ``band`` is ``mag``."""

    def __init__(self, temperature=QTH_TEMPERATURE, mag=12.0, band=DEFAULT_LAMP_BAND, magsys="ab"):
        temperature = _number("lamp temperature [K]", temperature)
        mag = _number("lamp magnitude [mag/arcsec²]", mag, positive=False)
        if not isinstance(band, str) or not isinstance(magsys, str):
            raise ParameterError(f"band and magsys must be sncosmo names, got {band!r}, {magsys!r}")
        self.temperature, self.mag, self.band, self.magsys = temperature, mag, band, magsys
        self.scale, self.native_mag = normalise_to_mag(_NORM_GRID, blackbody_flambda(_NORM_GRID, temperature),
                                                       mag, band, magsys)

    def surface_brightness(self, lbda):
        """S(λ) [erg/s/cm²/Å/arcsec²] at λ [Å]."""
        return self.scale * blackbody_flambda(lbda, self.temperature)

    def structure_scale(self, lbda):
        """Finest structure [Å]: the peak FWHM (half an FSR when the peaks overlap).

        Parameters
        ----------
        lbda : array_like
            Wavelengths [Å].

        Returns
        -------
        numpy.ndarray
            The scale [Å].
        """
        return np.full(np.shape(lbda), np.inf)

    def coverage(self):
        return 0.0, np.inf


class TabulatedContinuum(Versioned):
    """Tabulated surface brightness (λ [Å], S [erg/s/cm²/Å/arcsec²]), linear interpolation,
    optionally renormalised to ``mag`` (AB per arcsec²) in ``band``; no extrapolation."""

    def __init__(self, lbda, flux, mag=None, band="bessellb", magsys="ab"):
        self.lbda_in, self.flux_in = validate_spectrum(lbda, flux, "lamp spectrum")
        self.scale, self.native_mag, self.mag, self.band = 1.0, None, mag, band
        if mag is not None:
            mag = _number("lamp magnitude [mag/arcsec²]", mag, positive=False)
            self.scale, self.native_mag = normalise_to_mag(self.lbda_in, self.flux_in, mag, band, magsys)

    def surface_brightness(self, lbda):
        lbda = np.asarray(lbda, dtype=float)
        lo, hi = self.coverage()
        if lbda.size and (lbda.min() < lo or lbda.max() > hi):
            raise SpectrumError(f"lamp spectrum covers {lo:g}–{hi:g} Å, not {lbda.min():g}–{lbda.max():g} Å")
        return self.scale * np.interp(lbda, self.lbda_in, self.flux_in)

    def structure_scale(self, lbda):
        return np.full(np.shape(lbda), float(np.min(np.diff(self.lbda_in))))

    def coverage(self):
        return float(self.lbda_in[0]), float(self.lbda_in[-1])


# --------------------------------------------------------------------------- etalons
class FabryPerotEtalon(Versioned):
    """Airy transmission of a Fabry–Perot etalon at normal incidence.

    T(σ) = T_max / (1 + F sin²(π σ / FSR_σ)),  F = (2𝓕/π)²,  σ = 10⁸/λ[Å]  [cm⁻¹].

    Give exactly one of ``fsr`` and ``optical_thickness``.

    Parameters
    ----------
    fsr : float, optional
        Free spectral range FSR_σ [cm⁻¹] (> 0).
    finesse : float, optional
        𝓕 > 0 (≈ FSR/FWHM for 𝓕 ≫ 1).
    optical_thickness : float, optional
        n·d [µm] (> 0); FSR_σ = 10⁴ / (2 n d).
    peak_transmission : float, optional
        T_max in (0, 1].
    """

    def __init__(self, fsr=None, finesse=25.0, optical_thickness=None, peak_transmission=1.0):
        if (fsr is None) == (optical_thickness is None):
            raise ParameterError("give the etalon's free spectral range either as fsr [cm⁻¹] or as "
                                 "optical_thickness n·d [µm], not both or neither")
        if fsr is not None:
            fsr = _number("etalon free spectral range fsr [cm⁻¹]", fsr)
        else:
            fsr = 1e4 / (2.0 * _number("etalon optical thickness n·d [µm]", optical_thickness))
        self.fsr = fsr
        self.finesse = _number("etalon finesse", finesse)
        self.peak_transmission = _number("etalon peak transmission", peak_transmission, upper=1.0)

    @property
    def optical_thickness(self):
        """n·d [µm]."""
        return 1e4 / (2.0 * self.fsr)

    @property
    def coefficient_of_finesse(self):
        """F = (2𝓕/π)²."""
        return (2.0 * self.finesse / math.pi) ** 2

    @property
    def fwhm_wavenumber(self):
        """Full width at half maximum of a peak [cm⁻¹]: (2 FSR/π) arcsin(1/√F); inf when F ≤ 1
        (the transmission never falls to half its peak)."""
        F = self.coefficient_of_finesse
        return 2.0 * self.fsr / math.pi * math.asin(1.0 / math.sqrt(F)) if F > 1 else math.inf

    def transmission(self, lbda):
        """T at λ [Å].

        Parameters
        ----------
        lbda : array_like
            Wavelengths [Å].

        Returns
        -------
        numpy.ndarray
            The transmission, in [0, ``peak_transmission``].
        """
        sigma = 1e8 / np.asarray(lbda, dtype=float)
        return self.peak_transmission / (1.0 + self.coefficient_of_finesse
                                         * np.sin(math.pi * sigma / self.fsr) ** 2)

    def order(self, lbda):
        """Interference order σ / FSR_σ (an integer at a peak).

        Parameters
        ----------
        lbda : array_like
            Wavelengths [Å].

        Returns
        -------
        numpy.ndarray
            The order.
        """
        return 1e8 / np.asarray(lbda, dtype=float) / self.fsr

    def peak_wavelengths(self, lo, hi):
        """Wavelengths [Å] of the transmission peaks σ_k = k·FSR_σ inside [lo, hi] Å, increasing.

        Parameters
        ----------
        lo, hi : float
            The range [Å].

        Returns
        -------
        numpy.ndarray
            The peak wavelengths [Å].
        """
        kmin, kmax = math.ceil(1e8 / hi / self.fsr - 1e-12), math.floor(1e8 / lo / self.fsr + 1e-12)
        k = np.arange(max(kmin, 1), kmax + 1)[::-1]
        return 1e8 / (k * self.fsr)

    def fwhm(self, lbda):
        """FWHM of the peak near λ [Å]: λ² δσ / 10⁸.

        Parameters
        ----------
        lbda : array_like
            Wavelengths [Å].

        Returns
        -------
        numpy.ndarray
            FWHM [Å].
        """
        return np.asarray(lbda, dtype=float) ** 2 * self.fwhm_wavenumber * 1e-8

    def structure_scale(self, lbda):
        """Finest structure [Å]: the peak FWHM (half an FSR when the peaks overlap).

        Parameters
        ----------
        lbda : array_like
            Wavelengths [Å].

        Returns
        -------
        numpy.ndarray
            The scale [Å].
        """
        return np.asarray(lbda, dtype=float) ** 2 * min(self.fwhm_wavenumber, 0.5 * self.fsr) * 1e-8


class TabulatedEtalon(Versioned):
    """Tabulated etalon transmission T(λ) (slicersim 1.4.2's form), linear interpolation.

    Outside the table the end values are held (1.4.2 holds the first value, with a warning).
    :meth:`from_file` reads a CSV/ECSV with a ``transmission`` column (1.4.2's
    ``lazuli_fp_transmission.csv`` layout: ``lbda, transmission, R, A``).

    Parameters
    ----------
    lbda : array_like of shape (n,)
        Wavelengths of the table [Å].
    transmission : array_like of shape (n,)
        Transmission T at those wavelengths [fraction].
    """

    def __init__(self, lbda, transmission):
        lbda, trans = validate_spectrum(lbda, transmission, "etalon transmission")
        if np.any(trans > 1):
            raise ParameterError(f"etalon transmission must be within [0, 1], max {trans.max():g}")
        self.lbda_in, self.transmission_in = lbda, trans

    @classmethod
    def from_file(cls, path, column="transmission"):
        from slicersim.io.curves import read_curve
        lbda, cols = read_curve(str(path), columns=[column])
        return cls(lbda, cols[column])

    def transmission(self, lbda):
        return np.interp(np.asarray(lbda, dtype=float), self.lbda_in, self.transmission_in)

    def structure_scale(self, lbda):
        return np.full(np.shape(lbda), float(np.min(np.diff(self.lbda_in))))

    def peak_wavelengths(self, lo, hi):
        """Local maxima of the table inside [lo, hi] Å, refined by a parabola through 3 nodes
        (maxima below 10 % of the table's maximum are ignored).

        Parameters
        ----------
        lo, hi : float
            The range [Å].

        Returns
        -------
        numpy.ndarray
            The peak wavelengths [Å].
        """
        t = self.transmission_in
        i = np.flatnonzero((t[1:-1] > t[:-2]) & (t[1:-1] >= t[2:]) & (t[1:-1] > 0.1 * t.max())) + 1
        a, b, c = t[i - 1], t[i], t[i + 1]
        shift = 0.5 * (a - c) / np.where(a - 2 * b + c != 0, a - 2 * b + c, -1.0)
        peaks = np.interp(i + shift, np.arange(t.size), self.lbda_in)
        return peaks[(peaks >= lo) & (peaks <= hi)]


class _CallableEtalon(Versioned):
    """Any callable T(λ [Å]) (slicersim 1.4.2's ``fp_throughput``); sampled at ``resolution`` [Å]."""

    def __init__(self, func, resolution=1.0):
        self.func, self.resolution = func, _number("etalon resolution [Å]", resolution)

    def transmission(self, lbda):
        out = np.asarray(self.func(np.asarray(lbda, dtype=float)), dtype=float)
        if out.shape != np.shape(lbda) or not np.all(np.isfinite(out)) or np.any((out < 0) | (out > 1)):
            raise ParameterError("fp_throughput(λ) must return finite values within [0, 1], one per λ")
        return out

    def structure_scale(self, lbda):
        return np.full(np.shape(lbda), self.resolution)

    def peak_wavelengths(self, lo, hi):
        grid = np.arange(lo, hi + self.resolution, self.resolution / 4)
        return TabulatedEtalon(grid, self.transmission(grid)).peak_wavelengths(lo, hi)


def as_etalon(fp_throughput):
    """An etalon object from a :class:`FabryPerotEtalon` / :class:`TabulatedEtalon`, a CSV/ECSV
    path (``transmission`` column) or a callable T(λ [Å])."""
    import os
    if hasattr(fp_throughput, "transmission") and hasattr(fp_throughput, "structure_scale"):
        return fp_throughput
    if isinstance(fp_throughput, (str, os.PathLike)):
        return TabulatedEtalon.from_file(fp_throughput)
    if callable(fp_throughput):
        return _CallableEtalon(fp_throughput)
    raise ParameterError(f"fp_throughput must be an etalon, a transmission file or a callable of λ [Å], "
                         f"got {fp_throughput!r}")


# --------------------------------------------------------------------------- lamps
class CalibrationLamp(Versioned):
    """Lamp surface brightness S(λ) = S_c(λ) T(λ) [erg/s/cm²/Å/arcsec²]: a continuum seen
    directly (``etalon=None``) or through an etalon (the continuum's magnitude is set before it).

    Parameters
    ----------
    continuum : object
        The continuum S_c(λ): anything with ``surface_brightness(lbda)``
        [erg/s/cm²/Å/arcsec²] (e.g. the black body of :func:`qth_lamp`).
    etalon : FabryPerotEtalon or TabulatedEtalon, optional
        Its transmission T(λ); None: the continuum seen directly.
    """

    def __init__(self, continuum, etalon=None):
        self.continuum, self.etalon = continuum, etalon

    def _state_parts(self):
        return (self.continuum, self.etalon)

    def surface_brightness(self, lbda):
        """S(λ) at λ [Å].

        Parameters
        ----------
        lbda : array_like
            Wavelengths [Å].

        Returns
        -------
        numpy.ndarray
            S [erg/s/cm²/Å/arcsec²].
        """
        s = self.continuum.surface_brightness(lbda)
        return s if self.etalon is None else s * self.etalon.transmission(lbda)

    def spectrum(self, lbda):
        """The lamp as a spectrum (e.g. an arc-lamp line list for a PointSource).

        Parameters
        ----------
        lbda : array_like
            Wavelengths [Å].

        Returns
        -------
        lbda : numpy.ndarray
            Wavelengths [Å].
        brightness : numpy.ndarray
            S [erg/s/cm²/Å/arcsec²].
        """
        lbda = np.asarray(lbda, dtype=float)
        return lbda, self.surface_brightness(lbda)

    def line_wavelengths(self, lo, hi):
        """Wavelengths [Å] of the etalon's transmission peaks in [lo, hi] (empty without etalon).

        Parameters
        ----------
        lo, hi : float
            The range [Å].

        Returns
        -------
        numpy.ndarray
            The peak wavelengths [Å].
        """
        return np.empty(0) if self.etalon is None else self.etalon.peak_wavelengths(lo, hi)

    def structure_scale(self, lbda):
        scale = self.continuum.structure_scale(lbda)
        return scale if self.etalon is None else np.minimum(scale, self.etalon.structure_scale(lbda))

    def check_coverage(self, lo, hi):
        """SpectrumError unless the continuum covers [lo, hi] Å.

        Parameters
        ----------
        lo, hi : float
            The range [Å].

        Returns
        -------
        None
            It only raises.
        """
        clo, chi = self.continuum.coverage()
        if lo < clo or hi > chi:
            raise SpectrumError(f"the lamp spectrum covers {clo:g}–{chi:g} Å, not the instrument's "
                                f"{lo:g}–{hi:g} Å (bin edges)")

    def _moments(self, lo, hi):
        """(∫ S dλ, ∫ S t dλ) over intervals [lo, hi] [Å], t = (λ − lo)/(hi − lo): 8-point
        Gauss–Legendre on equal panels no wider than :data:`PANEL_FRACTION` of the finest
        structure (etalon FWHM, table spacing)."""
        width = hi - lo
        scale = np.minimum(self.structure_scale(lo), self.structure_scale(hi))
        with np.errstate(divide="ignore"):
            npanel = np.maximum(1, np.ceil(width / (PANEL_FRACTION * scale))).astype(np.int64)
        if npanel.sum() * _GL_X.size > MAX_NODES:
            raise ParameterError(f"the lamp's spectral structure ({np.min(scale):.3g} Å) needs "
                                 f"{npanel.sum() * _GL_X.size:.3g} quadrature nodes on this grid "
                                 f"(more than {MAX_NODES}): lower the etalon finesse")
        m0, m1 = np.empty(lo.size), np.empty(lo.size)
        ends = np.cumsum(npanel)
        start = 0
        while start < lo.size:        # chunks of intervals holding ≤ _NODES_PER_CHUNK nodes
            stop = max(start + 1, int(np.searchsorted(ends, ends[start] - npanel[start]
                                                      + _NODES_PER_CHUNK // _GL_X.size, side="right")))
            n = npanel[start:stop]
            owner = np.repeat(np.arange(n.size), n)
            j = np.arange(owner.size) - np.repeat(np.cumsum(n) - n, n)
            t = (j[:, None] + 0.5 + 0.5 * _GL_X) / n[owner, None]                    # (panel, node) in [0, 1]
            x = lo[start:stop][owner, None] + width[start:stop][owner, None] * t
            weight = 0.5 * _GL_W * (width[start:stop] / n)[owner, None]
            f = self.surface_brightness(x) * weight
            m0[start:stop] = np.bincount(owner, weights=f.sum(axis=1), minlength=n.size)
            m1[start:stop] = np.bincount(owner, weights=(f * t).sum(axis=1), minlength=n.size)
            start = stop
        return m0, m1

    def bin_average(self, edges, centres=None):
        """Lamp content of each bin divided by its width Δλ [erg/s/cm²/Å/arcsec²].

        ``centres=None``: the plain average ∫_bin S dλ / Δλ.  With the bin ``centres``: the
        cloud-in-cell deposit — the light at fractional bin position x (x = i at centre i, i ± ½
        at its edges, linear in λ between them) is shared between the two nearest centres with
        weights 1 − abs(x − i) (the half bins at the grid's ends go to the end bins), so the total
        is conserved, a smooth spectrum gets its bin average to O(Δλ² S″), and a line narrower
        than a bin keeps its position (its first moment) through the discrete LSF, where the
        plain average would move it to the centre of its bin.

        Parameters
        ----------
        edges : array_like of shape (nλ+1,)
            Bin edges [Å].
        centres : array_like of shape (nλ,), optional
            Bin centres [Å] (the cloud-in-cell deposit).

        Returns
        -------
        numpy.ndarray of shape (nλ,)
            [erg/s/cm²/Å/arcsec²].
        """
        edges = np.asarray(edges, dtype=float)
        if edges.ndim != 1 or edges.size < 2 or not np.all(np.isfinite(edges)) or np.any(np.diff(edges) <= 0):
            raise ParameterError("bin edges must be a finite, strictly increasing 1-D array [Å]")
        n = edges.size - 1
        box = centres is None
        centres = 0.5 * (edges[1:] + edges[:-1]) if box else np.asarray(centres, dtype=float)
        if centres.shape != (n,) or np.any(centres <= edges[:-1]) or np.any(centres >= edges[1:]):
            raise ParameterError("bin centres must lie strictly inside their bins")
        nodes = np.empty(2 * n + 1)
        nodes[0::2], nodes[1::2] = edges, centres
        m0, m1 = self._moments(nodes[:-1], nodes[1:])
        left0, left1 = m0[0::2], m1[0::2]             # [edge_i, centre_i]: x from i − ½ to i
        right0, right1 = m0[1::2], m1[1::2]           # [centre_i, edge_i+1]: x from i to i + ½
        width = np.diff(edges)
        if box:
            return (left0 + right0) / width
        content = 0.5 * (left0 + left1) + right0 - 0.5 * right1      # kept by bin i
        content[:-1] += 0.5 * (left0[1:] - left1[1:])               # to bin i − 1 from [edge_i, centre_i]
        content[0] += 0.5 * (left0[0] - left1[0])                   # … the first bin keeps its own
        content[1:] += 0.5 * right1[:-1]                            # to bin i + 1 from [centre_i, edge_i+1]
        content[-1] += 0.5 * right1[-1]                             # … the last bin keeps its own
        return content / width


def qth_lamp(temperature=None, mag=12.0, band=DEFAULT_LAMP_BAND, magsys="ab"):
    """The QTH lamp: a black body (default ``QTH_TEMPERATURE``, 3000 K) of ``mag`` per arcsec² in ``band``.

    Parameters
    ----------
    temperature : float, optional
        Black-body temperature [K] (default 3000).
    mag : float, optional
        Magnitude per arcsec² in ``band`` [mag/arcsec²].
    band : str, optional
        sncosmo band of that magnitude (default "bessellr").
    magsys : str, optional
        sncosmo magnitude system of that magnitude.

    Returns
    -------
    CalibrationLamp
        The lamp, seen directly (no etalon).
    """
    return CalibrationLamp(BlackBodyContinuum(QTH_TEMPERATURE if temperature is None else temperature,
                                              mag, band, magsys))


def fabry_perot_lamp(etalon, temperature=None, mag=12.0, band=DEFAULT_LAMP_BAND, magsys="ab"):
    """The QTH lamp seen through an etalon; ``mag`` is the lamp's, before it.

    Parameters
    ----------
    etalon : FabryPerotEtalon, TabulatedEtalon, str or callable
        The etalon: an etalon object, a CSV/ECSV path (``transmission`` column) or a callable
        T(λ [Å]).
    temperature, mag, band, magsys
        The QTH lamp, as :func:`qth_lamp`.

    Returns
    -------
    CalibrationLamp
        The lamp seen through the etalon.
    """
    etalon = as_etalon(etalon)
    return CalibrationLamp(qth_lamp(temperature, mag, band, magsys).continuum, etalon)


class LampIllumination(Background):
    """A lamp as a spatially uniform scene background [erg/s/cm²/Å/arcsec²].

    ``flambda(lbda)`` returns the lamp's cloud-in-cell bin values (:meth:`CalibrationLamp.bin_average`)
    on the bins of ``spectrograph`` when ``lbda`` is its grid (its own edges), else on edges halfway
    between the given centres."""

    def __init__(self, lamp, spectrograph=None, name="lamp"):        # noqa: super().__init__ not wanted
        if not callable(getattr(lamp, "bin_average", None)):
            raise ParameterError(f"lamp must be a CalibrationLamp, got {lamp!r}")
        self.lamp, self.spectrograph, self.name = lamp, spectrograph, name
        self.model, self.scale = lamp.surface_brightness, 1.0

    def _state_parts(self):
        return (self.lamp,)

    def edges_for(self, lbda):
        lbda = np.asarray(lbda, dtype=float)
        spec = self.spectrograph
        if spec is not None and np.shape(spec.lbda) == lbda.shape and np.array_equal(spec.lbda, lbda):
            return np.asarray(spec.lbda_edges, dtype=float)
        return bin_edges_from_centres(lbda)

    def flambda(self, lbda):
        lbda = np.asarray(lbda, dtype=float)
        if lbda.ndim != 1 or lbda.size < 2:
            return self.lamp.surface_brightness(lbda)
        return self.lamp.bin_average(self.edges_for(lbda), centres=lbda)
