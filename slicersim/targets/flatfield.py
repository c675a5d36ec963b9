"""Flat-field structure of the instrument for calibration exposures:
:class:`FlatFieldStructure` (off by default, see :mod:`slicersim.targets.calibration`).

* slice-to-slice throughput: each slice s transmits t_s = exp(σ_s z_s − σ_s²/2) of the lamp
  light, z_s ~ N(0, 1);
* pixel response non-uniformity (PRNU): each detector pixel p multiplies its photo-electrons
  by r_p = exp(σ_p z_p − σ_p²/2) (mean 1); a cube cell gets the mean of its pixels' responses,
  drawn per voxel.

Draws are counter-based Philox keyed by (``seed``, slice id or voxel / pixel index, stream
:data:`FLAT_SLICE_STREAM` / :data:`FLAT_PIXEL_STREAM` + k): reproducible on any backend and
chunking, and independent of the noise seed.  Every name is re-exported by
:mod:`slicersim.targets.calibration`, its import path.
"""
from __future__ import annotations

import numpy as np

from slicersim import validation
from slicersim.errors import ParameterError
from slicersim.instrument.slices import NARROW_SLICES, WIDE_SLICES

__all__ = ["FLAT_SLICE_STREAM", "FLAT_PIXEL_STREAM", "MAX_SCATTER", "FlatFieldStructure"]

#: Philox stream of the slice throughputs (index: slice id)
FLAT_SLICE_STREAM = 0x464C5331
#: Philox streams of the pixel responses: + 0 detector pixels (index y·2¹⁶ + x), + 1 narrow cube,
#: + 2 wide cube, + 3 single-field cube (index: flat voxel index)
FLAT_PIXEL_STREAM = 0x464C5058
_FIELD_STREAM = {"narrow": 1, "wide": 2, None: 3}
#: rows of the detector drawn per block for the pixel response
_PIXEL_BLOCK_ROWS = 256
#: largest slice or pixel scatter accepted (lognormal σ)
MAX_SCATTER = 0.5


