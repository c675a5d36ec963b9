"""Projection of cubes onto the detector by a :class:`~slicersim.instrument.mapper.SlicerMapper`,
as its mixin :class:`ProjectionMixin`: the detector boxes of the cube cells, the projection
tables (cached in memory and on disk) and the flux-conserving projection of one field's cube
or of both fields (the method is described in :mod:`slicersim.instrument.mapper`), plus
:func:`detector_rate_image`, the expected rate of the whole detector.

The mixin reads the mapper through its forward map (``forward_grid``), node grids, spot values,
pixel size, ``cube_blur_px``, ``detector_shape`` and table caches (``_cache``,
``_cache_size``, ``_disk_keys``, ``table_cache``).  :func:`detector_rate_image` is re-exported
by :mod:`slicersim.instrument.mapper`, its import path.
"""
from __future__ import annotations

import functools
import hashlib
from pathlib import Path

import numpy as np

from slicersim.backends.precision import resolve_precision
from slicersim.backends.projection import (backend_tag, build_tables, default_block, deposit, load_tables,
                                          resolve_table_cache, store_tables, table_key)
from slicersim.errors import ParameterError
from slicersim.instrument.slices import NARROW_SLICES, WIDE_SLICES

__all__ = ["ProjectionMixin", "detector_rate_image"]


@functools.lru_cache(maxsize=1)
def _code_digest():
    """SHA-256 of the sources of the mapper and of this module (the forward map and the cell
    boxes they compute key the table cache)."""
    here = Path(__file__)
    return hashlib.sha256(here.with_name("mapper.py").read_bytes() + here.read_bytes()).hexdigest()


