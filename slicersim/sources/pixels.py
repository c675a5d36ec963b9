"""Pixel grids on the field: exact, flux-conserving resampling of images and user cubes.

Cell grid (see :mod:`slicersim.physics.psf`): cell (j, k) of an (ny, nx) field of square
cells of side s [arcsec] spans x ∈ [(k − nx/2) s, (k + 1 − nx/2) s],
y ∈ [(j − ny/2) s, (j + 1 − ny/2) s] relative to the field centre.  An input pixel is
uniformly bright and shares its flux among cells in proportion to the exact overlap areas
(``resample_pixels``); inputs are read in blocks of rows within a memory budget
(``HOST_MAX_BYTES``).  :class:`CubeSource` is a user cube placed on the field; its
resampled cubes are cached (``ResampleCache``), keyed by content.
"""
from __future__ import annotations

import hashlib
import math
import threading
from collections import OrderedDict

import numpy as np
import scipy.sparse

from slicersim import validation
from slicersim.errors import ParameterError, SpectrumError
from slicersim.sources.cosmology import check_source_redshift, get_cosmology, redshift_scalings
from slicersim.versioning import Versioned

__all__ = ["HOST_MAX_BYTES", "HOST_CACHE_BYTES", "PLANE_GROUP_MAX", "overlap_matrix", "resample_pixels",
           "CubeSource", "ResampleCache"]

#: default working-memory budget [bytes] of one block of input pixels (images, user cubes)
HOST_MAX_BYTES = 64 * 2**20
#: resampled cubes a CubeSource (and its ``at_redshift`` copies) keeps [bytes]
HOST_CACHE_BYTES = 256 * 2**20
#: most output planes a CubeSource resamples in one pass
PLANE_GROUP_MAX = 64


def _cell_edges(n, scale):
    return (np.arange(n + 1, dtype=np.float64) - n / 2.0) * scale


def _number(value, name):
    """A finite real number as float (ParameterError naming ``name`` otherwise)."""
    return validation.number(name, value)


def _pair(value, name):
    """(x, y) [arcsec] as two finite floats (ParameterError otherwise)."""
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != 2:
        raise ParameterError(f"{name} must be (x, y) [arcsec], got {validation.short_repr(value)}")
    x, y = value
    return _number(x, f"{name}[0]"), _number(y, f"{name}[1]")


def _from_redshift(source, from_redshift):
    z0 = source.redshift if from_redshift is None else from_redshift
    if z0 is None:
        raise ParameterError(f"this {type(source).__name__} has no redshift: give redshift=z when building it "
                             "(or from_redshift) to move it to another redshift")
    return check_source_redshift(z0, "redshift of origin")


def overlap_matrix(edges_out, edges_in):
    """(n_out, n_in) fraction of each input interval inside each output interval
    (exact overlap lengths / input length; intervals outside the output range are lost)."""
    lo = np.maximum(edges_out[:-1, None], edges_in[None, :-1])
    hi = np.minimum(edges_out[1:, None], edges_in[None, 1:])
    return np.clip(hi - lo, 0.0, None) / np.diff(edges_in)[None, :]


def _lambda_matrix(lbda_in, lbda_grid):
    """Sparse (nλ_out, nλ_in) linear-interpolation matrix (ValueError outside the range)."""
    lbda_grid = validation.array("lbda (wavelength grid) [Å]", lbda_grid, ndim=1, error=SpectrumError)
    if lbda_grid.size and (lbda_grid.min() < lbda_in[0] or lbda_grid.max() > lbda_in[-1]):
        raise SpectrumError(f"lbda: wavelength grid [{lbda_grid.min():g}, {lbda_grid.max():g}] Å extends beyond "
                         f"the cube's [{lbda_in[0]:g}, {lbda_in[-1]:g}] Å")
    i = np.clip(np.searchsorted(lbda_in, lbda_grid, side="right") - 1, 0, lbda_in.size - 2)
    t = (lbda_grid - lbda_in[i]) / (lbda_in[i + 1] - lbda_in[i])
    rows = np.repeat(np.arange(lbda_grid.size), 2)
    cols = np.stack([i, i + 1], axis=1).ravel()
    vals = np.stack([1.0 - t, t], axis=1).ravel()
    return scipy.sparse.csr_matrix((vals, (rows, cols)), shape=(lbda_grid.size, lbda_in.size))


