"""Where each slice lands on the detector: footprint masks, outlines, label image, traces.

Computed from the mapper's geometry alone (:meth:`SlicerMapper.cell_boxes
<slicersim.instrument.mapper.SlicerMapper.cell_boxes>`), without projecting a cube.  For a
field's cube grid (``ncol`` columns per slice, λ bin edges [Å]) each cube cell (slice s,
column k, bin i) deposits its light inside the pixel window of the projection
(:mod:`slicersim.backends.projection`): the cell's detector box widened by ``truncate``
spot rms on each side, floor(lo − t·σ) … floor(hi + t·σ) along each axis, clipped to the
detector.  So:

* **mask** of slice s: the union of its cells' windows = the pixels that receive light of
  that slice when any positive cube is projected with the same grid and ``truncate``;
* **core** of slice s: the same union with no blur (t = 0): the pixels its geometric
  image overlaps;
* **label image**: slice id per pixel, ``NO_SLICE`` (−1) where no slice sends light.
  With the 4σ windows neighbouring slices share a few columns of faint tails (the Lazuli
  layouts: pitch 121 px, slices ≤ 116 px long, spots 0.8–1.5 px rms); such a pixel goes
  to the slice whose core is nearest to it (distance [px] along its row, or from the core's
  end row; ties to the lower slice id) — to a good approximation the slice that deposits
  most light there.  :meth:`FieldFootprints.overlaps` reports the shared pixels;
* **outlines**: closed polygons along pixel edges, vertices (x, y) [px] in the mapper's
  convention (pixel column c covers x ∈ [c, c+1), row r covers y ∈ [r, r+1)); the first is
  the outer contour (counter-clockwise with y up), further ones holes (clockwise) or
  separate pieces.  A pixel centre lies inside the polygons (even–odd rule) exactly when
  the pixel is in the mask;
* **trace**: the slice centre line (fieldpos 0) at the bin centres, (λ [Å], x [px], y [px]),
  and ``lbda_range`` [Å], the edges of the bins whose windows reach the detector.

Footprints of one (mapper, field, grid, truncate) are computed once per process (a full
Lazuli field — 58 slices × 116 columns × 510 bins — takes ~1 s, its label image 0.1–0.4 s) and kept
(:func:`field_footprints`, a few per mapper).
"""
from __future__ import annotations

import hashlib
import weakref
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from slicersim import validation
from slicersim.errors import ParameterError
from slicersim.instrument.slices import NARROW_SLICES, WIDE_SLICES
from slicersim.io import footprint_files
from slicersim.io.row_blocks import row_ranges

__all__ = ["SliceFootprint", "FieldFootprints", "field_footprints", "detector_label_image", "save_footprints",
           "mask_outlines", "polygon_area", "FIELD_SLICES", "NO_SLICE", "FOOTPRINT_FORMAT"]

#: slice ids of each Lazuli field (cube row r ↔ slice ``slices[n_rows − 1 − r]``)
FIELD_SLICES = {"narrow": NARROW_SLICES, "wide": WIDE_SLICES}
#: label of pixels that receive no light
NO_SLICE = -1
#: ``format`` and ``version`` of the outlines file written by :func:`save_footprints`
FOOTPRINT_FORMAT = ("slicersim-footprints", 1)
_SLICES_PER_CHUNK = 8          # cell boxes of this many slices at a time (~24 MB for Lazuli)
_CACHE_PER_MAPPER = 4
_CACHE = weakref.WeakKeyDictionary()


