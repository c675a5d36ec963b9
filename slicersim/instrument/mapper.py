"""Optical model of the slicer spectrograph on the detector: :class:`SlicerMapper`.

A spot table (format of the reference's ``mapping_spotdata.csv``: columns
``slice fieldpos lbda x y rmsx_um rmsy_um``, λ in µm, x/y in mm from the
detector centre, spot rms in µm) samples, for every slice, the position of
the spectrum on the detector on a rectilinear (fieldpos × λ) node grid.

* **Forward map** (slice, fieldpos, λ [Å]) → (p_x, p_y) [px]: piecewise
  interpolation on that slice's node grid, **bilinear** in each rectangle
  (default) or, to reproduce the reference exactly, linear on the two
  triangles chosen by ``face_diagonal`` (0: split along P00–P11, 1: along
  P10–P01).  Both agree on the rectangle edges.  Outside the node range the
  end rectangles are extrapolated linearly.  Pixel coordinates:
  p = 1000·X[mm]/pixel_size[µm] + n/2; pixel column c covers p_x ∈ [c, c+1)
  (``image[row, col]``, row ↔ p_y).
* **Spot rms** (σ_x, σ_y) [px] interpolated the same way.
* **Inverse map** (p_x, p_y) → (slice, fieldpos, λ): Newton iterations on the
  piecewise map, started from the nearest point of a fine forward grid.
* **Projection** of a cube (λ, row, column) onto the detector, flux
  conserving: each cube cell (slice s, column k, bin i) covers
  fieldpos [−1 + 2k/n, −1 + 2(k+1)/n] × [λ-edge i, λ-edge i+1]; its four
  mapped corners give an axis-aligned box on the detector (x between the
  mean x of the two corners on each fieldpos edge, y between the mean y on
  each λ edge; the small cross terms (shear) w enter as a variance w²/12
  added to the spot variance); the box blurred by the Gaussian spot (rms at
  the cell centre) is integrated exactly over pixels, truncated at
  ±``truncate`` rms and renormalised (:mod:`slicersim.backends.projection`):
  every cell deposits exactly its value (what falls off the detector is
  lost).  ``oversample = (n_λ, n_φ)`` splits each cell into sub-cells for
  strongly curved or sheared footprints (for the Lazuli layouts 3 × 3
  sub-cells change the image by < 0.2 % of its peak: see the tests).
  Cube row r of a field ↔ slice ``slices[n_rows − 1 − r]`` (narrow:
  s = 58 − r, wide: s = 116 − r).

The projection methods come from :class:`~slicersim.instrument.mapper_projection.ProjectionMixin`.
``SlicerMapper.default()`` loads slicersim's own synthetic Lazuli layout
(``data/lazuli/lazuli_spots.csv``, see ``build_spots.py``).
"""

from __future__ import annotations

import functools
from collections import OrderedDict
from pathlib import Path

import numpy as np

from slicersim import validation
from slicersim.errors import ConfigError, ParameterError
from slicersim.io.config import builtin_config_dir
from slicersim.io.tables import numeric_rows
from slicersim.backends.projection import resolve_table_cache
from slicersim.instrument.mapper_projection import ProjectionMixin, detector_rate_image
from slicersim.instrument.slices import NARROW_SLICES, WIDE_SLICES

__all__ = ["SlicerMapper", "read_spot_table", "detector_rate_image", "NARROW_SLICES", "WIDE_SLICES",
           "DEFAULT_SPOT_TABLE"]

DEFAULT_SPOT_TABLE = Path(builtin_config_dir()) / "lazuli_spots.csv"
COLUMNS = ("slice", "fieldpos", "lbda", "x", "y", "rmsx_um", "rmsy_um")
_CHUNK = 1 << 20


