"""Spectrographs: wavelength sampling, throughput, LSF and internal thermal optics.

``SlicerSpectrograph`` (image slicer, anamorphic 1×2 cells, 2 detector pixels
per cell) and ``MLASpectrograph`` (micro-lens array) share the ``Spectrograph``
base.  The wavelength grid comes from a dispersion law (detector offset versus
wavelength) or from a resolving power.
"""
from __future__ import annotations

import difflib

import numpy as np
from scipy.interpolate import CubicSpline

from slicersim.constants import ARCSEC
from slicersim import validation
from slicersim.errors import ParameterError
from slicersim.instrument.names import check_parameter_names
from slicersim.io.curves import read_curve
from slicersim.physics.lsf import apply_lsf
from slicersim.physics.thermal import photon_radiance, solid_angle_from_fratio
from slicersim.versioning import Versioned

__all__ = ["Spectrograph", "SlicerSpectrograph", "MLASpectrograph", "OpticalThroughput",
           "wavelength_grid_from_dispersion", "wavelength_grid_from_resolving_power",
]


#: largest wavelength grid accepted (guards against absurd ranges / resolving powers)
MAX_BINS = 1_000_000
#: spline values within this distance outside [0, 1] are clipped (tabulation round-off)
THROUGHPUT_TOL = 1e-3


# --------------------------------------------------------------------------- #
#  wavelength sampling                                                        #
# --------------------------------------------------------------------------- #
def wavelength_grid_from_dispersion(law_lbda, law_offset, spectral_range, dispersion_scale=1.0,
                                    dispersion_resolution=2.0):
    """Bin centres and edges [Å] from a dispersion law.

    The law gives the detector offset [px] versus λ [Å]; it is scaled by
    K = dispersion_scale × dispersion_resolution / 2.  Two not-a-knot cubic
    splines are built, D: λ → offset and W: offset → λ; the grid has
    N = round(D(λ_max) − D(λ_min)) + 1 bins with centres W(o₀ + i) and edges W(o₀ + i − ½),
    o₀ = round(D(λ_min)): the bins sit on the detector's pixel lattice and start at λ_min.
    (slicersim 1.0 always started at offset 0, whatever λ_min — the same grid for the default
    range, which begins where the law's offset is 0, and a grid at the wrong wavelengths for
    any other range.)
    """
    law_lbda = np.asarray(law_lbda, dtype=float)
    scaled = np.asarray(law_offset, dtype=float) * dispersion_scale * dispersion_resolution / 2.0
    if np.any(np.diff(law_lbda) <= 0) or np.any(np.diff(scaled) <= 0):
        raise ParameterError("dispersion_law must be strictly increasing in wavelength and offset")
    lbda_to_offset = CubicSpline(law_lbda, scaled, bc_type="not-a-knot", extrapolate=True)
    offset_to_lbda = CubicSpline(scaled, law_lbda, bc_type="not-a-knot", extrapolate=True)
    lo, hi = spectral_range
    tol = 1e-9 * max(abs(law_lbda[0]), abs(law_lbda[-1]))
    if not (law_lbda[0] - tol <= lo < hi <= law_lbda[-1] + tol):
        raise ParameterError(f"spectral_range {tuple(spectral_range)} Å lies outside the dispersion law's "
                             f"wavelength coverage [{law_lbda[0]:g}, {law_lbda[-1]:g}] Å (no extrapolation)")
    nbins = int(round(float(lbda_to_offset(hi) - lbda_to_offset(lo)))) + 1
    if nbins > MAX_BINS:
        raise ParameterError(f"spectral range {tuple(spectral_range)} gives {nbins} bins (more than {MAX_BINS})")
    if nbins < 2:
        raise ParameterError(f"spectral_range {tuple(spectral_range)} gives fewer than 2 bins")
    first = float(round(float(lbda_to_offset(lo))))
    lbda = offset_to_lbda(first + np.arange(nbins, dtype=float))
    edges = offset_to_lbda(first + np.arange(nbins + 1, dtype=float) - 0.5)
    return lbda, edges