def _clamped_edge_integral(xa, ya, xb, yb, s):
    """∫ clamp(x, 0, s) 1[0 ≤ y ≤ s] dy along the segment (xa, ya) → (xb, yb), signed.

    By Green's theorem, Σ over a counter-clockwise polygon's edges is the exact area of
    the polygon inside the square [0, s]²: ∂/∂x clamp(x, 0, s) = 1[0 ≤ x ≤ s].  The
    integrand is linear in y between the points where x crosses 0 or s, so the
    trapezoid rule on those sub-intervals is exact."""
    dy = yb - ya
    lo = np.clip(np.minimum(ya, yb), 0.0, s)
    hi = np.clip(np.maximum(ya, yb), 0.0, s)
    flat = dy == 0
    slope = np.where(flat, 0.0, (xb - xa) / np.where(flat, 1.0, dy))
    steep = slope != 0
    inv = np.where(steep, 1.0 / np.where(steep, slope, 1.0), 0.0)
    k0 = np.where(steep, ya + (0.0 - xa) * inv, lo)
    k1 = np.where(steep, ya + (s - xa) * inv, lo)
    pts = np.sort(np.stack(np.broadcast_arrays(lo, np.clip(k0, lo, hi), np.clip(k1, lo, hi), hi)), axis=0)
    xs = np.clip(xa + (pts - ya) * slope, 0.0, s)
    total = 0.5 * np.sum((pts[1:] - pts[:-1]) * (xs[1:] + xs[:-1]), axis=0)
    return np.where(flat, 0.0, np.sign(dy) * total)


def _rotated_overlap(u_edges, v_edges, p, centre, rotation, shape, s):
    """Sparse (ny·nx, nv·nu) fraction of each input pixel (edges ``u_edges``, ``v_edges``
    [arcsec] in the frame of the input grid, centred on ``centre``) inside each cell,
    for a grid rotated by ``rotation`` [deg]: exact areas by Green's theorem."""
    ny, nx = shape
    th = math.radians(rotation)
    c, sn = math.cos(th), math.sin(th)
    cx, cy = centre
    V, U = np.meshgrid(v_edges, u_edges, indexing="ij")                        # pixel corners
    X, Y = cx + U * c - V * sn, cy + U * sn + V * c
    # counter-clockwise corners of every input pixel (rotation keeps the orientation)
    px = np.stack([X[:-1, :-1], X[:-1, 1:], X[1:, 1:], X[1:, :-1]], -1).reshape(-1, 4)
    py = np.stack([Y[:-1, :-1], Y[:-1, 1:], Y[1:, 1:], Y[1:, :-1]], -1).reshape(-1, 4)
    L = int(math.ceil(p * (abs(c) + abs(sn)) / s)) + 1
    kx0 = np.floor(px.min(1) / s + nx / 2).astype(np.int64)
    ky0 = np.floor(py.min(1) / s + ny / 2).astype(np.int64)
    kx = kx0[:, None, None] + np.arange(L)[None, None, :]                     # (npix, 1, L)
    ky = ky0[:, None, None] + np.arange(L)[None, :, None]                     # (npix, L, 1)
    x0, y0 = (kx - nx / 2) * s, (ky - ny / 2) * s
    area = np.zeros((px.shape[0], L, L))
    for e in range(4):
        f = (e + 1) % 4
        area += _clamped_edge_integral(px[:, e, None, None] - x0, py[:, e, None, None] - y0,
                                       px[:, f, None, None] - x0, py[:, f, None, None] - y0, s)
    inside = (kx >= 0) & (kx < nx) & (ky >= 0) & (ky < ny) & (area > 0)
    rows = np.broadcast_to(ky * nx + kx, area.shape)[inside]
    cols = np.broadcast_to(np.arange(px.shape[0])[:, None, None], area.shape)[inside]
    return scipy.sparse.csr_matrix((area[inside] / (p * p), (rows, cols)), shape=(ny * nx, px.shape[0]))


def _field_columns(in_shape, p, centre, rotation, shape, s):
    """Per input row, the [first, last) input columns whose pixels can touch the field
    (pixel centre within half a pixel diagonal of the field rectangle)."""
    nyi, nxi = in_shape
    ny, nx = shape
    th = math.radians(rotation)
    c, sn = math.cos(th), math.sin(th)
    m = p * math.sqrt(0.5) * (1 + 1e-9)
    v = (np.arange(nyi) + 0.5 - nyi / 2) * p
    lo, hi = np.full(nyi, -np.inf), np.full(nyi, np.inf)
    # x(u) = cx − v sn + u c ∈ [−nx s/2 − m, nx s/2 + m], y(u) = cy + v c + u sn likewise
    for a, slope, half in ((centre[0] - v * sn, c, nx * s / 2 + m), (centre[1] + v * c, sn, ny * s / 2 + m)):
        if abs(slope) < 1e-15:
            out = np.abs(a) > half
            lo, hi = np.where(out, np.inf, lo), np.where(out, -np.inf, hi)
            continue
        u1, u2 = (-half - a) / slope, (half - a) / slope
        lo, hi = np.maximum(lo, np.minimum(u1, u2)), np.minimum(hi, np.maximum(u1, u2))
    j0 = np.clip(np.ceil(lo / p + nxi / 2 - 0.5), 0, nxi).astype(np.int64)
    j1 = np.clip(np.floor(hi / p + nxi / 2 - 0.5) + 1, 0, nxi).astype(np.int64)
    j1 = np.maximum(j1, j0)
    return j0, j1


