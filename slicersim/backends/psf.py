"""Point-source PSF cubes: OpenCL host wrappers and their NumPy twins.

``psf_cube`` returns P[λ, y, x], the fraction of a point source's flux in
every cell at every wavelength (flux outside the field is lost, never
renormalised); ``psf_cells`` the same for a list of cells only.

Profiles
--------
"gaussian": the Airy-equivalent Gaussian of :func:`slicersim.physics.psf.gaussian_psf_sigmas`
    (σ_t ∝ λ, jitter and instrumental blur added in quadrature), integrated
    exactly over each cell (erf product).
"airy": the diffraction pattern of an annular pupil (D, ε = D_int/D_ext),
    I = (1 − ε²) k²/(4π) g(k r)² per cell² (k = π D s/λ, r in cells), integrated
    over each cell by an o × o product rule (``grid``), convolved with the
    Gaussian jitter γ = guiding/s (both axes) and the instrumental blur σ_inst
    (x only) and binned to cells.  Blur and binning are done in one step: a
    sub-sample of weight w at p cells from a cell's lower edge contributes
    w · ½[erf((1−p)/√2σ) + erf(p/√2σ)] to that cell (exact for a point of light;
    σ_x = √(γ² + σ_inst²), σ_y = γ).  These 1-D weights do not depend on λ, so
    P_λ = M_y S_λ M_xᵀ with banded M: two small banded contractions per λ.
    Sub-samples cover the requested cells plus a margin of ⌈8σ⌉ cells on each
    side so that light from outside scatters in (Gaussian tails beyond 8σ,
    < 1e-15, are dropped).

Grids (``grid``)
----------------
"exact": o × o sub-cell centres X_k + (j + ½)/o, weights 1/o² (midpoint rule).
    With jitter this converges spectrally: the Airy pattern is band-limited
    (spatial frequencies below D/λ) and the Gaussian kernel damps the aliases.
    Lazuli narrow field (R_Airy = 0.84 cell at 4000 Å, jitter 0.25 cell),
    max error / peak: o = 1: 0.8, 2: 4e-3, 3: 8e-5, 4: 3e-7, 5: 1e-10; wide
    field (R_Airy = 0.42 cell, jitter 0.125 cell) o = 3: 6e-3, 4: 1.2e-3,
    5: 2.3e-4, 9: 1.3e-9.  Without any blur on an axis it is only O(1/o²)
    (o = 4: ~5e-3).
"gauss": o × o Gauss–Legendre nodes per cell: spectrally accurate when an
    axis has no blur (the integrand is then smooth inside each cell), worse
    than "exact" with jitter.  Also an independent cross-check of "exact".
"reference": NumPy only, Airy only, ε = 0: slicersim 1.0's sub-sample grid
    x_u = linspace(1, nx, o nx) − nx/2 − ½ (not the sub-cell centres), its
    sampled-then-scaled normalisation p = [2J1(u)/u]² s²/o² / (4R²/(πρ²)),
    u = π r ρ / R, R = 1.22 λ/D, ρ = j₁,₁/π, then scipy ``gaussian_filter``
    (σ = o γ along y, o √(γ² + σ_inst²) along x, mode "reflect", truncate 4)
    and o × o block sums.  Its PSFs sum to 0.3–1.9 % more than 1.  Reproduces
    the reference cases' Airy cubes to 2e-8 of the peak.

Oversampling: an integer o (o × o per cell), a pair (o_y, o_x), or "auto"
(default): per axis, the smallest o whose aliasing bound
(:func:`slicersim.physics.psf.midpoint_oversampling`) is below 1e-4 of the peak at
the shortest wavelength of the call — Lazuli narrow field (4, 3), 3e-7 of the
peak; wide field (8, 4), 7e-8 (the strongly blurred x axis needs few
sub-samples, the jitter-only y axis more); ``auto_oversampling`` returns the
pair (pass it explicitly when building a cube in wavelength blocks); see
benchmarks/results/psf_speed_accuracy.md.

The OpenCL host side (sub-sample layouts, launches) is :mod:`slicersim.backends.psf_opencl`.
Backends agree to ~1e-13 of the peak (Gaussian ~1e-16; Airy: the kernel's
own J1, |ΔJ1| <= 2e-12, see ``kernels/psf.cl``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter
from scipy.special import j1

from slicersim.backends import opencl
from slicersim.backends.dispatch import DEFAULT_MAX_BYTES, chunk_ranges, resolve_backend
from slicersim.backends.precision import check_precision, real_dtype, resolve_precision
from slicersim.backends.psf_opencl import KERNELS, airy_window_opencl, gaussian_opencl
from slicersim.constants import AIRY_RHO, ARCSEC
from slicersim.errors import ParameterError
from slicersim.validation import array as validation_array, choice, number, shape as validation_shape, short_repr
from slicersim.physics.psf import (airy_encircled_energy, airy_intensity, airy_wavenumber, blur_bin_taps,
                           blur_margin, cell_quadrature, gaussian_psf_cells, gaussian_psf_fractions,
                           gaussian_psf_sigmas, jinc, midpoint_oversampling)

__all__ = ["psf_cube", "psf_cube_device", "DevicePSF", "psf_cells", "PSFOptics", "psf_optics", "auto_oversampling", "bessel_j1",
           "airy_encircled_energy", "PROFILES", "GRIDS", "DEFAULT_OVERSAMPLING"]

PROFILES = ("gaussian", "airy")
DEFAULT_OVERSAMPLING = "auto"
GRIDS = ("exact", "gauss", "reference")


# --------------------------------------------------------------------------- #
#  public API                                                                  #
# --------------------------------------------------------------------------- #
@dataclass(frozen=True)
class PSFOptics:
    """The optics a PSF cube is computed for (keywords of :func:`psf_cube`).

    sigma_ref_arcsec : Gaussian σ at 1 µm [arcsec] (Gaussian profile only)
    spatial_scale : cell size s [arcsec];  guiding_sigma : achromatic Gaussian jitter [arcsec] (both
        axes);  instrumental_sigma : spectrograph blur along x [cells] (these three required)
    diameter, obscuration : outer pupil diameter D [m], ε = D_int/D_ext (Airy)
    oversampling : "auto", o, or (o_y, o_x) sub-samples per cell (Airy; see module doc)
    grid : sub-sample rule, "exact", "gauss" or "reference" (Airy; see module doc)
    """
    sigma_ref_arcsec: float | None = None
    spatial_scale: float | None = None
    guiding_sigma: float | None = None
    instrumental_sigma: float | None = None
    diameter: float = 3.0
    obscuration: float = 0.0
    oversampling: object = DEFAULT_OVERSAMPLING
    grid: str = "exact"


_REQUIRED_OPTICS = ("spatial_scale", "guiding_sigma", "instrumental_sigma")


def psf_optics(optics=None, **keywords):
    """A :class:`PSFOptics` from ``optics`` or from its fields as keywords (not both); the grid
    checked and the required fields present (ParameterError naming them)."""
    fields = PSFOptics.__dataclass_fields__
    unknown = sorted(set(keywords) - set(fields))
    if unknown:
        raise ParameterError(f"unknown PSF keyword(s) {', '.join(map(repr, unknown))}; valid: {', '.join(fields)}")
    if optics is not None:
        if keywords:
            raise ParameterError(f"give optics= or its keywords ({', '.join(sorted(keywords))}), not both")
        if not isinstance(optics, PSFOptics):
            raise ParameterError(f"optics must be a PSFOptics, got {short_repr(optics)}")
    else:
        optics = PSFOptics(**keywords)
    missing = [name for name in _REQUIRED_OPTICS if getattr(optics, name) is None]
    if missing:
        raise ParameterError(f"the PSF needs {', '.join(missing)}")
    choice("grid", optics.grid, GRIDS)
    return optics


def psf_cube(lbda, shape, position=(0.0, 0.0), profile="gaussian", *, optics=None, backend="auto",
             max_bytes=DEFAULT_MAX_BYTES, precision="auto", **optics_keywords):
    """PSF cube P[λ, y, x] (nλ, ny, nx) float64: fraction of the flux in each cell.

    Parameters
    ----------
    lbda : (nλ,) wavelengths [Å]
    shape : (ny, nx) cells
    position : (x0, y0) source position [cells] from the field centre
    profile : "gaussian" or "airy"
    optics : a :class:`PSFOptics`, or its fields as keywords (``sigma_ref_arcsec``,
        ``spatial_scale``, ``guiding_sigma``, ``instrumental_sigma``, ``diameter``, ``obscuration``,
        ``oversampling``, ``grid``)
    backend : "auto", "opencl" or "numpy" (grid="reference": NumPy only)
    max_bytes : memory budget of the temporaries [bytes]; wavelengths go in chunks
    precision : "auto", "double" or "single" kernels (:mod:`slicersim.backends.precision`; single:
        ≤ 1e-5 of the peak against double, measured 3.9e-7 for a source in the field; the result is
        float64 either way)
    """
    optics = psf_optics(optics, **optics_keywords)
    lbda, shape, position = _check(lbda, shape, position, profile)
    ny, nx = shape
    name, precision = _backend(backend, optics.grid, precision)
    if profile == "gaussian":
        sig_y, sig_x = _gaussian_sigmas(lbda, optics)
        if name == "opencl":
            return gaussian_opencl(sig_y, sig_x, shape, position, max_bytes, precision)
        return gaussian_psf_fractions(sig_y, sig_x, shape, position)
    airy = _AiryParams(lbda, optics)
    if optics.grid == "reference":
        return _airy_reference_numpy(airy, shape, position, max_bytes)
    window = (0, ny, 0, nx)
    if name == "opencl":
        return airy_window_opencl(airy, shape, position, window, max_bytes, precision=precision)
    return _airy_window_numpy(airy, shape, position, window, max_bytes)


@dataclass(frozen=True)
class DevicePSF:
    """A PSF cube P[λ, y, x] (C order, float64 or float32: ``dtype``) left in an OpenCL device buffer."""
    buffer: object
    shape: tuple
    dtype: np.dtype = np.dtype(np.float64)

    @property
    def nbytes(self):
        return int(np.prod(self.shape)) * np.dtype(self.dtype).itemsize

    def to_host(self):
        """The cube as a float64 NumPy array (nλ, ny, nx) (one device → host copy)."""
        out = np.empty(self.shape, self.dtype)
        if out.size:
            opencl.from_device(out, self.buffer)
        return out.astype(np.float64, copy=False)


def psf_cube_device(lbda, shape, position=(0.0, 0.0), profile="airy", *, optics=None, backend="auto",
                    max_bytes=DEFAULT_MAX_BYTES, out_buffer=None, precision="auto", **optics_keywords):
    """:func:`psf_cube` left on the OpenCL device when it is computed there: a :class:`DevicePSF`
    (Airy, grid "exact"/"gauss", OpenCL backend), else the NumPy array of :func:`psf_cube`.

    Saves the device → host → device round trip of the cube (28 MB for the Lazuli narrow field)
    for device consumers such as :func:`slicersim.backends.cube.detector_block`.  ``out_buffer``:
    a device buffer of at least 8 nλ ny nx bytes (single precision: 4) to reuse (None: a new one);
    other parameters as :func:`psf_cube` (``precision`` "single" leaves a float32 block).
    """
    optics = psf_optics(optics, **optics_keywords)
    name, precision_used = _backend(backend, optics.grid, precision)
    if profile != "airy" or optics.grid == "reference" or name != "opencl":
        return psf_cube(lbda, shape, position, profile, optics=optics, backend=backend, max_bytes=max_bytes,
                        precision=precision)
    lbda, shape, position = _check(lbda, shape, position, profile)
    ny, nx = shape
    airy = _AiryParams(lbda, optics)
    dtype = real_dtype(precision_used)
    if out_buffer is None:
        out_buffer = opencl.device_buffer(dtype.itemsize * lbda.size * ny * nx)
    airy_window_opencl(airy, shape, position, (0, ny, 0, nx), max_bytes, out_buffer=out_buffer,
                        precision=precision_used)
    return DevicePSF(out_buffer, (lbda.size, ny, nx), dtype)


def _check_cells(cells, shape):
    """(iy, ix) int index arrays of cells within the field ``shape``."""
    if cells is None:
        raise ParameterError("psf_cells needs cells=(iy, ix)")
    try:
        iy, ix = (np.asarray(c).ravel() for c in cells)
    except (TypeError, ValueError):
        raise ParameterError(f"cells must be two integer index arrays (iy, ix), got {short_repr(cells)}") from None
    if iy.shape != ix.shape or not (np.issubdtype(iy.dtype, np.integer) or iy.size == 0) \
            or not (np.issubdtype(ix.dtype, np.integer) or ix.size == 0):
        raise ParameterError("cells must be two integer index arrays of the same length")
    iy, ix = iy.astype(int), ix.astype(int)
    ny, nx = shape
    if iy.size and (iy.min() < 0 or iy.max() >= ny or ix.min() < 0 or ix.max() >= nx):
        raise ParameterError(f"cells must lie within the field {shape}")
    return iy, ix


def psf_cells(lbda, shape, position=(0.0, 0.0), cells=None, profile="gaussian", *, optics=None, backend="auto",
              max_bytes=DEFAULT_MAX_BYTES, precision="auto", **optics_keywords):
    """P restricted to ``cells`` = (iy, ix) index arrays: (nλ, ncell) float64.

    Same parameters as :func:`psf_cube`.  Airy: only the bounding box of the
    cells plus the blur margin is computed (an extraction aperture of ~160
    cells costs a few % of the cube); Gaussian: erf products (NumPy, cheap).
    """
    optics = psf_optics(optics, **optics_keywords)
    lbda, shape, position = _check(lbda, shape, position, profile)
    iy, ix = _check_cells(cells, shape)
    check_precision(precision)
    if iy.size == 0:
        return np.zeros((lbda.size, 0))
    if profile == "gaussian":
        sig_y, sig_x = _gaussian_sigmas(lbda, optics)
        return gaussian_psf_cells(sig_y, sig_x, shape, position, (iy, ix))
    airy = _AiryParams(lbda, optics)
    name, precision = _backend(backend, optics.grid, precision)
    if optics.grid == "reference":
        return _airy_reference_numpy(airy, shape, position, max_bytes)[:, iy, ix]
    j0, k0 = int(iy.min()), int(ix.min())
    window = (j0, int(iy.max()) + 1, k0, int(ix.max()) + 1)
    if name == "opencl":
        box = airy_window_opencl(airy, shape, position, window, max_bytes, precision=precision)
    else:
        box = _airy_window_numpy(airy, shape, position, window, max_bytes)
    return box[:, iy - j0, ix - k0]


def auto_oversampling(lbda, *, spatial_scale, guiding_sigma, instrumental_sigma, diameter=3.0):
    """(o_y, o_x) that ``oversampling="auto"`` picks for wavelengths ``lbda`` [Å].

    "auto" depends on the shortest wavelength of a call: a caller that builds
    a cube in wavelength blocks should compute this once for the whole grid
    and pass it to every block, so that the cube does not depend on the blocks.
    """
    lbda = np.asarray(lbda, dtype=float)
    gamma = float(guiding_sigma) / float(spatial_scale)
    kmax = float(airy_wavenumber(lbda.min(), diameter, spatial_scale))
    return _auto_pair(kmax, gamma, float(np.hypot(gamma, instrumental_sigma)))


def _auto_pair(kmax, sigma_y, sigma_x):
    return midpoint_oversampling(sigma_y, kmax), midpoint_oversampling(sigma_x, kmax)


def bessel_j1(x, backend="auto"):
    """J1(x): the OpenCL kernel's approximation ("opencl") or scipy's ("numpy")."""
    x = np.ascontiguousarray(np.ravel(x), dtype=np.float64)
    if resolve_backend(backend) == "numpy":
        return j1(x)
    if np.any(x < 0):
        raise ParameterError("x: bessel_j1 (OpenCL) is defined for x >= 0")
    vw = opencl.preferred_vector_width(8)
    n = -(-x.size // vw) * vw
    xp = np.concatenate([x, np.zeros(n - x.size)])
    out = np.empty(n)
    kern = opencl.get_kernel(KERNELS, "bessel_j1_values", (f"-DVW={vw}",))
    d_out = opencl.device_buffer(8 * n)
    if n:
        opencl.launch(kern, (n // vw,), None, opencl.to_device(xp), d_out)
        opencl.from_device(out, d_out)
    return out[:x.size]


# --------------------------------------------------------------------------- #
#  helpers                                                                     #
# --------------------------------------------------------------------------- #
def _check(lbda, shape, position, profile):
    """(λ (nλ,) [Å] float64, (ny, nx), (x0, y0) [cells]) checked; ``profile`` one of :data:`PROFILES`."""
    choice("profile", profile, PROFILES)
    lbda = np.ascontiguousarray(np.atleast_1d(validation_array("lbda [Å]", lbda)))
    if lbda.ndim != 1 or np.any(lbda <= 0):
        raise ParameterError("lbda must be a 1-D array of positive wavelengths [Å]")
    ny, nx = validation_shape("shape", shape)
    if isinstance(position, (str, bytes)) or np.size(position) != 2:
        raise ParameterError(f"point-source position must be (x0, y0) [cells], got {short_repr(position)}")
    x0, y0 = (number(f"point-source position {axis}", p) for axis, p in zip(("x0", "y0"), position))
    return lbda, (ny, nx), (x0, y0)


def _backend(backend, grid, precision="double"):
    """(backend, precision) of a PSF computation (:func:`~slicersim.backends.precision.resolve_precision`)."""
    if grid == "reference":
        if backend == "opencl":
            raise ParameterError("grid='reference' is implemented in NumPy only (backend='numpy' or 'auto')")
        if precision == "single":
            raise ParameterError("grid='reference' is NumPy only, in double precision: precision='single' "
                                 "is not available for it")
        resolve_precision(precision, "numpy", "psf")      # validates the name
        return "numpy", "double"
    return resolve_precision(precision, backend, "psf")


def _gaussian_sigmas(lbda, optics):
    """(σ_y, σ_x) (nλ,) [cells] of the Gaussian profile."""
    if optics.sigma_ref_arcsec is None:
        raise ParameterError("the Gaussian profile needs sigma_ref_arcsec")
    return gaussian_psf_sigmas(lbda, optics.sigma_ref_arcsec, optics.spatial_scale, optics.guiding_sigma,
                               optics.instrumental_sigma)


class _AiryParams:
    """Validated Airy-cube parameters; k = π D s/λ [rad/cell], γ, σ_x [cells], (o_y, o_x)."""

    def __init__(self, lbda, optics):
        self.lbda = lbda
        self.scale = number("spatial_scale [arcsec]", optics.spatial_scale, low=0, low_open=True)
        self.diameter = number("diameter [m]", optics.diameter, low=0, low_open=True)
        self.eps = number("obscuration", optics.obscuration, low=0, high=1, high_open=True)
        self.grid = optics.grid
        guiding = number("guiding_sigma [arcsec]", optics.guiding_sigma, low=0)
        self.sigma_inst = number("instrumental_sigma [cells]", optics.instrumental_sigma, low=0)
        if self.grid == "reference" and self.eps > 0:
            raise ParameterError("grid='reference' reproduces slicersim 1.0, which has no central obscuration")
        self.gamma = guiding / self.scale
        self.sigma_y = self.gamma
        self.sigma_x = float(np.hypot(self.gamma, self.sigma_inst))
        self.kwave = airy_wavenumber(lbda, self.diameter, self.scale)
        self.pref = (1.0 - self.eps**2) * self.kwave**2 / (4.0 * np.pi)
        self.o_y, self.o_x = self._oversampling(optics.oversampling)
        if self.grid == "reference" and self.o_y != self.o_x:
            raise ParameterError("grid='reference' needs one oversampling factor for both axes")

    def _oversampling(self, oversampling):
        if isinstance(oversampling, str):
            if oversampling != "auto":
                raise ParameterError(f"oversampling must be 'auto', an integer or (o_y, o_x), got {oversampling!r}")
            if self.grid == "reference":
                return 3, 3
            return _auto_pair(float(self.kwave.max()), self.sigma_y, self.sigma_x)
        try:
            pair = np.broadcast_to(np.asarray(oversampling, dtype=float), (2,))
        except (TypeError, ValueError):
            raise ParameterError(f"oversampling must be 'auto', an integer or (o_y, o_x), got "
                                 f"{short_repr(oversampling)}") from None
        if not np.all(pair == np.round(pair)) or np.any(pair < 1):
            raise ParameterError(f"oversampling must be positive integers, got {oversampling!r}")
        return int(pair[0]), int(pair[1])

    def axis(self, c0, c1, n, centre, sigma, o):
        """Sub-sample offsets from the source [cells] covering cells [c0, c1) ± margin, and taps."""
        t, _ = cell_quadrature(o, self.grid)
        m = blur_margin(sigma)
        cells = np.arange(c0 - m, c1 + m, dtype=float) - n / 2.0
        offsets = ((cells[:, None] + t[None, :]) - centre).ravel()
        return offsets, blur_bin_taps(o, self.grid, sigma)


def _banded(taps, nout, o):
    """Dense (nout, o (nout − 1) + len(taps)) matrix M[j, o j + e] = taps[e]."""
    w = taps.size
    m = np.zeros((nout, o * (nout - 1) + w))
    for j in range(nout):
        m[j, o * j:o * j + w] = taps
    return m


# --------------------------------------------------------------------------- #
#  NumPy twins                                                                 #
# --------------------------------------------------------------------------- #
def _airy_window_numpy(airy, shape, position, window, max_bytes):
    """P for output cells [j0, j1) × [k0, k1): (nλ, j1 − j0, k1 − k0)."""
    ny, nx = shape
    x0, y0 = position
    j0, j1, k0, k1 = window
    dy, ky = airy.axis(j0, j1, ny, y0, airy.sigma_y, airy.o_y)
    dx, kx = airy.axis(k0, k1, nx, x0, airy.sigma_x, airy.o_x)
    nyo, nxo = j1 - j0, k1 - k0
    my, mx = _banded(ky, nyo, airy.o_y), _banded(kx, nxo, airy.o_x)
    # r = 0 exactly would give 0/0: 1e-200 cells gives 2 J1(v)/v = 1 to rounding
    r = np.maximum(np.sqrt(dy[:, None] ** 2 + dx[None, :] ** 2), 1e-200)   # (nys, nxs) cells
    nys, nxs = r.shape
    out = np.empty((airy.lbda.size, nyo, nxo))
    for l0, l1 in chunk_ranges(airy.lbda.size, 8 * 3 * r.size, max_bytes):
        s = _airy_samples_numpy(r, airy.kwave[l0:l1], airy.pref[l0:l1], airy.eps)
        # P_l = M_y S_l M_xᵀ as two large GEMMs (much faster than a stack of small ones)
        u = my @ s.transpose(1, 0, 2).reshape(nys, -1)                       # (nyo, n nxs)
        p = u.reshape(-1, nxs) @ mx.T                                         # (nyo n, nxo)
        out[l0:l1] = p.reshape(nyo, l1 - l0, nxo).transpose(1, 0, 2)
    return out


def _airy_samples_numpy(r, kwave, pref, eps):
    """S[l] = pref_l g(k_l r)² (nλ, *r.shape), with scipy's J1 (r > 0)."""
    v = kwave[:, None, None] * r[None]
    g = j1(v)
    if eps > 0:
        g -= eps * j1(eps * v)
    g *= 2.0 / (1.0 - eps**2)
    g /= v
    g *= g
    g *= pref[:, None, None]
    return g


