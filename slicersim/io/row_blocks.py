"""The row-block engine shared by every pass over a detector that does not fit in memory at once:
raw-ramp simulation (:func:`slicersim.products.ramps.simulate`), ramp fitting
(:func:`slicersim.reduction.ramp_fit.fit_ramps`) and the level-1b FITS conversion
(:func:`slicersim.io.uncal.write_uncal_from_hdf5`).

One place for the three things they share:

1. :func:`rows_per_block` — memory budget [bytes] → rows per block;
2. :class:`RowBlocks` — the (outer index, y0, y1) steps of a pass, with the progress bar
   (``progress``: None = a tqdm bar only when stderr is a terminal and the pass has more than a
   few blocks, True, False);
3. double buffering — :class:`BufferRing` (host buffers reused round-robin, so the next block is
   read while a device works on the last one), :func:`pipelined` (a launch returns a "finish"
   callable, finished one block later) and :class:`BackgroundLanes` (named single-thread lanes
   for work that overlaps the computation: file writes, truth).

No physics here: callers say how many bytes a row costs.
"""
from __future__ import annotations

import sys
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from slicersim import validation
from slicersim.errors import ParameterError, ResourceError

__all__ = ["rows_per_block", "RowBlocks", "BufferRing", "pipelined", "BackgroundLanes", "show_progress",
           "row_ranges", "SIMULATED_ROWS"]

#: root attribute of a ramp file that holds only some detector rows: JSON list of [y0, y1) pairs (the other
#: rows were never simulated nor written; :func:`row_ranges` reads it)
SIMULATED_ROWS = "SIMULATED_ROWS"


