"""The option and result objects of :func:`slicersim.products.ramps.simulate` (frozen, checked dataclasses):
what it writes (:class:`RampIO`), how it runs (:class:`RunOptions`), the detector maps it takes
(:class:`DetectorMaps`) and what it returns (:class:`RampResult`)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from slicersim import validation
from slicersim.io.uncal_meta import GROUPDQ_FLAGS

__all__ = ["RampIO", "RunOptions", "DetectorMaps", "RampResult", "DEFAULT_MAX_BYTES", "FILE_FORMATS"]

FILE_FORMATS = ("hdf5", "jwst-uncal")

#: default memory budget of :func:`simulate` [bytes] (a full-detector ramp peaks below 1.5 GB)
DEFAULT_MAX_BYTES = 2**29


@validation.checked_fields
@dataclass(frozen=True, kw_only=True)
class RampIO:
    """What :func:`simulate` writes, and how (the ``io`` options).

    Parameters
    ----------
    format : {"hdf5", "jwst-uncal"}, optional
        ``"hdf5"`` (group-level file, ``slicersim.io.rampfile``) or ``"jwst-uncal"`` (JWST
        level-1b FITS, ``slicersim.io.uncal``); None: ``jwst-uncal`` for a ``.fits`` name, else
        hdf5.
    overwrite : bool, optional
        Replace an existing output (default: refuse with RampFileError).
    compression : str or dict, optional
        HDF5 compression (``slicersim.io.rampfile.compression_options``), None: none.
    truth : bool, optional
        Write ``truth/rate`` (and the effects' truth) to the file.
    config : dict, optional
        Configuration recorded in the CONFIG attribute.
    return_dq : bool, optional
        With ``out=None``, also return GROUPDQ in memory.
    target : object, optional
        A ``slicersim.io.target_truth.TargetTruth``, written as ``truth/target`` (the target's redshift,
        phase, input spectrum and expected rate; ``LazuliTarget.get_ramps`` makes it).
    groupdq : {None, "none", "observed", "truth"}, optional
        What a level-1b file's GROUPDQ holds (``slicersim.io.uncal_meta.GROUPDQ_FLAGS``): None or
        "none" (no GROUPDQ, as flight level-1b), "observed" (SATURATED from the observed DN) or "truth"
        (the simulator's flags, from the true charge); an HDF5 file keeps the simulator's flags (None
        or "truth" only).
    window : tuple of int, optional
        (x0, y0, nx, ny) [pixels, 0-based]: simulate and write only this rectangle of the detector
        (``rate`` is the full detector's), read on the full detector's clock: bit-identical to the same
        pixels of a full-detector ramp of the same seed (``slicersim.products.windows``).
    rows : sequence of (int, int), optional
        Row ranges [y0, y1) [0-based, half-open]: simulate and write only these full-width rows of the
        detector (HDF5 files only).  The other rows are never simulated and absent from the file, whose
        ``SIMULATED_ROWS`` attribute lists the ranges; :func:`~slicersim.reduction.ramp_fit.fit_ramps`
        gives them NaN rates flagged DO_NOT_USE, and readers of whole ramps refuse the file.  The rows
        written are bit-identical to those of a full-detector ramp of the same seed.  Streaming campaigns
        use it for the rows their reduction reads
        (``detector_rows()`` of :class:`~slicersim.instrument.footprints.FieldFootprints`).

    """

    format: str | None = None
    overwrite: bool = False
    compression: object = None
    truth: bool = True
    config: dict | None = None
    return_dq: bool = False
    target: object = None
    groupdq: str | None = None
    window: object = None
    rows: object = None

    def __post_init__(self):
        if self.format is not None:
            validation.choice("file_format", self.format, FILE_FORMATS)
        if self.groupdq is not None:
            validation.choice("groupdq", self.groupdq, GROUPDQ_FLAGS)
        for name in ("overwrite", "truth", "return_dq"):              # 0/1 accepted as before, not "yes"
            value = getattr(self, name)
            value = bool(value) if isinstance(value, (int, np.integer)) else value
            object.__setattr__(self, name, validation.flag(name, value))


@validation.checked_fields
@dataclass(frozen=True, kw_only=True)
class RunOptions:
    """How :func:`simulate` computes.

    Parameters
    ----------
    max_bytes : int, optional
        Host memory for the row blocks [bytes] (and, with correlated noise, a third of it for
        its cached segments).
    progress : bool or None, optional
        Progress bar (None: a bar only when stderr is a terminal).
    work_group : int, optional
        OpenCL local size (None: 64 on CPUs, the runtime's on GPUs; never changes the result)."""

    max_bytes: int = DEFAULT_MAX_BYTES
    progress: bool | None = None
    work_group: int | None = None

    def __post_init__(self):
        object.__setattr__(self, "max_bytes", validation.positive_int("max_bytes", self.max_bytes))
        if self.progress is not None:
            value = bool(self.progress) if isinstance(self.progress, (int, np.integer)) else self.progress
            object.__setattr__(self, "progress", validation.flag("progress", value))
        if self.work_group is not None:
            object.__setattr__(self, "work_group", validation.positive_int("work_group", self.work_group))


@validation.checked_fields
@dataclass(frozen=True, kw_only=True)
class DetectorMaps:
    """Per-pixel inputs of :func:`simulate`, each of shape (ny, nx) or None.

    Parameters
    ----------
    dead_pixels : numpy.ndarray of shape (ny, nx), optional
        bool: pixels collecting no charge.
    pixeldq : numpy.ndarray of shape (ny, nx), optional
        uint32 JWST flags.
    previous_charge : numpy.ndarray of shape (ny, nx), optional
        Charge of the previous exposure [e-] (for the ``persistence`` effect)."""

    dead_pixels: object = None
    pixeldq: object = None
    previous_charge: object = None


@dataclass(frozen=True)
class RampResult:
    """What :func:`simulate` made.

    Parameters
    ----------
    seed : int
        The seed used: record it to repeat the run.
    path : str, optional
        Path of the file (None in memory).
    sci : numpy.ndarray of shape (nramps, ngroups, ny, nx), optional
        uint16 ramps [ADU] in memory (None with a file).
    groupdq : numpy.ndarray of shape (nramps, ngroups, ny, nx), optional
        uint8 GROUPDQ in memory (None with a file; only with ``io.return_dq``).
    attrs : dict, optional
        The file's root attributes."""

    seed: int
    path: str | None = None
    sci: np.ndarray | None = None
    groupdq: np.ndarray | None = None
    attrs: dict = field(default_factory=dict)