def resample_pixels(read, in_shape, pixel_scale, centre, rotation, shape, spatial_scale, nplanes,
                    max_bytes=None, plane_group=None):
    """Flux-conserving resampling of (nplanes) images of uniformly bright input pixels onto
    the (ny, nx) cell grid: out[k, cell] = Σ_pixels value[k, pixel] · area(pixel ∩ cell) / p².

    read(r0, r1, j0, j1) → (nplanes, r1 − r0, j1 − j0) values of input rows r0 … r1 − 1 and
    columns j0 … j1 − 1 (any units).  The input grid has pixels of side ``pixel_scale`` [arcsec],
    its geometric centre at ``centre`` (x, y) [arcsec] and is rotated by ``rotation`` [deg]
    counter-clockwise.  Rows and columns that cannot touch the field are never read; the others
    are read in blocks of rows sized to ``max_bytes`` (default ``HOST_MAX_BYTES``), so the
    input may be larger than memory (a numpy memmap, an h5py dataset).  Exact overlaps:
    separable for rotation = 0, polygon areas otherwise.

    ``plane_group``: planes are read ``plane_group`` at a time, as
    ``read(r0, r1, j0, j1, planes=slice(p0, p1))``, and the row blocks are sized for that many
    planes whatever ``nplanes`` is: each plane's result then does not depend on how many
    planes are resampled together (bit for bit)."""
    nyi, nxi = (int(v) for v in in_shape)
    ny, nx = (int(v) for v in shape)
    p, s = float(pixel_scale), float(spatial_scale)
    budget = HOST_MAX_BYTES if max_bytes is None else int(max_bytes)
    out = np.zeros((nplanes, ny, nx))
    j0, j1 = _field_columns((nyi, nxi), p, centre, rotation, (ny, nx), s)
    used = np.nonzero(j1 > j0)[0]
    if used.size == 0:
        return out
    r_first, r_last = int(used[0]), int(used[-1]) + 1
    c_first, c_last = int(j0[used].min()), int(j1[used].max())
    ncol = c_last - c_first
    separable = rotation % 360.0 == 0.0
    per_plane = nplanes if plane_group is None else max(1, int(plane_group))
    groups = [None] if plane_group is None else [slice(g, min(nplanes, g + per_plane))
                                                 for g in range(0, nplanes, per_plane)]
    per_pixel = 8 * (2 * per_plane + (4 if separable else 12 * (int(p * 1.5 / s) + 2) ** 2))
    step = max(1, budget // max(1, per_pixel * ncol))
    u_edges, v_edges = _cell_edges(nxi, p), _cell_edges(nyi, p)
    ox = overlap_matrix(_cell_edges(nx, s), centre[0] + u_edges[c_first:c_last + 1]) if separable else None
    for r0 in range(r_first, r_last, step):
        r1 = min(r_last, r0 + step)
        if separable:
            oy = overlap_matrix(_cell_edges(ny, s), centre[1] + v_edges[r0:r1 + 1])
        else:
            W = _rotated_overlap(u_edges[c_first:c_last + 1], v_edges[r0:r1 + 1], p, centre, rotation,
                                 (ny, nx), s)
        for planes in groups:
            values = np.asarray(read(r0, r1, c_first, c_last) if planes is None
                                else read(r0, r1, c_first, c_last, planes=planes), dtype=np.float64)
            target = out if planes is None else out[planes]
            if separable:
                target += np.matmul(oy, values @ ox.T)
            else:
                k = values.shape[0]
                target += np.asarray(W @ values.reshape(k, -1).T).T.reshape(k, ny, nx)
            del values
    return out


def _digest(array):
    return hashlib.sha1(np.ascontiguousarray(array, dtype=np.float64).tobytes()).hexdigest()


class ResampleCache:
    """Bounded LRU of resampled cubes (read-only arrays) of one user cube, shared by a
    :class:`CubeSource` and its ``at_redshift`` copies.

    Keyed by content: the cube object itself (identity) and every number the result depends on
    (cell grid, placement, pixel scale, flux scale, input and output wavelengths), so a
    moved, rescaled or redshifted source never reuses another's result.  A wavelength grid
    that is a contiguous part of a cached one is served from it (each plane's result does not
    depend on the planes resampled with it).  At most ``max_bytes`` are kept; larger results
    are not cached.  The cube's values are assumed not to change in place."""

    def __init__(self, max_bytes=HOST_CACHE_BYTES):
        self.max_bytes = int(max_bytes)
        self.hits = 0
        self._entries = OrderedDict()          # (key, grid digest) → (cube, grid, result)
        self._lock = threading.Lock()

    @property
    def nbytes(self):
        return sum(out.nbytes for _, _, out in self._entries.values())

    def get(self, cube, key, grid):
        with self._lock:
            for name, (obj, cached, out) in reversed(self._entries.items()):
                if obj is not cube or name[0] != key or cached.size < grid.size:
                    continue
                i = int(np.searchsorted(cached, grid[0])) if grid.size else 0
                if i + grid.size <= cached.size and np.array_equal(cached[i:i + grid.size], grid):
                    self._entries.move_to_end(name)
                    self.hits += 1
                    return out[i:i + grid.size]
        return None

    def put(self, cube, key, grid, out):
        if out.nbytes > self.max_bytes:
            return
        out.setflags(write=False)
        with self._lock:
            self._entries[(key, _digest(grid))] = (cube, grid.copy(), out)
            while self.nbytes > self.max_bytes:
                self._entries.popitem(last=False)

    def clear(self):
        with self._lock:
            self._entries.clear()


class CubeSource(Versioned):
    """User cube [erg/s/cm²/Å per input pixel] placed on the field, flux conserving.

    Parameters
    ----------
    cube : array_like of shape (nλ_in, ny_in, nx_in)
        F_λ per input pixel [erg/s/cm²/Å]: a numpy array, memmap or h5py dataset (it is
        read in blocks, never copied whole).
    lbda_in : array_like of shape (nλ_in,)
        Wavelengths of the planes, strictly increasing [Å].
    pixel_scale : float
        Side of an input pixel [arcsec].
    centre : tuple of float, optional
        (x, y) of the cube centre relative to the field centre [arcsec].
    rotation : float, optional
        Rotation counter-clockwise about that centre [deg].
    flux_scale : float, optional
        Factor applied to the values when read.
    redshift : float, optional
        Redshift the cube is seen at, as for :class:`~slicersim.Host` (:meth:`at_redshift`).
    cosmology : astropy.cosmology.Cosmology, optional
        Cosmology of that move, as for :class:`~slicersim.Host` (default Planck18).
    max_bytes : int, optional
        Working-memory budget of one block of input rows [bytes] (default
        ``HOST_MAX_BYTES``, 64 MiB).

    Notes
    -----
    Spatial resampling: each input pixel is uniformly bright and shares its flux among
    cells in proportion to the exact overlap areas (``resample_pixels``), in groups of
    output planes of a fixed size (so each plane's result does not depend on the grid it is
    asked with).  Wavelength: F_λ linearly interpolated in λ (flux density, not integrated
    over bins); grids beyond [lbda_in[0], lbda_in[-1]] raise SpectrumError; only the input
    planes the grid needs are read.  Results are cached per (grid, placement, redshift)
    (``ResampleCache``, ``cache``): the cube's values must not change in place afterwards.
    """

    def __init__(self, cube, lbda_in, pixel_scale, centre=(0.0, 0.0), rotation=0.0, flux_scale=1.0,
                 redshift=None, cosmology=None, max_bytes=None):
        if not hasattr(cube, "shape") or not hasattr(cube, "__getitem__"):
            cube = np.asarray(cube, dtype=np.float64)
        if len(cube.shape) != 3 or min(cube.shape) == 0:
            raise ParameterError(f"cube must have shape (nλ, ny, nx), got {cube.shape}")
        lbda_in = validation.array("lbda_in [Å]", lbda_in, ndim=1)
        if lbda_in.shape != tuple(cube.shape[:1]) or lbda_in.size < 2 or np.any(np.diff(lbda_in) <= 0):
            raise ParameterError("lbda_in must be strictly increasing with one value per cube plane (≥ 2)")
        pixel_scale = validation.number("pixel_scale", pixel_scale, low=0.0, low_open=True, unit="arcsec")
        rotation = validation.number("rotation", rotation, unit="deg")
        self.max_bytes = max_bytes
        budget = HOST_MAX_BYTES if max_bytes is None else int(max_bytes)
        plane = 8 * int(cube.shape[1]) * int(cube.shape[2])
        step = max(1, budget // max(1, plane))
        for k in range(0, cube.shape[0], step):            # validated block by block
            if not np.all(np.isfinite(np.asarray(cube[k:k + step], dtype=np.float64))):
                raise ParameterError("cube contains NaN/inf values")
        self.cube, self.lbda_in, self.pixel_scale = cube, lbda_in, float(pixel_scale)
        self.centre = _pair(centre, "centre")
        self.rotation = float(rotation)
        self.flux_scale = _number(flux_scale, "flux_scale")
        self.redshift = None if redshift is None else check_source_redshift(redshift, "cube redshift")
        self.cosmology = get_cosmology(cosmology)
        self.cache = ResampleCache()

    def at_redshift(self, redshift, cosmology=None, from_redshift=None):
        """The same source seen at ``redshift`` (see :meth:`Host.at_redshift <slicersim.Host.at_redshift>`);
        the cube array (already validated) and the resampling cache are shared, not copied.

        Parameters
        ----------
        redshift : float
            The new redshift z.
        cosmology : astropy.cosmology.Cosmology, optional
            Cosmology of the move.
        from_redshift : float, optional
            z₀ (default: the source's own redshift).

        Returns
        -------
        CubeSource
            The new source.
        """
        z0 = _from_redshift(self, from_redshift)
        cosmo = self.cosmology if cosmology is None else get_cosmology(cosmology)
        z = check_source_redshift(redshift, "cube redshift")
        angle, stretch, dim = redshift_scalings(z0, z, cosmo)
        new = object.__new__(CubeSource)
        new.cube, new.lbda_in, new.pixel_scale = self.cube, self.lbda_in * stretch, self.pixel_scale * angle
        new.centre = (self.centre[0] * angle, self.centre[1] * angle)
        new.rotation, new.flux_scale, new.redshift = self.rotation, self.flux_scale * dim, z
        new.cosmology, new.max_bytes, new.cache = cosmo, self.max_bytes, self.cache
        return new

    def _plane_group(self):
        """Output planes resampled in one pass: fixed by the cube and the budget (not the grid)."""
        budget = HOST_MAX_BYTES if self.max_bytes is None else int(self.max_bytes)
        plane = 16 * int(self.cube.shape[1]) * int(self.cube.shape[2])
        return int(min(PLANE_GROUP_MAX, max(1, budget // max(1, plane))))

    def flux_cube(self, lbda_grid, shape, spatial_scale):
        """Flux density per cell on ``lbda_grid`` (read-only; cached).

        Parameters
        ----------
        lbda_grid : array_like of shape (nλ,)
            Wavelengths [Å].
        shape : tuple of int
            (ny, nx) cells.
        spatial_scale : float
            Cell side [arcsec].

        Returns
        -------
        numpy.ndarray of shape (nλ, ny, nx)
            Flux density per cell [erg/s/cm²/Å].
        """
        lbda_grid = np.asarray(lbda_grid, dtype=np.float64)
        shape, s = tuple(int(v) for v in shape), float(spatial_scale)
        L = _lambda_matrix(self.lbda_in, lbda_grid).tocsr()           # validates the grid
        key = (shape, s, tuple(self.centre), self.rotation, self.pixel_scale, self.flux_scale, self.max_bytes,
               _digest(self.lbda_in))
        cached = self.cache.get(self.cube, key, lbda_grid)
        if cached is not None:
            return cached
        nyi, nxi = (int(v) for v in self.cube.shape[1:])
        group = self._plane_group()
        parts = {}                              # plane group start → (k0, k1, λ matrix of its input planes)
        for g0 in range(0, lbda_grid.size, group):
            Lg = L[g0:g0 + group].tocsc()
            cols = np.nonzero(np.diff(Lg.indptr))[0]
            k0, k1 = int(cols[0]), int(cols[-1]) + 1
            parts[g0] = (k0, k1, Lg[:, k0:k1].tocsr() * self.flux_scale)

        def read(r0, r1, j0, j1, planes):
            k0, k1, Lk = parts[planes.start]
            block = np.asarray(self.cube[k0:k1, r0:r1, j0:j1], dtype=np.float64)
            return (Lk @ block.reshape(k1 - k0, -1)).reshape(-1, r1 - r0, j1 - j0)
        out = resample_pixels(read, (nyi, nxi), self.pixel_scale, self.centre, self.rotation, shape, s,
                              lbda_grid.size, self.max_bytes, plane_group=group)
        self.cache.put(self.cube, key, lbda_grid, out)
        return out