def rows_per_block(max_bytes, bytes_per_row, nrows, *, reserve=0, what="one detector row", chunk=1,
                   name="max_bytes"):
    """Rows per block: as many as ``max_bytes − reserve`` bytes hold at ``bytes_per_row`` each
    (at least 1, at most ``nrows``), rounded down to a multiple of ``chunk`` when above it (the
    rows of a file's chunk).  ResourceError (a MemoryError) when not even one row fits (``name``: the
    caller's keyword)."""
    budget = int(max_bytes) - int(reserve)
    if budget < bytes_per_row:
        raise ResourceError(f"{name} {int(max_bytes)} B is below {what} ({int(bytes_per_row)} B"
                            f"{f' plus {int(reserve)} B reserved' if reserve else ''})")
    rows = int(max(1, min(nrows, budget // bytes_per_row)))
    if chunk > 1 and rows > chunk:
        rows -= rows % chunk
    return rows


def row_ranges(ranges, nrows, name="rows"):
    """Sorted, disjoint, non-empty (y0, y1) row ranges (half-open, 0-based) of a detector of ``nrows``
    rows from any sequence of pairs (overlapping or touching ranges merged).

    Parameters
    ----------
    ranges : sequence of (int, int)
        Row ranges [y0, y1).
    nrows : int
        Rows of the detector.
    name : str, optional
        The caller's name of ``ranges``, for the error.

    Returns
    -------
    tuple of (int, int)
        The ranges, merged and sorted; ParameterError naming ``name`` when a pair is not two integers
        with 0 ≤ y0 < y1 ≤ nrows, or when there is none.
    """
    pairs = []
    try:
        for pair in ranges:
            a, b = pair
            if isinstance(a, bool) or isinstance(b, bool) or int(a) != a or int(b) != b:
                raise ValueError
            pairs.append((int(a), int(b)))
    except (TypeError, ValueError, OverflowError):           # OverflowError: int(inf)
        raise ParameterError(f"{name} must be a sequence of (y0, y1) integer row ranges, got "
                             f"{validation.short_repr(ranges)}") from None
    if not pairs:
        raise ParameterError(f"{name} must hold at least one (y0, y1) row range, got none")
    bad = [p for p in pairs if not 0 <= p[0] < p[1] <= nrows]
    if bad:
        raise ParameterError(f"{name}: row range {bad[0]} is not inside the detector's {nrows} rows "
                             f"(0 ≤ y0 < y1 ≤ {nrows})")
    merged = []
    for a, b in sorted(pairs):
        if merged and a <= merged[-1][1]:
            merged[-1] = (merged[-1][0], max(merged[-1][1], b))
        else:
            merged.append((a, b))
    return tuple(merged)


def show_progress(progress, nblocks=None, auto_min=4):
    """Whether to show a progress bar, the package's one meaning of ``progress``: True/False as
    given; None (every default) only when stderr is a terminal (and, when ``nblocks`` is given, there
    are more than ``auto_min`` steps).  Anything else: ParameterError naming progress."""
    if progress is None:
        isatty = getattr(sys.stderr, "isatty", None)
        return bool(isatty and isatty()) and (nblocks is None or nblocks > auto_min)
    return validation.flag("progress", progress)


class RowBlocks:
    """The steps of a pass: for each outer index (a ramp; 1 when there is none) the row blocks
    [y0, y1) of ``rows`` rows over rows [``first``, ``nrows``), or over each range of ``ranges``
    (sorted, disjoint (y0, y1) pairs: only those rows are visited, a block never spans two ranges).
    Iterating yields (outer, y0, y1), lazily (the outer count may be huge), through a tqdm bar when
    :func:`show_progress` says so."""

    def __init__(self, nrows, rows, *, nouter=1, progress=None, desc="blocks", auto_min=4, first=0, ranges=None):
        self.nrows, self.rows, self.nouter, self.first = int(nrows), int(rows), int(nouter), int(first)
        self.ranges = ((self.first, self.nrows),) if ranges is None else tuple((int(a), int(b)) for a, b in ranges)
        self.per_outer = sum(-(-(b - a) // self.rows) for a, b in self.ranges)
        self.progress = show_progress(progress, len(self), auto_min)
        self.desc = desc

    def __len__(self):
        return self.nouter * self.per_outer

    def _steps(self):
        for outer in range(self.nouter):
            for a, b in self.ranges:
                for y0 in range(a, b, self.rows):
                    yield outer, y0, min(b, y0 + self.rows)

    def __iter__(self):
        if not self.progress:
            return self._steps()
        from tqdm.auto import tqdm
        return iter(tqdm(self._steps(), desc=self.desc, unit="block", total=len(self)))


class BufferRing:
    """``nsets`` sets of flat host buffers (one per dtype of ``dtypes``, ``size`` elements each), handed
    out round-robin: with two sets a block is filled while the previous one is still in use."""

    def __init__(self, size, dtypes, nsets=1):
        self.sets = [tuple(np.empty(int(size), dt) for dt in dtypes) for _ in range(int(nsets))]
        self.count = 0

    def next(self, shape=None):
        """The next set, each buffer cut to ``shape`` (its first prod(shape) elements) when given."""
        buffers = self.sets[self.count % len(self.sets)]
        self.count += 1
        if shape is None:
            return buffers
        size = int(np.prod(shape))
        return tuple(b[:size].reshape(shape) for b in buffers)


def pipelined(steps, launch, store):
    """Run ``launch(step)`` for each step; a launch returns a callable that waits for its result,
    which is passed to ``store(step, result)`` after the NEXT step has been launched (one block in
    flight while the host prepares the next).  ``launch`` returning a non-callable result is
    stored at once (no device)."""
    pending = None
    for step in steps:
        launched = launch(step)
        if not callable(launched):
            store(step, launched)
            continue
        if pending is not None:
            store(pending[0], pending[1]())
        pending = (step, launched)
    if pending is not None:
        store(pending[0], pending[1]())


class BackgroundLanes:
    """Named single-thread lanes (e.g. "truth", "write"): each lane runs its jobs in order, at most one
    queued behind the running one (a block waits for the previous block's job, bounding memory to
    two blocks); the first error is raised by :meth:`submit` or :meth:`finish`, which waits for every
    lane.  NumPy, FFTs, OpenCL waits and file writes release the GIL meanwhile."""

    def __init__(self, names=("truth", "write")):
        self._pools = {name: ThreadPoolExecutor(1, thread_name_prefix=f"slicersim-{name}") for name in names}
        self._pending = {name: None for name in self._pools}

    def submit(self, lane, func, *args):
        self.raise_failed()
        previous = self._pending[lane]
        if previous is not None:
            previous.result()
        self._pending[lane] = self._pools[lane].submit(func, *args)

    def raise_failed(self):
        """Raise the error of any lane's job that has already failed (a lane's one long job is otherwise
        looked at only in :meth:`finish`; a SIGINT held back inside HDF5 is raised there)."""
        for future in self._pending.values():
            if future is not None and future.done() and future.exception() is not None:
                raise future.exception()

    def finish(self, raise_error=True):
        """Wait for every lane and shut it down; raise the first error (unless ``raise_error`` is False)."""
        error = None
        for lane, pool in self._pools.items():
            future, self._pending[lane] = self._pending[lane], None
            try:
                if future is not None:
                    future.result()
            except BaseException as exc:             # noqa: BLE001 - first error re-raised below
                error = error or exc
            finally:
                pool.shutdown(wait=True)
        if error is not None and raise_error:
            raise error