def wavelength_grid_from_resolving_power(resolving_power, spectral_range, dispersion_resolution=2.0):
    """Bin centres and edges [Å] for a resolving power R (float or callable λ→R).

    Bins are spaced so that λ/Δλ_bin = R · dispersion_resolution.
    """
    lo, hi = spectral_range
    fine = np.geomspace(lo, hi, 4097)
    rpow = resolving_power(fine) if callable(resolving_power) else np.full_like(fine, resolving_power)
    if np.any(~(rpow > 0)) or not np.all(np.isfinite(rpow)):
        raise ParameterError("resolving_power must be finite and > 0")
    # offset [bins] = ∫ R dr / λ dλ (trapezoid in ln λ)
    dln = np.diff(np.log(fine))
    offset = np.concatenate([[0.0], np.cumsum(0.5 * (rpow[1:] + rpow[:-1]) * dispersion_resolution * dln)])
    return wavelength_grid_from_dispersion(fine, offset, spectral_range, 1.0, 2.0)


# --------------------------------------------------------------------------- #
#  throughput                                                                  #
# --------------------------------------------------------------------------- #
class OpticalThroughput:
    """Throughput T(λ) = Π_i T_i(λ)^noptics_i of optical components.

    Each component is a float in [0, 1] or a (λ[Å], T) curve (finite, strictly increasing λ,
    T in [0, 1]) interpolated with a not-a-knot cubic spline; spline values in [−1e-3, 0)
    are set to 0 and values in (1, 1 + 1e-3] to 1.  Curves are never extrapolated: evaluating
    outside a curve's wavelength coverage, or where its spline leaves [−1e-3, 1 + 1e-3],
    raises :class:`~slicersim.errors.ParameterError`.

    Parameters
    ----------
    components : float, tuple of array_like or dict
        One component, or a dict {name: component}; each component is a float in [0, 1] or
        a (λ [Å], T) curve.
    noptics : dict or int, optional
        Number of times each component is passed, {name: count} or one count for every
        component: non-negative integers (int or integral float); default 1.
    """

    def __init__(self, components, noptics=None):
        if not isinstance(components, dict):
            components = {"total": components}
        self.components = dict(components)
        self.noptics = {k: 1 for k in self.components}
        if noptics is not None and np.ndim(noptics) == 0 and not isinstance(noptics, dict):
            noptics = {k: noptics for k in self.components}    # one count for every component
        if noptics:
            self._check_noptics_keys(noptics)
            self.noptics.update({k: self._check_noptics(k, v) for k, v in noptics.items()})
        for name, comp in self.components.items():
            if np.isscalar(comp):
                if isinstance(comp, (str, bytes)) or not 0 <= float(comp) <= 1:
                    raise ParameterError(f"throughput {name}={comp!r} must be a number within [0, 1]")
            else:
                lbda, val = (np.asarray(c, dtype=float) for c in comp)
                if lbda.ndim != 1 or lbda.shape != val.shape or lbda.size < 4:
                    raise ParameterError(f"throughput curve {name}: need matching 1-D λ and T arrays "
                                         "(≥ 4 points)")
                if not (np.all(np.isfinite(lbda)) and np.all(np.diff(lbda) > 0)):
                    raise ParameterError(f"throughput curve {name}: wavelengths must be finite and "
                                         "strictly increasing")
                if not (np.all(np.isfinite(val)) and np.all((val >= 0) & (val <= 1))):
                    raise ParameterError(f"throughput curve {name}: values must be finite and within [0, 1] "
                                         f"(got {np.nanmin(val):g} to {np.nanmax(val):g})")

    def _check_noptics_keys(self, noptics):
        """ParameterError listing every unknown key of ``noptics`` and every valid one (the components),
        with a did-you-mean and what a single-curve throughput means."""
        unknown = sorted(set(noptics) - set(self.components), key=str)
        if not unknown:
            return
        valid = list(self.components)
        close = [m for u in unknown if isinstance(u, str) for m in difflib.get_close_matches(u, valid, n=1)]
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        what = "1 component: one curve for the whole light path, e.g. a column of the configuration's " \
            "throughput file" if len(valid) == 1 else f"{len(valid)} components"
        raise ParameterError(
            f"unknown noptics key(s) {', '.join(validation.short_repr(u) for u in unknown)}{hint}: noptics counts "
            f"the elements of each throughput component, and this throughput has {what}; valid keys: "
            f"{', '.join(map(repr, valid))}, or one integer for every component; components are named by "
            "set_throughput({'name': curve, ...})")

    @staticmethod
    def _check_noptics(name, value):
        try:
            ok = not isinstance(value, (bool, np.bool_)) and float(value) == int(value) and int(value) >= 0
        except (TypeError, ValueError, OverflowError):
            ok = False
        if not ok:
            raise ParameterError(f"noptics {name}={value!r} must be a non-negative integer")
        return int(value)

    def __call__(self, lbda):
        lbda = np.asarray(lbda, dtype=float)
        total = np.ones_like(lbda)
        for name, comp in self.components.items():
            if np.isscalar(comp):
                val = np.full_like(lbda, float(comp))
            else:
                clbda, cval = (np.asarray(c, dtype=float) for c in comp)
                if lbda.size and (np.min(lbda) < clbda[0] or np.max(lbda) > clbda[-1]):
                    raise ParameterError(
                        f"throughput curve {name} covers {clbda[0]:g}-{clbda[-1]:g} Å only, not the "
                        f"instrument's {np.min(lbda):g}-{np.max(lbda):g} Å (curves are not extrapolated)")
                val = CubicSpline(clbda, cval, bc_type="not-a-knot", extrapolate=True)(lbda)
                if np.any(~np.isfinite(val)) or np.any(val < -THROUGHPUT_TOL) or np.any(val > 1 + THROUGHPUT_TOL):
                    raise ParameterError(f"throughput curve {name}: its spline leaves [0, 1] on the grid "
                                         f"({np.nanmin(val):g} to {np.nanmax(val):g}); sample it more finely")
                val[(val < 0) & (val >= -THROUGHPUT_TOL)] = 0.0
                val[(val > 1) & (val <= 1 + THROUGHPUT_TOL)] = 1.0
            total = total * val ** self.noptics[name]
        return total


