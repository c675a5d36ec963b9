"""Windows (subarrays) of the detector: a rectangle of the full detector simulated and written alone.

A window is read on the full detector's clock: same outputs, pixel time, row and frame overheads,
so its correlated noise is the full detector's at its pixels' read times.  :func:`simulate` with
``window=`` computes the expected charge and the detector effects on the full detector (rate,
bias and nonlinearity maps, cosmic rays, IPC neighbours, 1/f streams keyed by the full
detector's outputs and pixel times), samples only the rows the window covers (every draw is
Philox keyed by the full detector's pixel index, and the correlated noise of a row block is the
same whatever the blocking) and keeps only its columns: the window's SCI is bit-identical to the
same pixels cut from a full-detector ramp of the same seed.  Cost: the window's rows at full width.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slicersim import validation
from slicersim.errors import ParameterError

__all__ = ["Window", "check_window"]


@dataclass(frozen=True)
class Window:
    """Rectangle [y0, y0 + ny) × [x0, x0 + nx) of a detector of ``detector_shape`` (0-based pixels).

    JWST keywords: SUBSTRT1 = x0 + 1, SUBSTRT2 = y0 + 1, SUBSIZE1 = nx, SUBSIZE2 = ny."""

    x0: int
    y0: int
    nx: int
    ny: int
    detector_shape: tuple

    @property
    def shape(self):
        """(ny, nx) of the window."""
        return (self.ny, self.nx)

    @property
    def rows(self):
        return slice(self.y0, self.y0 + self.ny)

    @property
    def cols(self):
        return slice(self.x0, self.x0 + self.nx)

    @property
    def substrt(self):
        """1-based (SUBSTRT2, SUBSTRT1) = (y, x) of the first pixel."""
        return (self.y0 + 1, self.x0 + 1)

    def attrs(self):
        """Root attributes recording the window (HDF5 files; read back by the level-1b converter)."""
        return {"SUBSTRT1": self.x0 + 1, "SUBSTRT2": self.y0 + 1, "SUBSIZE1": self.nx, "SUBSIZE2": self.ny,
                "DETECTOR_NY": int(self.detector_shape[0]), "DETECTOR_NX": int(self.detector_shape[1])}

    def cut(self, image):
        """The window's pixels of a full-detector image (..., ny_det, nx_det)."""
        return image[..., self.rows, self.cols]


def check_window(window, detector_shape):
    """A :class:`Window` from ``(x0, y0, nx, ny)`` on a detector of ``detector_shape`` (ny, nx), or None.

    Parameters
    ----------
    window : None, a :class:`Window` or 4 integers (x0, y0, nx, ny) [pixels, 0-based first pixel]
    detector_shape : (ny, nx) of the full detector (the rate image)

    Returns
    -------
    Window or None; ParameterError naming ``window`` when it is not inside the detector.
    """
    if window is None:
        return None
    if isinstance(window, Window):
        window = (window.x0, window.y0, window.nx, window.ny)
    try:
        values = [int(v) for v in window]
        if len(values) != 4 or any(v != w for v, w in zip(values, window)):
            raise ValueError
    except (TypeError, ValueError):
        raise ParameterError(f"{validation.shown('window')} must be 4 integers X0 Y0 NX NY, got "
                             f"{validation.short_repr(window)}") from None
    x0, y0, nx, ny = values
    NY, NX = (int(v) for v in detector_shape)
    if x0 < 0 or y0 < 0 or nx < 1 or ny < 1 or x0 + nx > NX or y0 + ny > NY:
        raise ParameterError(f"{validation.shown('window')} X0 Y0 NX NY = {x0} {y0} {nx} {ny} is not inside the "
                             f"{NX}×{NY} detector (0 ≤ X0, X0 + NX ≤ {NX}, 0 ≤ Y0, Y0 + NY ≤ {NY}, NX, NY ≥ 1)")
    return Window(x0, y0, nx, ny, (NY, NX))


class WindowSink:
    """A writer (or memory sink) of the window fed full-width row blocks of the detector: keeps the
    window's columns, shifts rows to the window's."""

    def __init__(self, sink, window):
        self.sink, self.window = sink, window
        self.groupdq_flags = getattr(sink, "groupdq_flags", None)

    def write_block(self, ramp, y0, sci, gdq=None, **kw):
        w = self.window
        if "saturation" in kw and np.ndim(kw["saturation"]) == 2:
            kw["saturation"] = kw["saturation"][:, w.cols]
        self.sink.write_block(ramp, y0 - w.y0, np.ascontiguousarray(sci[:, :, w.cols]),
                              None if gdq is None else np.ascontiguousarray(gdq[:, :, w.cols]), **kw)