class ProjectionMixin:
    """Cell boxes, projection tables and cube projection of a
    :class:`~slicersim.instrument.mapper.SlicerMapper` (a base class of it, whose page documents
    these methods)."""

    # ------------------------------------------------------------------ projection
    def cell_boxes(self, slices, ncol, lbda_edges, oversample=(1, 1)):
        """Detector boxes ax, bx, sx, ay, by, sy [px] of the (sub-)cells, (s, e, q) order.

        x-extent: between the mean x of the cell's two corners at each fieldpos
        edge; y-extent: between the mean y at each λ edge (neighbouring cells
        share their edges exactly).  The cross terms (x change along λ, y change
        along fieldpos, w) widen the spot: σ² = max(0, rms² − b²) + w²/12, b = ``cube_blur_px``
        (the aberration the projected cube already carries in its LSF and spatial blur: the
        table's spot is the total aberration, counted once).

        Parameters
        ----------
        slices : sequence of int
            Slice ids.
        ncol : int
            Cube columns per slice.
        lbda_edges : array_like of shape (nλ+1,)
            Bin edges [Å].
        oversample : tuple of int, optional
            (n_λ, n_φ) sub-cells per cell.

        Returns
        -------
        numpy.ndarray of shape (N, 6)
            ax, bx, sx, ay, by, sy [px] of the (sub-)cells, (s, e, q) order.
        """
        ne, nq = (int(v) for v in oversample)
        edges = np.asarray(lbda_edges, np.float64)
        frac = np.arange(ne) / ne
        lam = np.append((edges[:-1, None] + np.diff(edges)[:, None] * frac[None]).ravel(), edges[-1])
        phi = np.linspace(-1.0, 1.0, ncol * nq + 1)
        X, Y = self.forward_grid(slices, phi, lam, (0, 1)).swapaxes(0, 1)  # (S, E+1, Q+1) each
        rms = self.forward_grid(slices, 0.5 * (phi[1:] + phi[:-1]), 0.5 * (lam[1:] + lam[:-1]), (2, 3))
        S, E, Q = X.shape[0], X.shape[1] - 1, X.shape[2] - 1
        box = np.empty((S, E, Q, 6))
        x_q0 = 0.5 * (X[:, :-1, :-1] + X[:, 1:, :-1])         # mean x at fieldpos edge q
        x_q1 = 0.5 * (X[:, :-1, 1:] + X[:, 1:, 1:])           # ... and q + 1
        np.minimum(x_q0, x_q1, out=box[..., 0])
        np.maximum(x_q0, x_q1, out=box[..., 1])
        # the spot's aberration already in the cube (its LSF and spatial blur) is not applied twice
        extra = [np.maximum(rms[:, k] ** 2 - self.cube_blur_px[k] ** 2, 0.0) for k in (0, 1)]
        shear = 0.5 * ((X[:, 1:, :-1] - X[:, :-1, :-1]) + (X[:, 1:, 1:] - X[:, :-1, 1:]))
        box[..., 2] = np.sqrt(extra[0] + shear ** 2 / 12.0)
        y_e0 = 0.5 * (Y[:, :-1, :-1] + Y[:, :-1, 1:])         # mean y at λ edge e
        y_e1 = 0.5 * (Y[:, 1:, :-1] + Y[:, 1:, 1:])           # ... and e + 1
        np.minimum(y_e0, y_e1, out=box[..., 3])
        np.maximum(y_e0, y_e1, out=box[..., 4])
        shear = 0.5 * ((Y[:, :-1, 1:] - Y[:, :-1, :-1]) + (Y[:, 1:, 1:] - Y[:, 1:, :-1]))
        box[..., 5] = np.sqrt(extra[1] + shear ** 2 / 12.0)
        return box.reshape(-1, 6)

    def projection_tables(self, slices, ncol, lbda_edges, *, oversample=(1, 1), truncate=4.0,
                          weights_dtype=np.float32, block=None, backend="auto"):
        """``slicersim.backends.projection.DepositTables`` for a field and λ grid.

        With a disk cache (``table_cache``, see ``slicersim.io.table_cache``) the tables
        are built once per content key (``slicersim.backends.projection.table_key``: the
        cell boxes, grid, truncation, dtype, backend, code version) and read back
        memory-mapped; nothing is kept in this object but the key, so the tables leave memory
        when the caller drops them.  Without one (or when it cannot be written) they are kept
        in memory here (``cache_size`` of them, :meth:`release_tables` drops them).

        Parameters
        ----------
        slices : sequence of int
            Slice ids of the field.
        ncol : int
            Cube columns per slice.
        lbda_edges : array_like of shape (nλ+1,)
            Bin edges [Å].
        oversample, truncate, weights_dtype, block, backend
            As :meth:`project_cube`.

        Returns
        -------
        DepositTables
            The projection tables.
        """
        slices = tuple(int(s) for s in slices)
        edges = np.ascontiguousarray(lbda_edges, dtype=np.float64)
        block = default_block(backend) if block is None else int(block)
        key = (slices, int(ncol), hashlib.sha1(edges.tobytes()).hexdigest(), tuple(oversample),
               float(truncate), np.dtype(weights_dtype).str, block)
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        disk = resolve_table_cache(self.table_cache)
        memo = (key, disk, backend_tag(backend)) if disk is not None else None
        disk_key = self._disk_keys.get(memo)
        if disk is not None and disk_key is not None:
            tables = load_tables(disk, disk_key)
            if tables is not None:
                return tables
        ne, nq = (int(v) for v in oversample)
        grid = (len(slices), (edges.size - 1) * ne, ncol * nq)
        options = dict(detector_shape=self.detector_shape, truncate=truncate, weights_dtype=weights_dtype,
                       block=block, backend=backend)
        if disk is not None:
            disk_key = table_key(self._geometry(slices, ncol, edges), grid, (ne, nq), **options)
            self._disk_keys[memo] = disk_key
            tables = load_tables(disk, disk_key)
            if tables is not None:
                return tables
        box = self.cell_boxes(slices, ncol, edges, (ne, nq))
        tables = build_tables(box, grid, (ne, nq), **options)
        del box
        if disk is not None:
            stored = store_tables(disk, disk_key, tables)
            if stored is not tables:
                return stored
        self._cache[key] = tables
        while len(self._cache) > self._cache_size:
            self._cache.popitem(last=False)
        return tables

    def _geometry(self, slices, ncol, edges):
        """What :meth:`cell_boxes` depends on, for the table cache key: the node grids, spot
        values, interpolation, face diagonals, pixel size, slices, columns, λ edges and this
        module's code (which computes the boxes)."""
        return {"slice_ids": self.slice_ids, "fieldpos": self.fieldpos_nodes, "lbda": self.lbda_nodes,
                "values": self.values, "interpolation": self.interpolation, "diagonal": self.face_diagonal,
                "pixel_size_um": self.pixel_size_um, "cube_blur_px": self.cube_blur_px,
                "slices": tuple(slices), "ncol": int(ncol),
                "edges": np.asarray(edges, np.float64), "code": _code_digest()}

    def release_tables(self):
        """Drop the projection tables held in memory (those on disk stay there).

        Returns
        -------
        None
            The memory cache is emptied in place.
        """
        self._cache.clear()

    def clear_cache(self):
        """Forget the projection tables held in memory (and the inverse-map seeds).

        Returns
        -------
        None
            The caches are emptied in place.
        """
        self._cache.clear()
        self._disk_keys.clear()
        self._trees = None

    def project_cube(self, cube, lbda, lbda_edges, slices=NARROW_SLICES, out=None, *, backend="auto",
                     oversample=(1, 1), truncate=4.0, weights_dtype=np.float32, block=None, precision="auto"):
        """Flux-conserving detector image of one field's cube.

        Parameters
        ----------
        cube : array_like of shape (nλ, n_rows, n_cols)
            Value per cell per bin (ADU, e-/s, ...); the image is in the same unit per pixel.
        lbda : array_like of shape (nλ,)
            Bin centres [Å] (checked only).
        lbda_edges : array_like of shape (nλ+1,)
            Bin edges [Å].
        slices : sequence of int or {"narrow", "wide"}, optional
            n_rows slice ids: cube row r ↔ slice ``slices[n_rows − 1 − r]``.
        out : numpy.ndarray of shape (rows, cols), optional
            float64 image accumulated into in place.
        backend : str, optional
            "auto", "opencl" or "numpy".
        oversample : tuple of int, optional
            (n_λ, n_φ) sub-cells per cell.
        truncate : float, optional
            Window half-width beyond each cell box [spot rms].
        weights_dtype : numpy.dtype, optional
            dtype of the projection tables' weights.
        block : int, optional
            Block size of the table builder (default: the backend's).
        precision : {"auto", "double", "single"}, optional
            Of the deposit (``slicersim.backends.projection.deposit``; the tables are built in
            double), checked before any work.

        Returns
        -------
        numpy.ndarray of shape (rows, cols)
            The detector image (``out`` when given).
        """
        precision = resolve_precision(precision, backend, "projection")[1]
        if isinstance(slices, str):
            slices = {"narrow": NARROW_SLICES, "wide": WIDE_SLICES}[slices]
        slices = [int(s) for s in slices]
        cube = np.asarray(cube)
        lbda = np.asarray(lbda, np.float64)
        edges = np.asarray(lbda_edges, np.float64)
        if cube.ndim != 3 or cube.shape[1] != len(slices):
            raise ParameterError(f"cube must have shape (nlbda, {len(slices)}, ncol), got {cube.shape}")
        if not np.all(np.isfinite(cube)):
            raise ParameterError("cube: values must be finite (replace NaN, e.g. saturated cells, first)")
        if lbda.shape != (cube.shape[0],) or edges.shape != (cube.shape[0] + 1,):
            raise ParameterError(f"lbda must have shape ({cube.shape[0]},) and lbda_edges ({cube.shape[0] + 1},)")
        if np.any(np.diff(edges) <= 0) or np.any(lbda < edges[:-1]) or np.any(lbda > edges[1:]):
            raise ParameterError("lbda_edges must increase and bracket the bin centres lbda")
        self.slice_index(slices)
        tables = self.projection_tables(slices, cube.shape[2], edges, oversample=oversample,
                                        truncate=truncate, weights_dtype=weights_dtype, block=block,
                                        backend=backend)
        value = cube[:, ::-1, :].transpose(1, 0, 2)                         # (slice, bin, column)
        return deposit(value, tables, out=out, backend=backend, precision=precision)

    def project_fields(self, lbda, lbda_edges, narrow=None, wide=None, out=None, **kwargs):
        """Image of the narrow (slices 1–58) and wide (59–116) cubes together.

        Parameters
        ----------
        lbda : array_like of shape (nλ,)
            Bin centres [Å].
        lbda_edges : array_like of shape (nλ+1,)
            Bin edges [Å].
        narrow, wide : array_like of shape (nλ, 58, ncol), optional
            The cubes of the two fields (value per cell per bin).
        out : numpy.ndarray of shape (rows, cols), optional
            float64 image accumulated into.
        **kwargs
            Of :meth:`project_cube` (``precision`` checked before the image is allocated).

        Returns
        -------
        numpy.ndarray of shape (rows, cols)
            The image, in the cubes' unit per pixel.
        """
        resolve_precision(kwargs.get("precision", "auto"), kwargs.get("backend", "auto"), "projection")
        if out is None:
            out = np.zeros(self.detector_shape)
        for cube, slices in ((narrow, NARROW_SLICES), (wide, WIDE_SLICES)):
            if cube is not None:
                self.project_cube(cube, lbda, lbda_edges, slices, out=out, **kwargs)
        return out