# --------------------------------------------------------------------------- #
#  spectrographs                                                               #
# --------------------------------------------------------------------------- #
def _checked_scalars(params):
    """``params`` with the spectrograph's scalar parameters checked and converted: spectral_range
    (lo, hi) [Å], dispersion_scale, dispersion_resolution [px] and spatial_scale [arcsec] finite > 0
    (astropy Quantities converted), spatial_shape two integers ≥ 1 (ParameterError naming each)."""
    params = dict(params)
    rng = params["spectral_range"]
    if isinstance(rng, (str, bytes)) or not hasattr(rng, "__len__") or len(rng) != 2:
        raise ParameterError(f"spectral_range must be (min, max) in Å, got {validation.short_repr(rng)}")
    params["spectral_range"] = tuple(validation.number(f"spectral_range[{i}]", v, low=0.0, low_open=True,
                                                       unit="Angstrom") for i, v in enumerate(rng))
    for key, unit in (("dispersion_scale", None), ("dispersion_resolution", "pix"), ("spatial_scale", "arcsec")):
        params[key] = validation.number(key, params[key], low=0.0, low_open=True, unit=unit,
                                        plausible=validation.PLAUSIBLE.get(key))
    params["spatial_shape"] = validation.shape("spatial_shape", params["spatial_shape"])
    return params