def read_spot_table(table_or_path):
    """Columns of a spot table as a dict of float arrays.

    Accepts a path (whitespace-separated text with the header line
    ``slice fieldpos lbda x y rmsx_um rmsy_um``), a mapping / structured
    array / DataFrame / astropy Table with those column names, or a
    (n, 7) array in that column order.
    """
    if isinstance(table_or_path, (str, Path)):
        path = Path(validation.regular_file("spot table", table_or_path, error=ConfigError))   # no FIFO, device
        with open(path, encoding="utf-8") as fh:
            header = fh.readline().split()
        if header != list(COLUMNS):
            raise ConfigError(f"{path}: header must be {' '.join(COLUMNS)!r}, got {' '.join(header)!r}")
        data = numeric_rows(path, len(COLUMNS), skiprows=1, what="spot-table")     # a bad row: its line named
        if not len(data):
            raise ConfigError(f"{path}: no rows of {len(COLUMNS)} numbers under the header")
        return {name: data[:, i] for i, name in enumerate(COLUMNS)}
    try:
        return {name: np.asarray(table_or_path[name], dtype=np.float64).ravel() for name in COLUMNS}
    except (KeyError, IndexError, ValueError, TypeError):
        arr = np.asarray(table_or_path, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != len(COLUMNS):
            raise ConfigError(f"spot table needs the columns {COLUMNS}") from None
        return {name: arr[:, i] for i, name in enumerate(COLUMNS)}


def _locate(nodes, x):
    """Rectangle index j and fraction t with x = nodes[j] + t (nodes[j+1] − nodes[j])."""
    j = np.clip(np.searchsorted(nodes, x, side="right") - 1, 0, nodes.size - 2)
    return j, (x - nodes[j]) / (nodes[j + 1] - nodes[j])


def _hat_matrix(nodes, x):
    """(len(x), len(nodes)) linear-interpolation weights (end intervals extrapolated)."""
    j, t = _locate(nodes, x)
    A = np.zeros((x.size, nodes.size))
    A[np.arange(x.size), j] = 1.0 - t
    A[np.arange(x.size), j + 1] = t
    return A


@functools.lru_cache(maxsize=2)
def _default_table(path):
    return read_spot_table(path)


def aberration_sigma_px(dispersion_resolution):
    """σ [px] of the optics' aberration inside a monochromatic slice image of full width
    ``dispersion_resolution`` (dr) px: √(dr² − 2²)/2, the 2-px image of the slice width removed
    (reference physics §2.5; the cube's LSF σ = dr/2 and spatial σ_inst carry it already)."""
    dr = float(dispersion_resolution)
    return 0.5 * float(np.sqrt(max(dr * dr - 4.0, 0.0)))


@functools.lru_cache(maxsize=1)
def _cbe_dispersion_resolution():
    from slicersim.io.config import load_config
    return float(load_config("cbe")["spectrograph"]["dispersion_resolution"])


class SlicerMapper(ProjectionMixin):
    """Forward/inverse optical map of a slicer spectrograph and cube projection.

    Parameters
    ----------
    slice_ids : array_like of shape (S,)
        Slice ids (int).
    fieldpos_nodes : array_like of shape (J,)
        Increasing positions along the slice (−1 … +1).
    lbda_nodes : array_like of shape (M,)
        Increasing wavelengths [Å].
    values : array_like of shape (S, J, M, 4)
        p_x, p_y [px] and σ_x, σ_y [px] at the nodes (float).
    pixel_size_um : float, optional
        Detector pixel size [µm].
    detector_shape : tuple of int, optional
        (rows, cols) of the detector [px].
    interpolation : {"bilinear", "triangles"}, optional
        Interpolation between the nodes.
    face_diagonal : array_like of shape (S, J−1, M−1), optional
        int, for "triangles" (default 0 everywhere).
    cache_size : int, optional
        Projection tables kept in memory (least recently used first out).
    table_cache : str, path-like, object or None, optional
        "default", None, a directory or an ``slicersim.io.table_cache.ArrayCache``: where
        projection tables are cached on disk (:meth:`projection_tables`); "default" is
        ``$SLICERSIM_CACHE/projection`` (else ``~/.cache/slicersim/projection``), None keeps
        them in memory only (``cache_size`` tables, least recently used first out).
    cube_blur_px : float or tuple of float, optional
        Aberration σ the projected cube already carries (x, y) [px], ≥ 0: subtracted from the
        table's spot, which is the total aberration (counted once).
    """

    def __init__(self, slice_ids, fieldpos_nodes, lbda_nodes, values, *, pixel_size_um=10.0,
                 detector_shape=(4096, 4096), interpolation="bilinear", face_diagonal=None, cache_size=4,
                 table_cache="default", cube_blur_px=0.0):
        self.slice_ids = np.asarray(slice_ids, dtype=np.int64)
        self.fieldpos_nodes = np.asarray(fieldpos_nodes, dtype=np.float64)
        self.lbda_nodes = np.asarray(lbda_nodes, dtype=np.float64)
        self.values = np.ascontiguousarray(values, dtype=np.float64)
        S, J, M = self.slice_ids.size, self.fieldpos_nodes.size, self.lbda_nodes.size
        if self.values.shape != (S, J, M, 4) or J < 2 or M < 2:
            raise ParameterError(f"values must have shape ({S}, {J}, {M}, 4) with >= 2 nodes per axis")
        for name, nodes in (("fieldpos", self.fieldpos_nodes), ("lbda", self.lbda_nodes)):
            if np.any(np.diff(nodes) <= 0):
                raise ParameterError(f"{name}_nodes must be strictly increasing")
        if not np.all(np.isfinite(self.values)) or np.any(self.values[..., 2:] < 0):
            raise ParameterError("values: spot positions must be finite and rms sizes >= 0")
        if np.unique(self.slice_ids).size != S or np.any(self.slice_ids < 0):
            raise ParameterError("slice_ids must be distinct non-negative integers")
        validation.choice("interpolation", interpolation, ("bilinear", "triangles"))
        self.interpolation = interpolation
        diag = np.zeros((S, J - 1, M - 1), np.int8) if face_diagonal is None else np.asarray(face_diagonal)
        if diag.shape != (S, J - 1, M - 1) or not np.isin(diag, (0, 1)).all():
            raise ParameterError(f"face_diagonal must have shape {(S, J - 1, M - 1)} with values 0/1")
        self.face_diagonal = diag.astype(np.int8)
        self.pixel_size_um = float(pixel_size_um)
        blur = np.broadcast_to(np.asarray(cube_blur_px, dtype=np.float64), (2,))
        if not np.all(np.isfinite(blur)) or np.any(blur < 0):
            raise ParameterError(f"cube_blur_px must be finite and >= 0 [px], got "
                                 f"{validation.short_repr(cube_blur_px)}")
        self.cube_blur_px = tuple(float(v) for v in blur)
        self.detector_shape = tuple(int(v) for v in detector_shape)
        self._lookup = np.full(self.slice_ids.max() + 1, -1, np.int64)
        self._lookup[self.slice_ids] = np.arange(S)
        self._cache = OrderedDict()
        self._cache_size = int(cache_size)
        self._disk_keys = {}
        resolve_table_cache(table_cache)          # checks the type now
        self.table_cache = table_cache
        self._trees = None

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_table(cls, table_or_path, pixel_size_um=10.0, detector_shape=(4096, 4096), **kwargs):
        """Mapper from a spot table (path or columns; λ in µm, x/y in mm, rms in µm).

        Parameters
        ----------
        table_or_path : str, path-like or astropy.table.Table
            The spot table.
        pixel_size_um : float, optional
            Detector pixel size [µm].
        detector_shape : tuple of int, optional
            (rows, cols) [px].
        **kwargs
            Keyword parameters of :class:`SlicerMapper`.

        Returns
        -------
        SlicerMapper
            The mapper.
        """
        t = read_spot_table(table_or_path)
        return cls._from_columns(t, pixel_size_um, detector_shape, **kwargs)

    @classmethod
    def default(cls, **kwargs):
        """slicersim's own Lazuli layout (``data/lazuli/lazuli_spots.csv``), for cubes of the CBE
        configuration: ``cube_blur_px`` = ``aberration_sigma_px`` of its dispersion resolution.

        Parameters
        ----------
        **kwargs
            Keyword parameters of :class:`SlicerMapper` (``cube_blur_px``, ``table_cache``, ...).

        Returns
        -------
        SlicerMapper
            The mapper.
        """
        kwargs.setdefault("cube_blur_px", aberration_sigma_px(_cbe_dispersion_resolution()))
        return cls._from_columns(_default_table(str(DEFAULT_SPOT_TABLE)), 10.0, (4096, 4096), **kwargs)

    @classmethod
    def _from_columns(cls, t, pixel_size_um, detector_shape, **kwargs):
        sid = np.rint(t["slice"]).astype(np.int64)
        if np.any(np.abs(sid - t["slice"]) > 1e-9):
            raise ConfigError("spot table: slice ids must be integers")
        ids, s = np.unique(sid, return_inverse=True)
        fp, j = np.unique(t["fieldpos"], return_inverse=True)
        lb, m = np.unique(t["lbda"], return_inverse=True)
        S, J, M = ids.size, fp.size, lb.size
        count = np.zeros((S, J, M), np.int64)
        np.add.at(count, (s, j, m), 1)
        if not np.all(count == 1):
            raise ConfigError(f"spot table must hold every (slice, fieldpos, lbda) node exactly once on a "
                             f"rectilinear grid ({S} slices x {J} fieldpos x {M} lbda; "
                             f"{int((count == 0).sum())} missing, {int((count > 1).sum())} repeated)")
        rows, cols = (int(v) for v in detector_shape)
        values = np.empty((S, J, M, 4))
        px_per_mm = 1000.0 / float(pixel_size_um)
        values[s, j, m, 0] = t["x"] * px_per_mm + cols / 2
        values[s, j, m, 1] = t["y"] * px_per_mm + rows / 2
        values[s, j, m, 2] = t["rmsx_um"] / float(pixel_size_um)
        values[s, j, m, 3] = t["rmsy_um"] / float(pixel_size_um)
        return cls(ids, fp, lb * 1e4, values, pixel_size_um=pixel_size_um, detector_shape=detector_shape,
                   **kwargs)

    def __repr__(self):
        return (f"SlicerMapper({self.slice_ids.size} slices, {self.fieldpos_nodes.size} fieldpos x "
                f"{self.lbda_nodes.size} lbda nodes [{self.lbda_nodes[0]:.0f}-{self.lbda_nodes[-1]:.0f} AA], "
                f"detector {self.detector_shape}, {self.interpolation})")

    # ------------------------------------------------------------------ forward map
    def slice_index(self, slice_id):
        """Row of ``values`` for slice ids (raises on unknown ids).

        Parameters
        ----------
        slice_id : int or array_like of int
            Slice ids.

        Returns
        -------
        int or numpy.ndarray
            Their rows of ``values``.
        """
        sid = np.asarray(slice_id)
        if not np.issubdtype(sid.dtype, np.integer):
            if np.any(sid != np.rint(sid)):
                raise ParameterError("slice_ids must be integers")
            sid = np.rint(sid).astype(np.int64)
        bad = (sid < 0) | (sid >= self._lookup.size)
        idx = np.where(bad, -1, self._lookup[np.where(bad, 0, sid)])
        if np.any(idx < 0):
            raise ParameterError(f"slices: unknown slice id(s): {np.unique(sid[idx < 0])[:10]}")
        return idx

    def _interp(self, sidx, phi, lam, ch, jacobian=False):
        """Interpolated channels ``ch`` (and d/dφ, d/dλ) at flat arrays of points."""
        j, u = _locate(self.fieldpos_nodes, phi)
        m, v = _locate(self.lbda_nodes, lam)
        V = self.values
        P00, P10 = V[sidx, j, m][:, ch], V[sidx, j + 1, m][:, ch]
        P01, P11 = V[sidx, j, m + 1][:, ch], V[sidx, j + 1, m + 1][:, ch]
        u, v = u[:, None], v[:, None]
        if self.interpolation == "bilinear":
            a0 = (1 - u) * P00 + u * P10
            a1 = (1 - u) * P01 + u * P11
            P = (1 - v) * a0 + v * a1
            Du, Dv = (1 - v) * (P10 - P00) + v * (P11 - P01), a1 - a0
        else:
            d = self.face_diagonal[sidx, j, m][:, None] == 1
            lower0 = u >= v
            lower1 = u + v <= 1
            P = np.where(d,
                         np.where(lower1, P00 + u * (P10 - P00) + v * (P01 - P00),
                                  P11 + (1 - u) * (P01 - P11) + (1 - v) * (P10 - P11)),
                         np.where(lower0, P00 + u * (P10 - P00) + v * (P11 - P10),
                                  P00 + v * (P01 - P00) + u * (P11 - P01)))
            Du = np.where(d, np.where(lower1, P10 - P00, P11 - P01), np.where(lower0, P10 - P00, P11 - P01))
            Dv = np.where(d, np.where(lower1, P01 - P00, P11 - P10), np.where(lower0, P11 - P10, P01 - P00))
        if not jacobian:
            return P
        hj = (self.fieldpos_nodes[j + 1] - self.fieldpos_nodes[j])[:, None]
        hm = (self.lbda_nodes[m + 1] - self.lbda_nodes[m])[:, None]
        return P, Du / hj, Dv / hm

    def _evaluate(self, slice_id, fieldpos, lbda, ch):
        s, phi, lam = np.broadcast_arrays(np.asarray(slice_id), np.asarray(fieldpos, dtype=np.float64),
                                          np.asarray(lbda, dtype=np.float64))
        sidx = self.slice_index(s).ravel()
        phi, lam = phi.ravel(), lam.ravel()
        out = np.empty((sidx.size, len(ch)))
        for i in range(0, sidx.size, _CHUNK):
            sl = slice(i, i + _CHUNK)
            out[sl] = self._interp(sidx[sl], phi[sl], lam[sl], ch)
        return tuple(out[:, c].reshape(s.shape) for c in range(len(ch)))

    def forward(self, slice_id, fieldpos, lbda):
        """Detector position of (slice id, fieldpos, λ) (broadcast).

        Parameters
        ----------
        slice_id : int or array_like of int
            Slice id(s).
        fieldpos : float or array_like
            Position along the slice (−1 … +1).
        lbda : float or array_like
            Wavelength [Å].

        Returns
        -------
        p_x, p_y : numpy.ndarray
            Detector position [px].
        """
        return self._evaluate(slice_id, fieldpos, lbda, [0, 1])

    def spot_rms(self, slice_id, fieldpos, lbda):
        """Spot rms at (slice id, fieldpos, λ) (broadcast).

        Parameters
        ----------
        slice_id : int or array_like of int
            Slice id(s).
        fieldpos : float or array_like
            Position along the slice (−1 … +1).
        lbda : float or array_like
            Wavelength [Å].

        Returns
        -------
        sigma_x, sigma_y : numpy.ndarray
            Spot rms (σ_x, σ_y) [px].
        """
        return self._evaluate(slice_id, fieldpos, lbda, [2, 3])

    def forward_grid(self, slice_ids, fieldpos, lbda, channels=(0, 1)):
        """Channels (p_x, p_y, σ_x, σ_y) [px] on the tensor grid.

        Bilinear: products with the (sparse) hat-function matrices; equal to
        :meth:`forward` up to rounding (~1e-12 px).

        Parameters
        ----------
        slice_ids : sequence of int
            S slice ids.
        fieldpos : array_like
            Positions along the slice (−1 … +1).
        lbda : array_like
            Wavelengths [Å].
        channels : tuple of int, optional
            The C channels (0: p_x, 1: p_y, 2: σ_x, 3: σ_y).

        Returns
        -------
        numpy.ndarray of shape (S, C, len(lbda), len(fieldpos))
            The channels [px].
        """
        sidx = self.slice_index(np.asarray(slice_ids).ravel())
        phi, lam = np.asarray(fieldpos, np.float64).ravel(), np.asarray(lbda, np.float64).ravel()
        ch = list(channels)
        if self.interpolation == "bilinear":
            A = _hat_matrix(self.fieldpos_nodes, phi)                       # (Q, J)
            B = _hat_matrix(self.lbda_nodes, lam)                           # (E, M)
            V = np.ascontiguousarray(self.values[sidx][..., ch].transpose(0, 3, 1, 2))   # (S, C, J, M)
            return np.matmul(np.matmul(V, B.T).swapaxes(-1, -2), A.T)       # (S, C, E, Q)
        S, E, Q = sidx.size, lam.size, phi.size
        ss, ee, qq = (a.ravel() for a in np.meshgrid(sidx, lam, phi, indexing="ij"))
        out = np.empty((S * E * Q, len(ch)))
        for i in range(0, out.shape[0], _CHUNK):
            sl = slice(i, i + _CHUNK)
            out[sl] = self._interp(ss[sl], qq[sl], ee[sl], ch)
        return np.ascontiguousarray(out.reshape(S, E, Q, len(ch)).transpose(0, 3, 1, 2))

    # ------------------------------------------------------------------ inverse map
    def _seed_grid(self):
        if self._trees is None:
            from scipy.spatial import cKDTree
            phi = np.linspace(self.fieldpos_nodes[0], self.fieldpos_nodes[-1], 17)
            L = self.lbda_nodes
            sub = max(2, -(-256 // (L.size - 1)))             # ~256 seeds along λ (several per node interval)
            lam = np.concatenate([L[:-1, None] + np.diff(L)[:, None] * np.arange(sub)[None] / sub, L[-1:, None]],
                                 axis=None)
            xy = self.forward_grid(self.slice_ids, phi, lam).transpose(0, 2, 3, 1)   # (S, E, Q, 2)
            S = self.slice_ids.size
            sidx, ee, qq = np.meshgrid(np.arange(S), lam, phi, indexing="ij")
            seeds = (sidx.reshape(S, -1), qq.reshape(S, -1), ee.reshape(S, -1))
            pts = xy.reshape(S, -1, 2)
            self._trees = {"all": cKDTree(pts.reshape(-1, 2)), "seeds": [a.ravel() for a in seeds],
                           "per_slice": [cKDTree(pts[s]) for s in range(S)], "per_slice_seeds": seeds}
        return self._trees

    def _newton(self, sidx, phi, lam, target, tol, maxiter=50):
        lo_p, hi_p = self.fieldpos_nodes[[0, -1]]
        span_p = hi_p - lo_p
        lo_l, hi_l = self.lbda_nodes[[0, -1]]
        span_l = hi_l - lo_l
        phi, lam = phi.copy(), lam.copy()
        active = np.arange(phi.size)
        for _ in range(maxiter):
            if active.size == 0:
                break
            P, Dp, Dl = self._interp(sidx[active], phi[active], lam[active], [0, 1], jacobian=True)
            r = target[active] - P
            det = Dp[:, 0] * Dl[:, 1] - Dp[:, 1] * Dl[:, 0]
            with np.errstate(divide="ignore", invalid="ignore"):
                dphi = (r[:, 0] * Dl[:, 1] - r[:, 1] * Dl[:, 0]) / det
                dlam = (Dp[:, 0] * r[:, 1] - Dp[:, 1] * r[:, 0]) / det
            bad = ~np.isfinite(dphi) | ~np.isfinite(dlam)
            dphi[bad], dlam[bad] = 0.0, 0.0
            phi[active] = np.clip(phi[active] + dphi, lo_p - span_p, hi_p + span_p)
            lam[active] = np.clip(lam[active] + dlam, lo_l - span_l, hi_l + span_l)
            moving = (np.abs(dphi) > 1e-14 * span_p) | (np.abs(dlam) > 1e-14 * span_l)
            active = active[moving & ~bad & (np.hypot(r[:, 0], r[:, 1]) > 1e-3 * tol)]
        P = self._interp(sidx, phi, lam, [0, 1])
        return phi, lam, np.hypot(*(target - P).T)

    def inverse(self, p_x, p_y, slice_id=None, lbda_range=None, tol=1e-9, candidates=4):
        """(slice id, fieldpos, λ [Å]) of detector points (p_x, p_y) [px].

        Points that are not on a trace (no slice with fieldpos in the node range
        and λ in ``lbda_range``, default the node range, whose forward map hits
        the point to ``tol`` px) get slice id 0 and NaN.

        Parameters
        ----------
        p_x, p_y : array_like
            Detector points [px].
        slice_id : int or array_like of int, optional
            Restrict the search to that slice (broadcast).
        lbda_range : tuple of float, optional
            (min, max) [Å] searched (default: the node range).
        tol : float, optional
            Tolerance of the forward map [px].
        candidates : int, optional
            Nearest seed points of the search tried per point.

        Returns
        -------
        slice_id : numpy.ndarray
            Slice ids (0: not on a trace).
        fieldpos : numpy.ndarray
            Position along the slice (NaN: not on a trace).
        lbda : numpy.ndarray
            Wavelength [Å] (NaN: not on a trace).
        """
        px, py = np.broadcast_arrays(np.asarray(p_x, np.float64), np.asarray(p_y, np.float64))
        shape = px.shape
        target = np.stack([px.ravel(), py.ravel()], axis=1)
        n = target.shape[0]
        lo, hi = (self.lbda_nodes[0], self.lbda_nodes[-1]) if lbda_range is None else lbda_range
        trees = self._seed_grid()
        if slice_id is None:
            k = min(int(candidates), trees["all"].n)
            _, nb = trees["all"].query(target, k=k)
            nb = nb.reshape(n, k)
            cand = [tuple(a[nb[:, c]] for a in trees["seeds"]) for c in range(k)]
        else:
            sidx = self.slice_index(np.broadcast_to(np.asarray(slice_id), shape).ravel())
            seed = np.empty((n, 2))
            for s in np.unique(sidx):
                sel = sidx == s
                _, i = trees["per_slice"][s].query(target[sel])
                seed[sel] = np.stack([trees["per_slice_seeds"][1][s][i], trees["per_slice_seeds"][2][s][i]], 1)
            cand = [(sidx, seed[:, 0], seed[:, 1])]
        out_s = np.zeros(n, np.int64)
        out_p = np.full(n, np.nan)
        out_l = np.full(n, np.nan)
        todo = np.ones(n, bool)
        eps = 1e-9 * (self.fieldpos_nodes[-1] - self.fieldpos_nodes[0])
        for sidx, phi0, lam0 in cand:
            i = np.flatnonzero(todo)
            if i.size == 0:
                break
            phi, lam, res = self._newton(sidx[i], phi0[i], lam0[i], target[i], tol)
            ok = ((res <= tol) & (phi >= self.fieldpos_nodes[0] - eps) & (phi <= self.fieldpos_nodes[-1] + eps)
                  & (lam >= lo) & (lam <= hi))
            i = i[ok]
            out_s[i] = self.slice_ids[sidx[i]]
            out_p[i], out_l[i] = phi[ok], lam[ok]
            todo[i] = False
        return out_s.reshape(shape), out_p.reshape(shape), out_l.reshape(shape)

    def show_slices(self, fields=("narrow", "wide"), spectrograph=None, *, image=None, region=None, labels=True,
                    ax=None, savefile=None):
        """Figure of the detector with every slice's footprint outlined and labelled
        (:func:`slicersim.plotting.images.draw_slices`).

        Parameters
        ----------
        fields : str or sequence of str, optional
            "narrow" (slices 1–58) and/or "wide" (59–116).
        spectrograph : Spectrograph, Simulation or Target, optional
            The cube grid (default: 200 bins over the λ nodes [Å], 116 columns).
        image : array_like of shape (rows, cols), optional
            A detector image [e-/s/px] behind the outlines (default: the label image).
        region : tuple of int, optional
            (row0, row1, col0, col1) [px] zooms in.
        labels : bool, optional
            Write each slice id at the blue end of its trace.
        ax : matplotlib.axes.Axes, optional
            None (new figure) or an Axes.
        savefile : str, os.PathLike or file object, optional
            If given the figure is saved there.

        Returns
        -------
        matplotlib.figure.Figure
            The figure.
        """
        from slicersim.instrument.footprints import detector_label_image, field_footprints
        from slicersim.plotting import check_region, draw_slices
        fields = (fields,) if isinstance(fields, str) else tuple(fields)
        for field in fields:
            validation.choice("fields", field, ("narrow", "wide"))
        grid = {"spectrograph": spectrograph} if spectrograph is not None else {
            "lbda_edges": np.linspace(self.lbda_nodes[0], self.lbda_nodes[-1], 201), "ncol": 116}
        footprints = [field_footprints(self, field, **grid) for field in fields]
        region = None if region is None else check_region(region, self.detector_shape)
        label_image = detector_label_image(*footprints) if image is None else None
        return draw_slices(footprints, image, label_image, region=region, labels=labels, ax=ax, savefile=savefile)