def detector_rate_image(mapper, lbda, lbda_edges, narrow=None, wide=None, *, dark=0.0, thermal_dark=0.0,
                        roic_glow=None, tframe=None, **kwargs):
    """Expected electron rate per pixel [e-/s/px] of the whole detector.

    ``narrow`` / ``wide``: photo-electron rate cubes [e-/s per cell per bin]
    (photon cube × QE), projected flux-conservingly.  ``dark`` [e-/s/px] and
    ``thermal_dark`` [e-/s/px, scalar or image] are added to **every** pixel,
    painted or not.  ROIC glow is a charge per frame read [e-/px/frame]: it is
    added as the rate ``roic_glow / tframe`` only when both are given (the
    same D_eff = dark + glow/t_f + thermal dark as the noise model); a ramp
    simulator that adds glow per read should leave it out here.

    Parameters
    ----------
    mapper : SlicerMapper
        The detector mapping.
    lbda : array_like of shape (nλ,)
        Bin centres of the cubes [Å].
    lbda_edges : array_like of shape (nλ+1,)
        Bin edges of the cubes [Å].
    narrow, wide : numpy.ndarray of shape (nλ, ny, nx), optional
        Photo-electron rate cubes of the two fields [e-/s per cell per bin] (photon cube ×
        QE), projected flux-conservingly.
    dark : float, optional
        Dark current added to **every** pixel, painted or not [e-/s/px].
    thermal_dark : float or numpy.ndarray of shape (rows, cols), optional
        Thermal dark added to every pixel [e-/s/px].
    roic_glow : float, optional
        ROIC glow, a charge per frame read [e-/px/frame]; needs ``tframe``.
    tframe : float, optional
        Frame time [s] (> 0 when ``roic_glow`` is given).
    **kwargs
        Options of :meth:`SlicerMapper.project_cube` (``backend``, ``precision`` of the
        deposit, ...).

    Returns
    -------
    numpy.ndarray of shape (rows, cols)
        The rate image of the whole detector [e-/s/px].
    """
    img = mapper.project_fields(lbda, lbda_edges, narrow=narrow, wide=wide, **kwargs)
    img += dark
    img += thermal_dark
    if roic_glow is not None:
        if tframe is None or not tframe > 0:
            raise ParameterError("roic_glow [e-/px/frame] needs the frame time tframe [s] > 0")
        img += roic_glow / tframe
    return img