class Spectrograph(Versioned):
    """Generic IFS: wavelength grid, throughput, spatial sampling, LSF and thermal optics.

    Parameters
    ----------
    spectral_range : tuple of float
        (min, max) wavelength of the grid [Å], 0 < min < max.
    dispersion_law : tuple of array_like or str or None, optional
        (λ [Å], offset [px]) arrays of the dispersion law, or the path of a curve file; None
        uses ``resolving_power``.
    resolving_power : float or callable, optional
        R = λ/Δλ (or a function of λ [Å]), used when ``dispersion_law`` is None (giving both
        raises :class:`~slicersim.errors.ParameterError`).
    dispersion_scale : float, optional
        Scaling of the dispersion law (> 0).
    dispersion_resolution : float, optional
        Pixels per resolution element (> 0).
    throughput : float, tuple of array_like, OpticalThroughput or str, optional
        Throughput: a number in [0, 1], a (λ [Å], T) curve, an :class:`OpticalThroughput` or
        the path of a curve file (with ``throughput_column``).
    throughput_column : str or int, optional
        Column of the throughput curve file.
    spatial_scale : float, optional
        Cell size along the slice width [arcsec].
    spatial_shape : tuple of int, optional
        (ny, nx) cells before anamorphosis.
    optics : dict of list, optional
        Thermal optics, one value per optics group for each of the keys ``temperature``
        [K], ``emissivity``, ``nelements``, ``fratio``, ``geometry`` and ``dispersed``.
    noptics : dict or int, optional
        Number of passes through each throughput component (non-negative integers), as for
        :class:`OpticalThroughput`.
    """

    anamorphosis = (1, 1)
    #: pixels a cell's monochromatic image covers (slicer: its 2-px slit image)
    pixels_per_cell = 1
    #: pixels a cell owns per native bin (one row along the dispersion; see
    #: ``slicersim.physics.conventions.detector_pixels_per_cell``)
    pixels_per_bin = 1
    kind = "generic"
    mutable_parameters = ("spectral_range", "dispersion_law", "dispersion_scale", "dispersion_resolution",
                          "spatial_scale", "spatial_shape", "resolving_power", "optics",
                          "noptics", "throughput", "throughput_column")
    #: optics keys, one value per optics group
    OPTICS_KEYS = ("temperature", "emissivity", "nelements", "fratio", "geometry", "dispersed")

    def __init__(self, spectral_range=(4000.0, 17000.0), dispersion_law=None, resolving_power=None,
                 dispersion_scale=1.0, dispersion_resolution=2.0, throughput=1.0,
                 throughput_column=None, spatial_scale=0.04, spatial_shape=(58, 58), optics=None,
                 noptics=None):
        self._params = _checked_scalars(dict(
            spectral_range=spectral_range, dispersion_law=dispersion_law, resolving_power=resolving_power,
            dispersion_scale=dispersion_scale, dispersion_resolution=dispersion_resolution,
            throughput=throughput, throughput_column=throughput_column, spatial_scale=spatial_scale,
            spatial_shape=spatial_shape, optics=optics, noptics=noptics))
        try:
            self._build()
        except ParameterError:
            raise
        except (TypeError, ValueError, KeyError, OSError) as exc:
            raise ParameterError(f"invalid spectrograph parameter: {exc}") from exc

    # -- construction ---------------------------------------------------------
    def _build(self):
        p = self._params
        lo, hi = p["spectral_range"]
        if not (0 < lo < hi) or not np.isfinite(hi):
            raise ParameterError(f"spectral_range must satisfy 0 < min < max, got {p['spectral_range']}")
        if not (np.isfinite(p["dispersion_resolution"]) and p["dispersion_resolution"] > 0
                and np.isfinite(p["dispersion_scale"]) and p["dispersion_scale"] > 0):
            raise ParameterError("dispersion_resolution and dispersion_scale must be finite and > 0")
        if not (np.isfinite(p["spatial_scale"]) and p["spatial_scale"] > 0) or min(p["spatial_shape"]) < 1:
            raise ParameterError(f"spatial_scale must be finite and > 0 and spatial_shape ≥ 1, got "
                                 f"{p['spatial_scale']} and {p['spatial_shape']}")
        law = p["dispersion_law"]
        if law is not None and p["resolving_power"] is not None:
            raise ParameterError("resolving_power is ignored when the spectrograph has a dispersion_law: "
                                 "give one of them (update(resolving_power=R, dispersion_law=None) "
                                 "switches to a resolving power)")
        if law is not None:
            if isinstance(law, str):
                llbda, cols = read_curve(law)
                law = (llbda, next(iter(cols.values())))
            self.lbda, self.lbda_edges = wavelength_grid_from_dispersion(
                law[0], law[1], p["spectral_range"], p["dispersion_scale"], p["dispersion_resolution"])
        elif p["resolving_power"] is not None:
            self.lbda, self.lbda_edges = wavelength_grid_from_resolving_power(
                p["resolving_power"], p["spectral_range"], p["dispersion_resolution"])
        else:
            raise ParameterError("a spectrograph needs a dispersion_law or a resolving_power")
        self.throughput_model = self._make_throughput(p["throughput"], p["throughput_column"], p["noptics"])
        self.throughput = self.throughput_model(self.lbda)
        self.optics = self._make_optics(p["optics"])

    @staticmethod
    def _make_throughput(throughput, column, noptics):
        if isinstance(throughput, OpticalThroughput):
            if noptics is None:
                return throughput
            merged = dict(throughput.noptics)
            merged.update({k: noptics for k in merged} if np.ndim(noptics) == 0 and not isinstance(noptics, dict)
                          else noptics)
            return OpticalThroughput(throughput.components, merged)
        if isinstance(throughput, str):
            lbda, cols = read_curve(throughput)
            if column is None:
                if len(cols) == 1:
                    column = next(iter(cols))
                else:  # several channels (e.g. Lazuli narrow/wide): never multiply them
                    raise ParameterError(
                        f"throughput file {throughput} has several columns {list(cols)}: choose one with "
                        "throughput_column (a Lazuli field: field='narrow' or 'wide')")
            if column not in cols:
                raise ParameterError(f"throughput file {throughput} has no column {column!r} ({list(cols)})")
            return OpticalThroughput({column: (lbda, cols[column])}, noptics)
        if isinstance(throughput, dict):
            comps = {}
            for name, val in throughput.items():
                if isinstance(val, str):
                    lbda, cols = read_curve(val)
                    val = (lbda, cols[column] if column in cols else next(iter(cols.values())))
                comps[name] = val
            return OpticalThroughput(comps, noptics)
        return OpticalThroughput({"total": throughput}, noptics)

    @staticmethod
    def _make_optics(optics):
        optics = dict(optics or {})
        nopt = len(optics.get("temperature", []))
        out = {"temperature": [float(t) for t in optics.get("temperature", [])],
               "emissivity": [float(e) for e in optics.get("emissivity", [0.0] * nopt)],
               "nelements": [int(n) for n in optics.get("nelements", [1] * nopt)],
               "fratio": list(optics.get("fratio", [[1.0, 1.0]] * nopt)),
               "geometry": list(optics.get("geometry", ["square"] * nopt)),
               "dispersed": [validation.flag(f"optics dispersed[{i}]", d)
                             for i, d in enumerate(optics.get("dispersed", [False] * nopt))]}
        if any(len(v) != nopt for v in out.values()):
            raise ParameterError("optics: the spectrograph optics lists must all have the same length")
        temps, eps = np.asarray(out["temperature"]), np.asarray(out["emissivity"])
        if not (np.all(np.isfinite(temps)) and np.all(temps >= 0)):
            raise ParameterError(f"optics temperature must be finite and ≥ 0 K, got {out['temperature']}")
        if not (np.all(np.isfinite(eps)) and np.all((eps >= 0) & (eps <= 1))):
            raise ParameterError(f"optics emissivity must be within [0, 1], got {out['emissivity']}")
        if any(n < 0 for n in out["nelements"]):
            raise ParameterError(f"optics nelements must be ≥ 0, got {out['nelements']}")
        for fr in out["fratio"]:
            f = np.atleast_1d(np.asarray(fr, dtype=float))
            if not (1 <= f.size <= 2 and np.all(np.isfinite(f)) and np.all(f > 0)):
                raise ParameterError(f"optics fratio must be f or (f_y, f_x), finite and > 0, got {fr!r}")
        bad = [g for g in out["geometry"] if g not in ("square", "circular")]
        if bad:
            raise ParameterError(f"unknown optics geometry {bad}: 'square' or 'circular'")
        return out

    def _merged_optics(self, optics):
        """Current optics with the keys of ``optics`` replaced; every list one value per group."""
        if optics is None:
            return None
        if not isinstance(optics, dict):
            raise ParameterError(f"optics must be a dict of per-group lists ({', '.join(self.OPTICS_KEYS)})")
        unknown = sorted(set(optics) - set(self.OPTICS_KEYS))
        if unknown:
            raise ParameterError(f"unknown optics key(s) {unknown}; accepted: {', '.join(self.OPTICS_KEYS)}")
        current = self.optics
        nexp = len(optics["temperature"]) if "temperature" in optics else len(current["temperature"])
        merged = {k: list(v) for k, v in current.items()}
        merged.update({k: list(np.atleast_1d(v)) if np.ndim(v) == 0 else list(v) for k, v in optics.items()})
        for key in self.OPTICS_KEYS:
            if len(merged[key]) != nexp:
                raise ParameterError(f"optics {key!r} needs one value per optics group: expected length "
                                     f"{nexp}, got {len(merged[key])}")
        return merged

    def updated(self, **kwargs):
        """A validated copy with ``kwargs`` changed (``self`` untouched); see :meth:`update`.

        Parameters
        ----------
        **kwargs
            As :meth:`update`.

        Returns
        -------
        Spectrograph
            The copy.
        """
        import copy
        check_parameter_names("spectrograph", kwargs, self.mutable_parameters)
        params = dict(self._params)
        kwargs = dict(kwargs)
        if "optics" in kwargs:
            kwargs["optics"] = self._merged_optics(kwargs["optics"])
        if kwargs.get("resolving_power") is not None and params["dispersion_law"] is not None \
                and "dispersion_law" not in kwargs:
            raise ParameterError("this spectrograph's grid comes from its dispersion_law: resolving_power "
                                 "would be ignored; pass dispersion_law=None with it to switch to a "
                                 "resolving-power grid")
        if kwargs.get("dispersion_law") is not None and "resolving_power" not in kwargs:
            params["resolving_power"] = None          # the new law defines the grid
        params.update(kwargs)
        params = _checked_scalars(params)
        new = copy.copy(self)
        object.__setattr__(new, "_params", params)
        try:
            new._build()
        except ParameterError:
            raise
        except (TypeError, ValueError, KeyError, OSError) as exc:
            raise ParameterError(f"invalid spectrograph parameter: {exc}") from exc
        return new

    def update(self, **kwargs):
        """Change mutable parameters and rebuild everything that depends on them, atomically:
        a copy is rebuilt and validated first; on error (:class:`~slicersim.errors.ParameterError`)
        nothing changes.

        Parameters
        ----------
        **kwargs
            Names of ``mutable_parameters``.  ``optics`` may give only some keys (the others are
            kept); each list needs one value per optics group.  ``noptics`` (dict per component or
            one int) applies to the current throughput.  ``resolving_power`` with a dispersion-law
            grid raises unless ``dispersion_law=None`` is passed too (then the grid switches to the
            resolving power); a new ``dispersion_law`` replaces a resolving-power grid.

        Returns
        -------
        None
            Changed in place.
        """
        self._adopt(self.updated(**kwargs))

    def set_throughput(self, throughput, column=None, noptics=None):
        """Replace the throughput.  Takes effect at once (the owning Simulation sees the new version).

        Parameters
        ----------
        throughput : float, tuple of array_like, str, OpticalThroughput or dict
            A float, a (λ [Å], T) curve, a file, an :class:`OpticalThroughput` or a per-component
            dict.
        column : str or int, optional
            For a file with several columns, the one picked (default: the current
            ``throughput_column`` when the file has it).
        noptics : dict or int, optional
            As in :class:`OpticalThroughput`.

        Returns
        -------
        None
            Changed in place.
        """
        if column is None and isinstance(throughput, str):
            current = self._params["throughput_column"]
            if current is not None:
                _, cols = read_curve(throughput)
                if current in cols:
                    column = current
        self.update(throughput=throughput, throughput_column=column, noptics=noptics)

    # -- derived quantities -----------------------------------------------------
    @property
    def spectral_range(self):
        return self._params["spectral_range"]

    @property
    def dispersion_resolution(self):
        """Detector pixels per resolution element."""
        return self._params["dispersion_resolution"]

    @property
    def spatial_scale(self):
        """Cell size [arcsec] (cells are treated as squares of this side)."""
        return self._params["spatial_scale"]

    @property
    def shape(self):
        """Cube spatial shape (ny, nx) after anamorphosis."""
        ny, nx = self._params["spatial_shape"]
        return ny * self.anamorphosis[0], nx * self.anamorphosis[1]

    @property
    def nlbda(self):
        return self.lbda.size

    @property
    def dlbda(self):
        """Bin widths Δλ [Å]."""
        return np.diff(self.lbda_edges)

    @property
    def resolving_power(self):
        """R = λ / Δλ / dispersion_resolution."""
        return self.lbda / self.dlbda / self.dispersion_resolution

    @property
    def lsf_sigma(self):
        """Gaussian LSF σ along λ [bins] = dispersion_resolution / 2."""
        return self.dispersion_resolution / 2.0

    @property
    def cell_solid_angle(self):
        """Solid angle of one cell [sr], sin²(s) with s in radians."""
        return float(np.sin(self.spatial_scale * ARCSEC) ** 2)

    def dispersed_thermal_radiance(self, lbda):
        """Photon radiance of the dispersed internal optics Σ ε n B_ph(λ, T) [ph/s/m²/sr/Å].

        Parameters
        ----------
        lbda : array_like
            Wavelengths [Å].

        Returns
        -------
        numpy.ndarray
            The radiance [ph/s/m²/sr/Å], of the shape of ``lbda``.
        """
        o = self.optics
        total = np.zeros_like(np.asarray(lbda, dtype=float))
        for temp, eps, n, disp in zip(o["temperature"], o["emissivity"], o["nelements"], o["dispersed"]):
            if disp and eps * n:
                total = total + eps * n * photon_radiance(lbda, temp)
        return total

    def undispersed_optics(self):
        """The optics after the disperser.

        Returns
        -------
        list of tuple
            (temperature [K], emissivity, nelements, solid angle [sr]) of each such optics group.
        """
        o = self.optics
        rows = []
        for temp, eps, n, fr, geo, disp in zip(o["temperature"], o["emissivity"], o["nelements"],
                                               o["fratio"], o["geometry"], o["dispersed"]):
            if not disp:
                rows.append((temp, eps, n, solid_angle_from_fratio(fr, geo)))
        return rows

    def apply_lsf(self, values, axis=0):
        """Apply this spectrograph's Gaussian LSF along ``axis`` (``slicersim.physics.lsf.apply_lsf``).

        Parameters
        ----------
        values : array_like
            Values on the wavelength grid along ``axis``.
        axis : int, optional
            The wavelength axis.

        Returns
        -------
        numpy.ndarray
            The convolved values, of the shape of ``values``.
        """
        return apply_lsf(values, self.lsf_sigma, axis=axis)

    def show_throughput(self, ax=None, savefile=None):
        """Figure of the throughput [fraction of photons] on the grid (λ [Å]) and of each of its
        components; see :func:`slicersim.plotting.spectra.plot_curves`.

        Parameters
        ----------
        ax : matplotlib.axes.Axes, optional
            None (new figure) or an Axes.
        savefile : str, os.PathLike or file object, optional
            If given the figure is saved there.

        Returns
        -------
        matplotlib.figure.Figure
            The figure.
        """
        from slicersim.plotting import plot_curves
        model = self.throughput_model
        curves = {"total": self.throughput}
        if len(model.components) > 1:
            for name, comp in model.components.items():
                power = model.noptics[name]
                curves[f"{name}" + (f" (× {power})" if power != 1 else "")] = \
                    OpticalThroughput({name: comp}, {name: power})(self.lbda)
        return plot_curves(self.lbda, curves, "throughput [fraction of photons]",
                           title=f"{type(self).__name__} throughput", ax=ax, savefile=savefile, ylim=(0, 1.02))


