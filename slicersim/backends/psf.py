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
_KERNELS = "psf.cl"
_FUSED_MAX_ROWS = 17      # jitter margins up to 8 cells: Airy + row blur in one kernel
_COL_ROWS_CPU = 4         # blur_bin_cols rows per work item on CPUs: 4 independent FMA chains
_CHUNK_LBDA = 16          # wavelengths per OpenCL launch: the intermediate rows stay in cache (~3 MB)


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
            return _gaussian_opencl(sig_y, sig_x, shape, position, max_bytes, precision)
        return gaussian_psf_fractions(sig_y, sig_x, shape, position)
    airy = _AiryParams(lbda, optics)
    if optics.grid == "reference":
        return _airy_reference_numpy(airy, shape, position, max_bytes)
    window = (0, ny, 0, nx)
    if name == "opencl":
        return _airy_window_opencl(airy, shape, position, window, max_bytes, precision=precision)
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
    _airy_window_opencl(airy, shape, position, (0, ny, 0, nx), max_bytes, out_buffer=out_buffer,
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
        box = _airy_window_opencl(airy, shape, position, window, max_bytes, precision=precision)
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
    kern = opencl.get_kernel(_KERNELS, "bessel_j1_values", (f"-DVW={vw}",))
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


def _offset_keys(d):
    """|d| [cells] as integers (units of 2^-44 cell): equal keys, equal Airy intensity to ~1e-14."""
    return np.round(np.abs(d) * 2.0**44).astype(np.int64)


def _mirror_blocks(dx, vw):
    """(nw, 2) int32: x blocks of VW sub-samples to evaluate, and the block holding the
    same |dx| in reverse order (its values are the reversed block's) or -1."""
    keys = _offset_keys(dx).reshape(-1, vw)
    seen, rows = {}, []
    for w in range(keys.shape[0]):
        partner = seen.pop(tuple(keys[w][::-1]), None)
        if partner is not None:
            rows[partner][1] = w
        else:
            seen.setdefault(tuple(keys[w]), len(rows))
            rows.append([w, -1])
    return np.ascontiguousarray(rows, dtype=np.int32).reshape(-1, 2)


def _x_layout(c0, nxo_p, mx, nx, x0, t, vw):
    """De-interleaved x sub-samples for output cells [c0, c0 + nxo_p) [window indices]:
    (xoff, ncx, dx, xblocks).  The window starts mx + xoff cells before c0; xoff < VW is
    the shift that pairs the most mirror blocks (a centred source: half of them)."""
    best = None
    for xoff in range(vw):
        ncx = -(-(nxo_p + 2 * mx + xoff) // vw) * vw
        cells = np.arange(c0 - mx - xoff, c0 - mx - xoff + ncx, dtype=float) - nx / 2.0
        dx = np.ascontiguousarray((t[:, None] + cells[None, :] - x0).ravel())
        blocks = _mirror_blocks(dx, vw)
        if best is None or blocks.shape[0] < best[3].shape[0]:
            best = (xoff, ncx, dx, blocks)
        if 2 * blocks.shape[0] <= ncx * t.size // vw + 1:      # every block paired: done
            break
    return best


def _output_mirror_blocks(c0, nxo_p, nx, x0, kx, vw):
    """(nwo, 2) int32: output blocks of VW cells to compute and the block whose cells
    mirror them about the source in reverse order (or -1).  Mirroring needs symmetric
    taps kx (to 1e-15) and cell centres at exactly opposite offsets (keys to 2^-44 cell)."""
    nb = nxo_p // vw
    centres = np.arange(c0, c0 + nxo_p, dtype=float) + 0.5 - nx / 2.0 - x0
    keys = np.round(centres * 2.0**44).astype(np.int64).reshape(nb, vw)
    symmetric = np.abs(kx - kx[::-1]).max() <= 1e-15 * np.abs(kx).max()
    where = {tuple(keys[w]): w for w in range(nb)}
    rows, covered = [], set()
    for w in range(nb):
        if w in covered:
            continue
        partner = where.get(tuple(-keys[w][::-1])) if symmetric else None
        if partner is not None and partner != w and partner not in covered and partner > w:
            covered.add(partner)
            rows.append([w, partner])
        else:
            rows.append([w, -1])
    return np.ascontiguousarray(rows, dtype=np.int32).reshape(-1, 2)


def _shared_rows(dy):
    """int32 code per sub-sample row: -1 evaluate; 2 s evaluate and keep in slot s;
    2 s + 1 read slot s (an earlier row with the same |dy|)."""
    keys = _offset_keys(dy)
    first, counts = {}, {}
    for i, k in enumerate(keys):
        counts[k] = counts.get(k, 0) + 1
    code = np.full(keys.size, -1, dtype=np.int32)
    for i, k in enumerate(keys):
        if counts[k] < 2:
            continue
        if k in first:
            code[i] = 2 * first[k] + 1
        else:
            first[k] = len(first)
            code[i] = 2 * first[k]
    return code


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


# --------------------------------------------------------------------------- #
#  OpenCL                                                                      #
# --------------------------------------------------------------------------- #
def _gaussian_opencl(sig_y, sig_x, shape, position, max_bytes, precision="double"):
    """Two kernels: 1-D erf cell fractions per axis, then their outer product."""
    ny, nx = shape
    nl = sig_y.size
    real = real_dtype(precision)
    out = np.empty((nl, ny, nx), real)
    opts = opencl.precision_options(precision)
    k_frac = opencl.get_kernel(_KERNELS, "gaussian_cell_fractions", opts)
    k_outer = opencl.get_kernel(_KERNELS, "outer_product", opts)
    size = real.itemsize
    per = size * (ny * nx + ny + nx + 2)
    step = max(1, min(nl, int(max_bytes // per)))
    d_fy, d_fx = opencl.device_buffer(size * step * ny), opencl.device_buffer(size * step * nx)
    d_out = opencl.device_buffer(size * step * ny * nx)
    for l0, l1 in chunk_ranges(nl, per, max_bytes):
        n = l1 - l0
        d_sy = opencl.to_device(np.ascontiguousarray(sig_y[l0:l1], real))
        d_sx = opencl.to_device(np.ascontiguousarray(sig_x[l0:l1], real))
        opencl.launch(k_frac, (ny, n), None, d_sy, real.type(position[1]), d_fy)
        opencl.launch(k_frac, (nx, n), None, d_sx, real.type(position[0]), d_fx)
        opencl.launch(k_outer, (nx, ny, n), None, d_fy, d_fx, d_out)
        opencl.from_device(out[l0:l1], d_out)
    return out.astype(np.float64, copy=False)


def _airy_window_opencl(airy, shape, position, window, max_bytes, out_buffer=None, precision="double"):
    """OpenCL twin of :func:`_airy_window_numpy`.

    y: ``airy_rows`` evaluates the Airy sub-samples of VW columns walking down
    the rows and applies the row taps on the fly (``airy_subsamples`` +
    ``blur_bin_rows`` when the jitter margin is too wide for registers);
    x: ``blur_bin_cols`` on sub-samples stored de-interleaved (node b of window
    cell c at b·ncx + c) so that VW consecutive output cells read contiguous
    vectors.  Output blocks of VW cells are padded symmetrically (padding is
    not stored).  The intensity depends on |dx|, |dy| only: x blocks and rows
    with the same offsets, and output blocks that mirror each other about the
    source, are computed once (a source at the centre of the narrow field:
    ¼ of the J1 evaluations, ~½ of the column contractions; 2.7× faster).
    ``out_buffer``: device buffer of ≥ 8 nλ nyo nxo bytes (single: 4) to receive the
    whole window (returned, nothing is copied to the host); None: a float64 NumPy array.
    ``precision`` "single": every kernel in float32 (sub-sample offsets, tap weights,
    accumulators), the host geometry in float64 rounded once to float32.
    """
    ny, nx = shape
    x0, y0 = position
    j0, j1_, k0, k1 = window
    real = real_dtype(precision)
    size = real.itemsize
    # the same number of lanes per vector register: twice as many floats as doubles
    oy, ox, vw = airy.o_y, airy.o_x, opencl.preferred_vector_width(16 if size == 4 else 8, 8 // size)
    dy, ky = airy.axis(j0, j1_, ny, y0, airy.sigma_y, oy)
    nyo, nxo, nys = j1_ - j0, k1 - k0, dy.size
    mx = blur_margin(airy.sigma_x)
    nxo_p = -(-nxo // vw) * vw
    pad = (nxo_p - nxo) // 2          # output cells [k0 - pad, k0 - pad + nxo_p): symmetric padding
    t, _ = cell_quadrature(ox, airy.grid)
    kx = blur_bin_taps(ox, airy.grid, airy.sigma_x)
    xoff, ncx, dx, xblocks = _x_layout(k0 - pad, nxo_p, mx, nx, x0, t, vw)
    oblocks = _output_mirror_blocks(k0 - pad, nxo_p, nx, x0, kx, vw)
    nxs, nl = ox * ncx, airy.lbda.size
    na_y = 2 * blur_margin(airy.sigma_y) + 1
    fused = na_y <= _FUSED_MAX_ROWS
    yslot = _shared_rows(dy)
    nslot = int(np.count_nonzero((yslot >= 0) & (yslot % 2 == 0))) if fused else 0
    nw = xblocks.shape[0]
    per_lbda = size * ((nslot * nw * vw) if fused else nys * nxs) + size * (nyo * nxs + nyo * nxo_p) + 2 * size
    step = max(1, min(nl, int(max_bytes // per_lbda), _CHUNK_LBDA))
    jr = 1 if vw == 1 else _COL_ROWS_CPU       # rows per blur_bin_cols work item (GPUs: 1)
    opts = (f"-DVW={vw}", f"-DJR={jr}") + ((f"-DNA={na_y}",) if fused else ()) + opencl.precision_options(precision)
    if fused:
        k_rows = opencl.get_kernel(_KERNELS, "airy_rows", opts)
        d_xb, d_ys = opencl.to_device(xblocks), opencl.to_device(yslot)
        d_t = opencl.device_buffer(size * step * nslot * nw * vw)
    else:
        k_sub = opencl.get_kernel(_KERNELS, "airy_subsamples", opts)
        k_rows = opencl.get_kernel(_KERNELS, "blur_bin_rows", opts)
        d_s = opencl.device_buffer(size * step * nys * nxs)
    k_cols = opencl.get_kernel(_KERNELS, "blur_bin_cols", opts)
    d_dx, d_dy = opencl.to_device(dx.astype(real)), opencl.to_device(np.ascontiguousarray(dy, real))
    d_ky, d_kx = opencl.to_device(ky.astype(real)), opencl.to_device(kx.astype(real))
    d_ob = opencl.to_device(oblocks)
    d_u = opencl.device_buffer(size * step * nyo * nxs)
    on_device = out_buffer is not None
    d_out = out_buffer if on_device else opencl.device_buffer(size * step * nyo * nxo)
    out = None if on_device else np.empty((nl, nyo, nxo), real)
    i32, f64 = np.int32, real.type
    for l0 in range(0, nl, step):
        l1 = min(nl, l0 + step)
        n = l1 - l0
        d_k = opencl.to_device(np.ascontiguousarray(airy.kwave[l0:l1], real))
        d_p = opencl.to_device(np.ascontiguousarray(airy.pref[l0:l1], real))
        if fused:
            opencl.launch(k_rows, (nw, n), None, d_dx, d_dy, d_k, d_p, d_ky, d_xb, d_ys, f64(airy.eps),
                          i32(oy), i32(nyo), i32(nxs), i32(nslot), d_t, d_u)
        else:
            opencl.launch(k_sub, (nxs // vw, nys, n), None, d_dx, d_dy, d_k, d_p, f64(airy.eps),
                          i32(nxs), d_s)
            opencl.launch(k_rows, (nxs // vw, nyo, n), None, d_s, d_ky, i32(ky.size), i32(oy),
                          i32(nys), i32(nxs), d_u)
        opencl.launch(k_cols, (oblocks.shape[0], -(-nyo // jr), n), None, d_u, d_kx, d_ob, i32(2 * mx + 1),
                      i32(ox), i32(ncx), i32(xoff), i32(pad), i32(nxo), i32(l0 if on_device else 0),
                      i32(nyo), d_out)
        if not on_device:
            opencl.from_device(out[l0:l1], d_out)
    return out_buffer if on_device else out.astype(np.float64, copy=False)