class FlatFieldStructure:
    """Multiplicative flat-field structure of the instrument (ideal by default).

    Parameters
    ----------
    slice_scatter : float, optional
        σ of the slice throughputs (lognormal, mean 1), in [0, 0.5].
    pixel_scatter : float, optional
        σ of the per-pixel responses (PRNU, lognormal, mean 1), in [0, 0.5].
    seed : int, optional
        Integer in [0, 2⁶⁴) keying the draws.
    """

    def __init__(self, slice_scatter=0.0, pixel_scatter=0.0, seed=0):
        self.slice_scatter = validation.number("slice_scatter", slice_scatter, low=0.0, high=MAX_SCATTER)
        self.pixel_scatter = validation.number("pixel_scatter", pixel_scatter, low=0.0, high=MAX_SCATTER)
        if seed is None or isinstance(seed, np.random.Generator):
            raise ParameterError("seed: the flat-field structure needs an integer seed in [0, 2**64)")
        self.seed = validation.seed(seed)

    @property
    def is_ideal(self):
        return self.slice_scatter == 0.0 and self.pixel_scatter == 0.0

    def __repr__(self):
        return (f"FlatFieldStructure(slice_scatter={self.slice_scatter}, pixel_scatter={self.pixel_scatter}, "
                f"seed={self.seed})")

    @staticmethod
    def _lognormal(z, sigma):
        return np.exp(sigma * z - 0.5 * sigma * sigma)

    def slice_throughput(self, slice_ids):
        """Throughput t_s (mean 1) of each slice id.

        Parameters
        ----------
        slice_ids : array_like of int
            Slice ids.

        Returns
        -------
        numpy.ndarray
            The throughputs, of the shape of ``slice_ids``.
        """
        from slicersim import rng
        ids = np.asarray(slice_ids, dtype=np.uint64)
        if self.slice_scatter == 0.0:
            return np.ones(ids.shape)
        return self._lognormal(rng.normal(self.seed, ids, FLAT_SLICE_STREAM)[..., 0], self.slice_scatter)

    def row_throughput(self, field, nrows):
        """Slice throughput of each cube row (row r ↔ slice ``slices[nrows − 1 − r]``; Lazuli
        narrow: slices 1–58, wide 59–116; single-field instruments: 1 … nrows).

        Parameters
        ----------
        field : str or None
            The field.
        nrows : int
            Cube rows.

        Returns
        -------
        numpy.ndarray of shape (nrows,)
            The throughputs (mean 1).
        """
        slices = {"narrow": NARROW_SLICES, "wide": WIDE_SLICES}.get(field, tuple(range(1, nrows + 1)))
        if len(slices) != nrows:
            slices = tuple(range(1, nrows + 1))
        return self.slice_throughput(slices[::-1])

    def cell_response(self, shape, field, pixels_per_cell=2, backend="auto"):
        """Response of each cube cell: the mean of its ``pixels_per_cell`` pixel responses (voxel v,
        pixel k: the Box–Muller branch k mod 2 of Philox draw k div 2).

        Parameters
        ----------
        shape : tuple of int
            (nλ, ny, nx) of the cube.
        field : str
            The field ("narrow", "wide" or None).
        pixels_per_cell : int, optional
            Detector pixels per cell.
        backend : str, optional
            "auto", "opencl" or "numpy".

        Returns
        -------
        numpy.ndarray of shape (nλ, ny, nx)
            The cell responses (mean 1).
        """
        from slicersim.backends.noise import uniform_normal_grid
        shape = tuple(int(v) for v in shape)
        if self.pixel_scatter == 0.0:
            return np.ones(shape)
        nl, npix, ppc = shape[0], int(np.prod(shape[1:])), max(1, int(pixels_per_cell))
        total = np.zeros((nl, npix))
        for draw in range((ppc + 1) // 2):
            z = uniform_normal_grid(nl, npix, self.seed, FLAT_PIXEL_STREAM + _FIELD_STREAM.get(field, 3),
                                    draw, backend)[1]
            for branch in range(min(2, ppc - 2 * draw)):
                total += self._lognormal(z[..., branch], self.pixel_scatter)
            del z
        return (total / ppc).reshape(shape)

    def pixel_response(self, shape, backend="auto"):
        """Response r_p of each detector pixel (index y·2¹⁶ + x).

        Parameters
        ----------
        shape : tuple of int
            (ny, nx) of the detector.
        backend : str, optional
            "auto", "opencl" or "numpy".

        Returns
        -------
        numpy.ndarray of shape (ny, nx)
            The pixel responses (mean 1).
        """
        from slicersim.backends.noise import uniform_normal_grid
        ny, nx = (int(v) for v in shape)
        out = np.ones((ny, nx))
        if self.pixel_scatter == 0.0:
            return out
        for y0 in range(0, ny, _PIXEL_BLOCK_ROWS):
            rows = min(_PIXEL_BLOCK_ROWS, ny - y0)
            z = uniform_normal_grid(rows, nx, self.seed, FLAT_PIXEL_STREAM, 0, backend, first_index=y0 << 16,
                                    row_stride=1 << 16)[1]
            out[y0:y0 + rows] = self._lognormal(z[..., 0], self.pixel_scatter)
        return out


def _check_structure(structure):
    if structure is None:
        return FlatFieldStructure()
    if isinstance(structure, FlatFieldStructure):
        return structure
    if isinstance(structure, dict):
        unknown = sorted(set(structure) - {"slice_scatter", "pixel_scatter", "seed"})
        if unknown:
            raise ParameterError(f"unknown flat-field structure key(s) {unknown}: slice_scatter, pixel_scatter, seed")
        return FlatFieldStructure(**structure)
    raise ParameterError(f"structure must be None, a dict or a FlatFieldStructure, got {structure!r}")