class SlicerSpectrograph(Spectrograph):
    """Image slicer: 1×2 anamorphosis, each cell imaged on 2 detector pixels (along the
    dispersion: the slit image, shared by consecutive bins, so 1 pixel per cell and bin).

    Parameters
    ----------
    spectral_range, dispersion_law, resolving_power, dispersion_scale, dispersion_resolution, \
throughput, throughput_column, spatial_scale, spatial_shape, optics, noptics
        As for :class:`Spectrograph`.
    """
    anamorphosis = (1, 2)
    pixels_per_cell = 2
    pixels_per_bin = 1
    kind = "slicer"


class MLASpectrograph(Spectrograph):
    """Micro-lens array: square cells, cross-dispersion profile on the detector.

    Each spaxel spectrum spreads over ~2 × xdisp_width_insigma × σ_xdisp pixels across
    the dispersion.

    Parameters
    ----------
    *args, **kwargs
        The parameters of :class:`Spectrograph`.
    xdisp_sigma_spectral : float, optional
        Wavelength-dependent part of the cross-dispersion σ [px at 1 µm].
    xdisp_sigma : float, optional
        Constant part of the cross-dispersion σ [px].
    xdisp_width_insigma : float, optional
        Extraction width [σ].
    """
    anamorphosis = (1, 1)
    kind = "mla"

    def __init__(self, *args, xdisp_sigma_spectral=0.9, xdisp_sigma=0.3, xdisp_width_insigma=10,
                 **kwargs):
        self.xdisp_sigma_spectral = float(xdisp_sigma_spectral)
        self.xdisp_sigma = float(xdisp_sigma)
        self.xdisp_width_insigma = float(xdisp_width_insigma)
        super().__init__(*args, **kwargs)

    def xdisp_sigma_at(self, lbda):
        """Cross-dispersion σ [px] at λ [Å].

        Parameters
        ----------
        lbda : array_like
            Wavelengths [Å].

        Returns
        -------
        numpy.ndarray
            σ [px].
        """
        return np.hypot(self.xdisp_sigma_spectral * np.asarray(lbda) / 1e4, self.xdisp_sigma)

    @property
    def pixels_per_bin(self):
        """Pixels a spaxel owns per native bin: its cross-dispersion strip (= pixels_per_cell)."""
        return self.pixels_per_cell

    @property
    def pixels_per_cell(self):
        """Pixels summed across the dispersion per spaxel (at 1 µm)."""
        return max(1, int(np.ceil(2 * self.xdisp_width_insigma * float(self.xdisp_sigma_at(1e4)))))