# --------------------------------------------------------------------------- #
#  outlines of a pixel mask                                                    #
# --------------------------------------------------------------------------- #
def mask_outlines(mask, origin=(0, 0)):
    """Closed outlines of a boolean pixel mask along pixel edges.

    Returns a list of (K, 2) float arrays of vertices (x, y) [px] (x = column + origin[1],
    y = row + origin[0]; pixel (r, c) is the square [c, c+1] × [r, r+1]), corners only, not
    repeating the first vertex.  Pixels touching only at a corner belong to separate loops
    (4-connectivity).  The region lies on the left of each loop: outer contours run
    counter-clockwise (positive area with y up), holes clockwise; the list is sorted by
    decreasing signed area, so the largest outer contour comes first.
    """
    m = np.asarray(mask, dtype=bool)
    if m.ndim != 2:
        raise ParameterError(f"mask must be 2-D, got shape {m.shape}")
    h, w = m.shape
    p = np.zeros((h + 2, w + 2), bool)
    p[1:-1, 1:-1] = m
    inner = p[1:-1, 1:-1]
    r, c = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    W = w + 1
    # directed edges with the region on their left: (start vertex, direction); dir 0 +x, 1 +y, 2 −x, 3 −y
    starts, dirs = [], []
    for d, (nbr, sx, sy) in enumerate(((p[:-2, 1:-1], 0, 0), (p[1:-1, 2:], 1, 0),
                                       (p[2:, 1:-1], 1, 1), (p[1:-1, :-2], 0, 1))):
        sel = inner & ~nbr
        starts.append(((r[sel] + sy) * W + c[sel] + sx).ravel())
        dirs.append(np.full(int(sel.sum()), d, np.int64))
    if not any(s.size for s in starts):
        return []
    start = np.concatenate(starts).astype(np.int64)
    direction = np.concatenate(dirs)
    step = np.array([1, W, -1, -W], np.int64)
    end = start + step[direction]
    out = np.full(((h + 1) * W, 4), -1, np.int64)
    out[start, direction] = np.arange(start.size)
    succ = np.full(start.size, -1, np.int64)
    for turn in (3, 0, 1):          # left turn first (keeps the loop tight: 4-connectivity)
        cand = out[end, (direction + 4 - turn) % 4]
        take = (succ < 0) & (cand >= 0)
        succ[take] = cand[take]
    if np.any(succ < 0):            # pragma: no cover - every vertex has as many edges in as out
        raise RuntimeError("internal error: open outline")
    succ_l, dir_l, start_l = succ.tolist(), direction.tolist(), start.tolist()
    seen = np.zeros(start.size, bool)
    loops = []
    for e0 in range(start.size):
        if seen[e0]:
            continue
        chain = []
        e = e0
        while not seen[e]:
            seen[e] = True
            chain.append(e)
            e = succ_l[e]
        corners = [start_l[k] for i, k in enumerate(chain) if dir_l[k] != dir_l[chain[i - 1]]]
        v = np.asarray(corners, np.int64)
        xy = np.stack([v % W + origin[1], v // W + origin[0]], axis=1).astype(np.float64)
        loops.append(xy)
    loops.sort(key=lambda xy: -polygon_area(xy))
    return loops


def polygon_area(xy):
    """Signed area (shoelace) [px²] of a closed polygon (K, 2): > 0 counter-clockwise (y up)."""
    x, y = np.asarray(xy, np.float64).T
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


# --------------------------------------------------------------------------- #
#  footprints                                                                  #
# --------------------------------------------------------------------------- #
@dataclass(frozen=True, eq=False)
class SliceFootprint:
    """Footprint of one slice on the detector (arrays cropped to its bounding box).

    Parameters
    ----------
    slice_id : int
        Id of the slice.
    field : str
        Name of its field.
    origin : tuple of int
        (row, column) of ``mask``/``core`` on the detector [px].
    mask : numpy.ndarray of shape (h, w)
        Pixels lit by the slice, in its bounding box.
    core : numpy.ndarray of shape (h, w)
        Pixels of the slice's core, in the same box.
    outlines : tuple
        Outlines of the mask (see ``mask_outlines`` in ``slicersim.instrument.footprints``).
    lbda_range : tuple of float
        (min, max) wavelength of the slice [Å].
    trace_lbda : numpy.ndarray of shape (nλ,)
        Bin centres of the trace [Å].
    trace_x, trace_y : numpy.ndarray of shape (nλ,)
        Detector position of the slice centre (fieldpos 0) at those wavelengths [px].
    """

    slice_id: int
    field: str
    origin: tuple
    mask: np.ndarray
    core: np.ndarray
    outlines: tuple
    lbda_range: tuple
    trace_lbda: np.ndarray
    trace_x: np.ndarray
    trace_y: np.ndarray

    @property
    def contour(self):
        """Outer contour (K, 2) [px]: vertices (x, y) of the largest outline."""
        return self.outlines[0]

    @property
    def bbox(self):
        """(row0, row1, col0, col1) [px], ends exclusive."""
        (r0, c0), (h, w) = self.origin, self.mask.shape
        return r0, r0 + h, c0, c0 + w

    @property
    def npix(self):
        """Number of pixels receiving light of this slice."""
        return int(np.count_nonzero(self.mask))

    def pixels(self):
        """The footprint's pixels on the detector.

        Returns
        -------
        rows, cols : numpy.ndarray
            Their row and column indices [px].
        """
        rows, cols = np.nonzero(self.mask)
        return rows + self.origin[0], cols + self.origin[1]

    def detector_mask(self, detector_shape, core=False):
        """Boolean image of the whole detector.

        Parameters
        ----------
        detector_shape : tuple of int
            (rows, cols) of the detector [px].
        core : bool, optional
            The unblurred footprint.

        Returns
        -------
        numpy.ndarray of shape (rows, cols)
            bool mask.
        """
        img = np.zeros(tuple(detector_shape), bool)
        r0, r1, c0, c1 = self.bbox
        img[r0:r1, c0:c1] = self.core if core else self.mask
        return img

    def trace(self):
        """The slice centre at the bin centres.

        Returns
        -------
        lbda : numpy.ndarray of shape (nλ,)
            Wavelengths [Å].
        x, y : numpy.ndarray of shape (nλ,)
            Detector position [px].
        """
        return self.trace_lbda, self.trace_x, self.trace_y


class FieldFootprints:
    """Footprints of every slice of a field, indexed by slice id (``fp[12]``, ``for s in fp``).

    Built by :func:`field_footprints`.  ``lbda_edges``, ``ncol``, ``truncate`` and
    ``oversample`` are the projection grid the footprints are exact for.

    Parameters
    ----------
    field : str
        Name of the field ("narrow", "wide", ...).
    footprints : sequence of SliceFootprint
        The footprint of each slice.
    detector_shape : tuple of int
        (rows, cols) of the detector [px].
    lbda_edges : numpy.ndarray of shape (nλ+1,)
        Bin edges of the cube grid [Å].
    ncol : int
        Cube columns per slice.
    truncate : float
        Window half-width beyond each cell box [spot rms].
    oversample : tuple of int, optional
        (n_λ, n_φ) sub-cells per cell.
    """

    def __init__(self, field, footprints, detector_shape, lbda_edges, ncol, truncate, oversample=(1, 1)):
        self.field = field
        self._fp = dict(footprints)
        self.detector_shape = tuple(int(v) for v in detector_shape)
        self.lbda_edges = np.asarray(lbda_edges, np.float64)
        self.ncol, self.truncate, self.oversample = int(ncol), float(truncate), tuple(oversample)
        self._label = self._pairs = None

    def __repr__(self):
        return (f"FieldFootprints({self.field!r}, {len(self)} slices, {self.lbda_edges.size - 1} bins "
                f"[{self.lbda_edges[0]:.0f}-{self.lbda_edges[-1]:.0f} AA] x {self.ncol} columns, "
                f"truncate {self.truncate:g} rms)")

    def __len__(self):
        return len(self._fp)

    def __iter__(self):
        return iter(self._fp.values())

    def __getitem__(self, slice_id):
        try:
            return self._fp[int(slice_id)]
        except (KeyError, TypeError, ValueError):
            raise ParameterError(f"slice {slice_id!r} is not in the {self.field} field "
                                 f"({min(self._fp)}-{max(self._fp)})") from None

    @property
    def slice_ids(self):
        return np.array(list(self._fp), np.int64)

    def detector_rows(self, margin=16, reference_rows=4):
        """The detector rows a reduction of this field reads: the rows of its slices' footprints,
        ``margin`` rows on each side (the neighbourhoods the reduction looks at: IPC, outlier medians,
        the side reference pixels smoothed over 11 rows), and the top and bottom ``reference_rows``
        (the reference-pixel correction's column terms).

        Parameters
        ----------
        margin : int, optional
            Rows added on each side of the footprints [px].
        reference_rows : int, optional
            Reference rows kept at the top and the bottom of the detector [px].

        Returns
        -------
        tuple of (int, int)
            Sorted, disjoint row ranges [y0, y1) (``simulate(rows=...)``).
        """
        margin = validation.integer("margin", margin, low=0)
        reference_rows = validation.integer("reference_rows", reference_rows, low=0)
        ny = self.detector_shape[0]
        ranges = [(max(0, fp.origin[0] - margin), min(ny, fp.origin[0] + fp.mask.shape[0] + margin)) for fp in self]
        if reference_rows:
            ranges += [(0, min(ny, reference_rows)), (max(0, ny - reference_rows), ny)]
        return row_ranges(ranges, ny, "rows")

    def mask(self, slice_id, core=False):
        """Boolean detector image of one slice's footprint.

        Parameters
        ----------
        slice_id : int
            The slice.
        core : bool, optional
            The unblurred footprint.

        Returns
        -------
        numpy.ndarray of shape (rows, cols)
            bool mask.
        """
        return self[slice_id].detector_mask(self.detector_shape, core)

    def union_mask(self):
        """Pixels receiving light of any slice of the field.

        Returns
        -------
        numpy.ndarray of shape (rows, cols)
            bool mask.
        """
        return self.label_image() != NO_SLICE

    def contours(self):
        """The outer contour of each slice.

        Returns
        -------
        dict
            {slice id: outer contour of shape (K, 2) [px]}.
        """
        return {s: fp.contour for s, fp in self._fp.items()}

    def label_image(self):
        """Slice id per pixel, ``NO_SLICE`` (−1) where no light falls; shared pixels go to the slice
        with the nearest core (module docstring).

        Returns
        -------
        numpy.ndarray of shape (rows, cols)
            int32 label image.
        """
        if self._label is None:
            label = np.full(self.detector_shape, NO_SLICE, np.int32)
            best = np.full(self.detector_shape, np.inf, np.float32)
            for sid, fp in self._fp.items():
                r0, r1, c0, c1 = fp.bbox
                d = np.where(fp.mask, _core_distance(fp.core), np.inf).astype(np.float32)
                win = best[r0:r1, c0:c1]
                take = d < win                # strict: ties stay with the lower id (sorted order)
                win[take] = d[take]
                label[r0:r1, c0:c1][take] = sid
            label.flags.writeable = False
            self._label = label
        return self._label

    def overlaps(self):
        """Every pair of slices whose masks share pixels (a < b).

        Returns
        -------
        list of tuple
            [(slice a, slice b, shared pixels)]; empty when the footprints are disjoint.
        """
        if self._pairs is None:
            fps = list(self._fp.values())
            box = np.array([fp.bbox for fp in fps]).reshape(-1, 4)
            pairs = []
            for i, a in enumerate(fps):
                hit = ((box[i + 1:, 0] < box[i, 1]) & (box[i, 0] < box[i + 1:, 1])
                       & (box[i + 1:, 2] < box[i, 3]) & (box[i, 2] < box[i + 1:, 3]))
                for j in np.flatnonzero(hit) + i + 1:
                    b = fps[j]
                    r0, r1 = max(box[i, 0], box[j, 0]), min(box[i, 1], box[j, 1])
                    c0, c1 = max(box[i, 2], box[j, 2]), min(box[i, 3], box[j, 3])
                    ma = a.mask[r0 - box[i, 0]:r1 - box[i, 0], c0 - box[i, 2]:c1 - box[i, 2]]
                    mb = b.mask[r0 - box[j, 0]:r1 - box[j, 0], c0 - box[j, 2]:c1 - box[j, 2]]
                    n = int(np.count_nonzero(ma & mb))
                    if n:
                        lo, hi = sorted((a.slice_id, b.slice_id))
                        pairs.append((lo, hi, n))
            self._pairs = sorted(pairs)
        return list(self._pairs)

    def polygons(self):
        """Plain description for files.

        Returns
        -------
        dict
            The grid (``field``, ``truncate``, ``ncol``, ``nbins``, ``lbda_min``/``lbda_max``
            [Å]) and ``slices``: per slice its id, ``lbda_range`` [Å], ``bbox`` (row0, row1, col0,
            col1) [px], ``npix``, ``outlines`` (lists of [x, y] [px]) and ``trace`` (``lbda`` [Å],
            ``x``, ``y`` [px] of the slice centre, rounded to 1e-4).
        """
        return {"field": self.field, "truncate": self.truncate, "ncol": self.ncol,
                "nbins": int(self.lbda_edges.size - 1), "oversample": list(self.oversample),
                "lbda_min": float(self.lbda_edges[0]), "lbda_max": float(self.lbda_edges[-1]),
                "detector_shape": list(self.detector_shape),
                "slices": [{"slice_id": fp.slice_id, "lbda_range": [float(v) for v in fp.lbda_range],
                            "bbox": [int(v) for v in fp.bbox], "npix": fp.npix,
                            "outlines": [xy.tolist() for xy in fp.outlines],
                            "trace": {"lbda": np.round(fp.trace_lbda, 4).tolist(),
                                      "x": np.round(fp.trace_x, 4).tolist(),
                                      "y": np.round(fp.trace_y, 4).tolist()}} for fp in self]}


def _core_distance(core):
    """Distance [px] of each pixel of the box to the core: along its row to the row's core
    extent, or, on rows without core, Euclidean to the extent of the nearest core row."""
    h, w = core.shape
    rows = np.flatnonzero(core.any(axis=1))
    if rows.size == 0:
        return np.full((h, w), np.inf)
    first = np.argmax(core[rows], axis=1)
    last = w - 1 - np.argmax(core[rows, ::-1], axis=1)
    ar = np.arange(h)
    pos = np.searchsorted(rows, ar)                       # first core row at or after each row
    lo, hi = np.clip(pos - 1, 0, rows.size - 1), np.clip(pos, 0, rows.size - 1)
    k = np.where(np.abs(rows[lo] - ar) <= np.abs(rows[hi] - ar), lo, hi)
    dy = np.abs(rows[k] - ar)[:, None]
    col = np.arange(w)[None]
    dx = np.maximum(np.maximum(first[k][:, None] - col, col - last[k][:, None]), 0)
    return np.hypot(dx, dy)


def _rasterise(y0, y1, x0, x1, shape):
    """Union of pixel rectangles [y0, y1) × [x0, x1) (local, clipped) as a boolean image."""
    h, w = shape
    acc = np.zeros((h + 1) * (w + 1), np.int64)
    for ys, xs, sign in ((y0, x0, 1), (y0, x1, -1), (y1, x0, -1), (y1, x1, 1)):
        acc += sign * np.bincount(ys * (w + 1) + xs, minlength=acc.size)
    cover = acc.reshape(h + 1, w + 1).cumsum(axis=0).cumsum(axis=1)
    return cover[:h, :w] > 0


def _windows(lo, hi, sigma, truncate, size):
    """Pixel windows [start, stop) of the projection along one axis, clipped to [0, size)."""
    start = np.floor(lo - truncate * sigma)
    stop = np.floor(hi + truncate * sigma) + 1
    return np.clip(start, 0, size).astype(np.int64), np.clip(stop, 0, size).astype(np.int64)


def _slice_footprints(mapper, field, slices, edges, ncol, truncate, oversample):
    """{slice id: SliceFootprint} from the cell boxes, a few slices at a time."""
    ne, nq = oversample
    H, W = mapper.detector_shape
    centres = 0.5 * (edges[:-1] + edges[1:])
    tx, ty = mapper.forward(np.asarray(slices)[:, None], 0.0, centres[None, :])
    out = {}
    per_slice = (edges.size - 1) * ne * ncol * nq
    for i0 in range(0, len(slices), _SLICES_PER_CHUNK):
        chunk = slices[i0:i0 + _SLICES_PER_CHUNK]
        box = mapper.cell_boxes(chunk, ncol, edges, oversample).reshape(len(chunk), per_slice, 6)
        for k, sid in enumerate(chunk):
            b = box[k]
            x0, x1 = _windows(b[:, 0], b[:, 1], b[:, 2], truncate, W)
            y0, y1 = _windows(b[:, 3], b[:, 4], b[:, 5], truncate, H)
            on = (x1 > x0) & (y1 > y0)
            if not on.any():
                raise ParameterError(f"slice {sid} falls entirely off the {H}x{W} detector for this grid")
            cx0, cx1 = _windows(b[:, 0], b[:, 1], b[:, 2], 0.0, W)
            cy0, cy1 = _windows(b[:, 3], b[:, 4], b[:, 5], 0.0, H)
            r0, r1, c0, c1 = y0[on].min(), y1[on].max(), x0[on].min(), x1[on].max()
            shape = (r1 - r0, c1 - c0)
            mask = _rasterise(y0[on] - r0, y1[on] - r0, x0[on] - c0, x1[on] - c0, shape)
            con = (cx1 > cx0) & (cy1 > cy0)
            core = _rasterise(cy0[con] - r0, cy1[con] - r0, cx0[con] - c0, cx1[con] - c0, shape)
            bins = np.flatnonzero(on.reshape(-1, ne, ncol * nq).any(axis=(1, 2)))
            out[int(sid)] = SliceFootprint(
                int(sid), field, (int(r0), int(c0)), mask, core, tuple(mask_outlines(mask, (r0, c0))),
                (float(edges[bins[0]]), float(edges[bins[-1] + 1])), centres,
                tx[i0 + k].copy(), ty[i0 + k].copy())
    return out


def field_footprints(mapper, field="narrow", lbda_edges=None, ncol=None, *, spectrograph=None, slices=None,
                     truncate=4.0, oversample=(1, 1)):
    """Footprints of a field's slices on the detector (:class:`FieldFootprints`).

    Parameters
    ----------
    mapper : SlicerMapper
        The detector mapping (:class:`~slicersim.instrument.mapper.SlicerMapper`).
    field : str, optional
        "narrow" (slices 1–58) or "wide" (59–116), or any name with ``slices``.
    lbda_edges : array_like of shape (nλ+1,), optional
        Bin edges of the cube grid [Å] (or give ``spectrograph``).
    ncol : int, optional
        Cube columns per slice (with ``lbda_edges``).
    spectrograph : Spectrograph, Simulation or Target, optional
        A spectrograph (its ``lbda_edges`` and ``shape[1]``), or a
        :class:`~slicersim.simulation.Simulation` or a Target, whose spectrograph is used,
        instead of ``lbda_edges`` and ``ncol``.
    slices : sequence of int, optional
        Slice ids (default: those of ``field``).
    truncate : float, optional
        Window half-width beyond each cell box [spot rms] (the projection's 4).
    oversample : tuple of int, optional
        (n_λ, n_φ) sub-cells per cell, as in :meth:`SlicerMapper.project_cube`.

    Returns
    -------
    FieldFootprints
        The footprints; the result is cached per mapper and grid.
    """
    if not (hasattr(mapper, "cell_boxes") and hasattr(mapper, "detector_shape")):
        raise ParameterError(f"expected a SlicerMapper, got {type(mapper).__name__}")
    if spectrograph is not None:
        if lbda_edges is not None or ncol is not None:
            raise ParameterError("give either a spectrograph or lbda_edges and ncol, not both")
        lbda_edges, ncol = _grid_of(spectrograph)
    if lbda_edges is None or ncol is None:
        raise ParameterError("footprints need the cube grid: lbda_edges [AA] and ncol, or a spectrograph")
    edges = np.asarray(lbda_edges, np.float64).ravel()
    if edges.size < 2 or not np.all(np.isfinite(edges)) or np.any(np.diff(edges) <= 0):
        raise ParameterError("lbda_edges must be >= 2 finite, strictly increasing wavelengths [AA]")
    if isinstance(ncol, bool) or not float(ncol).is_integer() or int(ncol) < 1:
        raise ParameterError(f"ncol must be a positive integer, got {ncol!r}")
    if not (np.isfinite(truncate) and 0 <= truncate <= validation.MAX_TRUNCATE):
        raise ParameterError(f"truncate must be in [0, {validation.MAX_TRUNCATE:g}] [spot rms], got "
                             f"{validation.short_repr(truncate)}")
    ov = tuple(int(v) for v in np.broadcast_to(oversample, (2,)))
    if min(ov) < 1:
        raise ParameterError(f"oversample must be >= 1 sub-cells per axis, got {oversample!r}")
    if slices is None:
        if field not in FIELD_SLICES:
            raise ParameterError(f"field must be 'narrow' or 'wide' (or give slices), got {field!r}")
        slices = FIELD_SLICES[field]
    slices = tuple(sorted(int(s) for s in np.ravel(slices)))
    if not slices or len(set(slices)) != len(slices):
        raise ParameterError("slices must be distinct slice ids")
    try:
        mapper.slice_index(slices)
    except ValueError as exc:
        raise ParameterError(str(exc)) from None
    key = (str(field), slices, int(ncol), hashlib.sha1(edges.tobytes()).hexdigest(), float(truncate), ov)
    store = _CACHE.setdefault(mapper, OrderedDict())
    if key in store:
        store.move_to_end(key)
        return store[key]
    fps = _slice_footprints(mapper, str(field), slices, edges, int(ncol), float(truncate), ov)
    result = FieldFootprints(str(field), fps, mapper.detector_shape, edges, int(ncol), float(truncate), ov)
    store[key] = result
    while len(store) > _CACHE_PER_MAPPER:
        store.popitem(last=False)
    return result


def _grid_of(spectrograph):
    """(lbda_edges, ncol) of a spectrograph, or of the spectrograph of a Simulation or Target."""
    spec = spectrograph
    for attr in ("simulation", "spectrograph"):        # Target -> Simulation -> spectrograph
        if not (hasattr(spec, "lbda_edges") and hasattr(spec, "shape")):
            spec = getattr(spec, attr, spec)
    try:
        return spec.lbda_edges, spec.shape[1]
    except (AttributeError, TypeError, IndexError):
        raise ParameterError("spectrograph must be a spectrograph (lbda_edges, shape) or a Simulation or "
                             f"Target, got {type(spectrograph).__name__}") from None


def detector_label_image(*fields):
    """Label image of several fields together (e.g. narrow and wide: both halves of the
    H4RG); a pixel claimed by two fields is an error (their slices would have to be
    distinguished by the field too).

    Parameters
    ----------
    *fields : FieldFootprints
        One or more fields of the same detector
        (:class:`~slicersim.errors.ParameterError` otherwise).

    Returns
    -------
    numpy.ndarray of shape (rows, cols)
        int32 image: slice id per pixel, ``NO_SLICE`` (−1) where no light falls."""
    if not fields:
        raise ParameterError("give at least one FieldFootprints")
    label = np.array(fields[0].label_image())
    for f in fields[1:]:
        if f.detector_shape != fields[0].detector_shape:
            raise ParameterError("fields of different detectors")
        other = f.label_image()
        both = (label != NO_SLICE) & (other != NO_SLICE)
        if both.any():
            raise ParameterError(f"fields {fields[0].field!r} and {f.field!r} share {int(both.sum())} pixels")
        label = np.where(other != NO_SLICE, other, label)
    return label


def save_footprints(directory, *fields, name="footprints", overwrite=False, also=None):
    """Write the footprints of one or more fields for a pipeline; returns the paths written.

    ``<name>_labels.fits``: the label image of all the fields (:func:`detector_label_image`,
    −1 where no light falls); ``<name>_outlines.json``: ``{"format", "version",
    "coordinates", "no_slice", "fields": [FieldFootprints.polygons(), ...]}``.  Both files
    (and ``also``, {path: bytes or a callable writing to a binary file}, e.g. a figure of
    them) are published together: all or none, never a pair of two writers
    (``slicersim.io.footprint_files.write_footprint_set``).  Existing files are refused
    unless ``overwrite`` (checked before anything is computed or written).

    Parameters
    ----------
    directory : str or path-like
        Directory the files are written to.
    *fields : FieldFootprints
        One or more fields of the same detector.
    name : str, optional
        Prefix of the file names.
    overwrite : bool, optional
        Replace existing files.
    also : dict, optional
        Further files published with them, {path: bytes or a callable writing to a binary
        file}.

    Returns
    -------
    list of str
        The paths written.
    """
    if not fields or not all(isinstance(f, FieldFootprints) for f in fields):
        raise ParameterError("save_footprints needs one or more FieldFootprints")
    paths = footprint_files.footprint_paths(directory, name)
    footprint_files.check_outputs((*paths, *(also or {})), overwrite)
    label = detector_label_image(*fields)
    first = fields[0]
    cards = [("FIELDS", ",".join(f.field for f in fields), "fields in this image"),
             ("NOSLICE", NO_SLICE, "label of pixels receiving no light"),
             ("TRUNCATE", first.truncate, "window half-width beyond a cell box [spot rms]"),
             ("NCOL", first.ncol, "cube columns per slice"),
             ("NBINS", int(first.lbda_edges.size - 1), "wavelength bins"),
             ("LBDAMIN", float(first.lbda_edges[0]), "[Angstrom] first bin edge"),
             ("LBDAMAX", float(first.lbda_edges[-1]), "[Angstrom] last bin edge"),
             ("NSHARED", int(sum(n for f in fields for *_, n in f.overlaps())),
              "pixels lit by two slices (nearest core wins)"),
             ("COMMENT", "slice id per pixel; image[row, col], FITS pixel (i, j) = image[j-1, i-1]")]
    description = {"format": FOOTPRINT_FORMAT[0], "version": FOOTPRINT_FORMAT[1], "no_slice": NO_SLICE,
                   "coordinates": "x = column, y = row [px]; pixel (row r, column c) covers "
                                  "[c, c+1) x [r, r+1); outlines run along pixel edges, the first "
                                  "is the outer contour",
                   "fields": [f.polygons() for f in fields]}
    return footprint_files.write_footprint_set(paths, label, cards, description, overwrite=overwrite, also=also)