def _airy_reference_numpy(airy, shape, position, max_bytes):
    """slicersim 1.0's Airy cube (its sub-sample grid, normalisation and blur)."""
    ny, nx = shape
    x0, y0 = position
    o, s = airy.o_y, airy.scale
    xu = np.linspace(1, nx, o * nx) - nx / 2.0 - 0.5
    yv = np.linspace(1, ny, o * ny) - ny / 2.0 - 0.5
    r_arcsec = s * np.sqrt((xu[None, :] - x0) ** 2 + (yv[:, None] - y0) ** 2)
    out = np.empty((airy.lbda.size, ny, nx))
    sigma = (0.0, o * airy.sigma_y, o * airy.sigma_x)
    for l0, l1 in chunk_ranges(airy.lbda.size, 8 * 4 * r_arcsec.size, max_bytes):
        R = (1.22 * airy.lbda[l0:l1] * 1e-10 / airy.diameter / ARCSEC)[:, None, None]   # arcsec
        sub = jinc(np.pi * r_arcsec[None] * AIRY_RHO / R) ** 2 * s**2 / o**2 \
            / (4.0 * R**2 / (np.pi * AIRY_RHO**2))
        if sigma[1] > 0 or sigma[2] > 0:
            sub = gaussian_filter(sub, sigma, mode="reflect", truncate=4.0)
        out[l0:l1] = sub.reshape(l1 - l0, ny, o, nx, o).sum(axis=(2, 4))
    return out
