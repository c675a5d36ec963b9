"""JWST calibration reference files (the CRDS formats that ``stdatamodels`` validates); no physics here.

Eight files, named as CRDS names them (``slicersim_<detector>_<type>.fits``), each written by its
``stdatamodels.jwst.datamodels`` model, validated strictly before it is saved::

    gain        GainModel        SCI (ny, nx) float32         e-/DN
    readnoise   ReadnoiseModel   SCI (ny, nx) float32         DN, of a CDS (two single-frame reads)
    saturation  SaturationModel  SCI (ny, nx) float32, DQ     DN, raw
    superbias   SuperBiasModel   SCI, ERR (ny, nx), DQ        DN
    linearity   LinearityModel   COEFFS (k, ny, nx), DQ       corrected DN = Σ c_k DN^k (superbias removed)
    dark        DarkModel        SCI, ERR (nframes, ny, nx)   DN, NFRAMES = 1, GROUPGAP = 0 (linear DN)
    mask        MaskModel        DQ (ny, nx) uint32           JWST pixel flags
    ipc         IPCModel         SCI (3, 3) float32           K[1+dy, 1+dx]: share of a pixel's signal at (dy, dx)

Keywords: INSTRUME and DETECTOR are "N/A" — the reference models' schema accepts only JWST names (or
"N/A"), so the level-1b files' own names (:data:`slicersim.io.uncal.DEFAULT_KEYWORDS`: LAZULI_IFS, H4RG-1)
are given in DESCRIP; TELESCOP is "JWST", the only value the reference-file models accept
(``ReferenceFileModel.validate``), ORIGIN "slicersim"; PEDIGREE "SIMULATION"; SUBARRAY FULL with
the array's size; REFTYPE the type in capitals; USEAFTER 2026-01-01T00:00:00.  Every file is
written under a temporary name and renamed when complete; an existing file is refused unless
``overwrite``.  ``stdatamodels`` is imported only here (``pip install stdatamodels``).
"""
from __future__ import annotations

import datetime as _dt
import os
import shutil
import tempfile

import numpy as np

from slicersim.errors import RampFileError
from slicersim.io.atomic import one_line, publish, remove_stale_temporaries
from slicersim.io.uncal import DEFAULT_KEYWORDS

__all__ = ["REFERENCE_TYPES", "USEAFTER", "reference_file_names", "write_reference_files", "read_reference_files",
           "ramp_file_keywords", "available"]

#: reference-file types, in the order of the JWST detector pipeline (CRDS REFTYPE in lower case)
REFERENCE_TYPES = ("mask", "saturation", "ipc", "superbias", "linearity", "dark", "gain", "readnoise")
USEAFTER = "2026-01-01T00:00:00"
_MODELS = {"gain": "GainModel", "readnoise": "ReadnoiseModel", "saturation": "SaturationModel",
           "superbias": "SuperBiasModel", "linearity": "LinearityModel", "dark": "DarkModel", "mask": "MaskModel",
           "ipc": "IPCModel"}
_UNITS = {"gain": "electron/DN", "readnoise": "DN", "saturation": "DN", "superbias": "DN", "dark": "DN"}
_DESCRIPTIONS = {
    "gain": "gain [e-/DN]",
    "readnoise": "read noise of a CDS of single-frame reads [DN]",
    "saturation": "saturation level of raw reads [DN], below the full-well value",
    "superbias": "bias of an empty pixel [DN]",
    "linearity": "linearity correction, corrected DN = sum_k c_k DN^k (bias removed)",
    "dark": "dark ramp per frame [DN] (linear DN)",
    "mask": "bad-pixel mask (JWST pixel flags)",
    "ipc": "IPC kernel K[1+dy,1+dx]: share of a pixel's signal at offset (dy,dx)",
}
#: JWST pixel flags (stdatamodels.jwst.datamodels.dqflags.pixel) named in the DQ_DEF tables
_DQ_FLAGS = {"DO_NOT_USE": 1, "SATURATED": 2, "NO_LIN_CORR": 1 << 20, "NO_SAT_CHECK": 1 << 21, "DEAD": 1024,
             "HOT": 2048, "WARM": 4096, "LOW_QE": 8192, "TELEGRAPH": 32768, "REFERENCE_PIXEL": 1 << 31}


def reference_file_names(detector="lazuli"):
    """{type: file name} of the reference files of ``detector`` (``slicersim_<detector>_<type>.fits``)."""
    label = str(detector).strip().lower()
    if not label or not all(c.isalnum() or c in "-." for c in label):
        raise RampFileError(f"detector label {detector!r}: letters, digits, '-' and '.' only")
    return {kind: f"slicersim_{label}_{kind}.fits" for kind in REFERENCE_TYPES}


def available():
    """True when stdatamodels (which writes the files) is installed."""
    import importlib.util
    return importlib.util.find_spec("stdatamodels") is not None


def _stdatamodels():
    try:
        from stdatamodels.jwst import datamodels
    except ImportError as exc:
        raise RampFileError(f"writing JWST reference files needs stdatamodels ({one_line(exc)}): pip install "
                            "stdatamodels") from None
    return datamodels


def _dq_def(flags):
    """DQ_DEF rows (BIT, VALUE, NAME, DESCRIPTION) of the named flags."""
    rows = [(int(np.log2(_DQ_FLAGS[n])), _DQ_FLAGS[n], n, n.replace("_", " ").lower()) for n in flags]
    return np.array(rows, dtype=[("BIT", "<i4"), ("VALUE", "<u4"), ("NAME", "S40"), ("DESCRIPTION", "S80")])


def _build(kind, arrays, datamodels, meta):
    """The validated model of ``kind`` from ``arrays`` (see :func:`write_reference_files`)."""
    model = getattr(datamodels, _MODELS[kind])(strict_validation=True)
    shape = tuple(arrays["mask"].shape)
    if kind == "gain":
        model.data = np.asarray(arrays["gain"], np.float32)
    elif kind == "readnoise":
        model.data = np.asarray(arrays["readnoise"], np.float32)
    elif kind == "saturation":
        model.data = np.asarray(arrays["saturation"], np.float32)
        model.dq = np.asarray(arrays.get("saturation_dq", np.zeros(shape, np.uint32)), np.uint32)
        model.dq_def = _dq_def(("NO_SAT_CHECK",))
    elif kind == "superbias":
        model.data = np.asarray(arrays["superbias"], np.float32)
        if "superbias_err" in arrays:                       # exact here: no ERR unless given
            model.err = np.asarray(arrays["superbias_err"], np.float32)
        model.dq = np.zeros(shape, np.uint32)
        model.dq_def = _dq_def(("DO_NOT_USE",))
    elif kind == "linearity":
        model.coeffs = np.asarray(arrays["linearity"], np.float32)
        model.dq = np.asarray(arrays.get("linearity_dq", np.zeros(shape, np.uint32)), np.uint32)
        model.dq_def = _dq_def(("NO_LIN_CORR",))
    elif kind == "dark":
        dark = np.asarray(arrays["dark"], np.float32)
        model.data = dark
        model.dq = np.zeros(shape, np.uint32)
        model.dq_def = _dq_def(("DO_NOT_USE",))
        model.meta.exposure.nframes, model.meta.exposure.groupgap = 1, 0
        model.meta.exposure.ngroups = int(dark.shape[0])
        model.meta.exposure.readpatt = "N/A"
        if "dark_current" in arrays:
            model.average_dark_current = np.asarray(arrays["dark_current"], np.float32)
    elif kind == "mask":
        model.dq = np.asarray(arrays["mask"], np.uint32)
        model.dq_def = _dq_def(("DO_NOT_USE", "DEAD", "HOT", "WARM", "LOW_QE", "TELEGRAPH", "REFERENCE_PIXEL"))
    else:
        model.data = np.asarray(arrays["ipc"], np.float32)
    m = model.meta
    m.reftype, m.pedigree, m.useafter = kind.upper(), "SIMULATION", USEAFTER
    m.author, m.origin, m.telescope = meta["author"], "slicersim", "JWST"      # the models insist on JWST
    # the reference models' schema knows only JWST instruments (or "N/A"): the level-1b files' own names
    # (INSTRUME, DETECTOR of DEFAULT_KEYWORDS) go into the description
    m.description = (f"slicersim {_DESCRIPTIONS[kind]} of {DEFAULT_KEYWORDS['INSTRUME']} "
                     f"{DEFAULT_KEYWORDS['DETECTOR']}; {meta['description']}")[:250]
    m.instrument.name, m.instrument.detector = "N/A", "N/A"
    m.date = meta["date"]
    if kind != "ipc":
        m.subarray.name, m.subarray.xstart, m.subarray.ystart = "FULL", 1, 1
        m.subarray.xsize, m.subarray.ysize = int(shape[1]), int(shape[0])
    if kind in _UNITS:
        m.bunit_data = _UNITS[kind]
    model.validate()
    return model


def _check_arrays(arrays):
    """RampFileError unless every array is there with the shape of ``mask`` (ny, nx)."""
    missing = [k for k in ("gain", "readnoise", "saturation", "superbias", "linearity", "dark", "mask", "ipc")
               if k not in arrays]
    if missing:
        raise RampFileError(f"reference arrays missing: {', '.join(missing)}")
    shape = np.shape(arrays["mask"])
    if len(shape) != 2:
        raise RampFileError(f"mask must be a 2-D image, got shape {shape}")
    for key in ("gain", "readnoise", "saturation", "superbias"):
        if np.shape(arrays[key]) != shape:
            raise RampFileError(f"{key} must be {shape}, got {np.shape(arrays[key])}")
    for key in ("linearity", "dark"):
        if np.ndim(arrays[key]) != 3 or np.shape(arrays[key])[1:] != shape:
            raise RampFileError(f"{key} must be (k, {shape[0]}, {shape[1]}), got {np.shape(arrays[key])}")
    if np.shape(arrays["ipc"]) != (3, 3):
        raise RampFileError(f"ipc must be a 3×3 kernel, got {np.shape(arrays['ipc'])}")


def write_reference_files(directory, arrays, detector="lazuli", description="", overwrite=False):
    """Write the eight reference files into ``directory`` (made if missing; its parent must exist).

    Parameters
    ----------
    directory : path
    arrays : dict
        ``gain`` [e-/DN], ``readnoise`` [DN], ``saturation`` [DN], ``superbias`` [DN] (ny, nx);
        ``linearity`` (k, ny, nx) [DN^(1-k)]; ``dark`` (nframes, ny, nx) [DN]; ``mask`` uint32 (ny, nx);
        ``ipc`` (3, 3); optional ``saturation_dq``, ``linearity_dq`` (uint32 flags), ``superbias_err``
        [DN], ``dark_current`` [DN/s] (ny, nx).
    detector : str
        Label in the file names.
    description : str
        Appended to each file's DESCRIP (e.g. the seed and the effects).
    overwrite : bool
        Replace existing files (default: refuse them all before writing any).

    Returns
    -------
    dict
        {type: absolute path}.
    """
    names = reference_file_names(detector)
    directory = os.path.abspath(os.fspath(directory))
    if os.path.lexists(directory) and not os.path.isdir(directory):
        raise RampFileError(f"output path is not a directory: {directory}")
    parent = os.path.dirname(directory)
    if not os.path.isdir(directory) and not os.path.isdir(parent):
        raise RampFileError(f"output directory's parent does not exist: {parent}")
    paths = {kind: os.path.join(directory, name) for kind, name in names.items()}
    if not overwrite:
        existing = [p for p in paths.values() if os.path.lexists(p)]
        if existing:
            raise RampFileError(f"output file exists: {existing[0]} (pass overwrite=True / --overwrite to replace "
                                "the reference files)")
    _check_arrays(arrays)
    datamodels = _stdatamodels()
    os.makedirs(directory, exist_ok=True)
    if not os.access(directory, os.W_OK):
        raise RampFileError(f"output directory is not writable: {directory}")
    remove_stale_temporaries(directory)
    meta = {"author": "slicersim", "description": str(description),
            "date": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%f")[:23]}
    scratch = tempfile.mkdtemp(prefix=".slicersim-reffiles-", dir=directory)   # FILENAME = the final name
    try:
        for kind in REFERENCE_TYPES:
            model = _build(kind, arrays, datamodels, meta)
            tmp = os.path.join(scratch, names[kind])
            try:
                model.save(tmp, overwrite=True)
                publish(tmp, paths[kind], overwrite=overwrite, error_class=RampFileError)
            except RampFileError:
                raise
            except OSError as exc:
                raise RampFileError(f"cannot write {paths[kind]}: {one_line(exc)}") from exc
            finally:
                model.close()
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return paths


def read_reference_files(directory, detector="lazuli"):
    """{type: array} of the reference files in ``directory``, read (and validated) by stdatamodels:
    the SCI data of each (COEFFS of linearity, DQ of mask), plus ``saturation_dq``, ``linearity_dq``
    and ``dark_nframes`` / ``dark_groupgap``."""
    datamodels = _stdatamodels()
    out = {}
    for kind, name in reference_file_names(detector).items():
        path = os.path.join(os.fspath(directory), name)
        if not os.path.isfile(path):
            raise RampFileError(f"{path}: no such file")
        with getattr(datamodels, _MODELS[kind])(path, strict_validation=True) as model:
            model.validate()
            if kind == "linearity":
                out[kind], out["linearity_dq"] = np.array(model.coeffs), np.array(model.dq)
            elif kind == "mask":
                out[kind] = np.array(model.dq)
            else:
                out[kind] = np.array(model.data)
            if kind == "saturation":
                out["saturation_dq"] = np.array(model.dq)
            if kind == "dark":
                out["dark_nframes"], out["dark_groupgap"] = model.meta.exposure.nframes, model.meta.exposure.groupgap
    return out


def ramp_file_keywords(path):
    """(root attributes, (ny, nx)) of a slicersim ramp file, HDF5 or level-1b FITS (its
    ``SLICERSIM <NAME>`` keywords), without reading the ramps; JSON texts (EFFECTS) stay text."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise RampFileError(f"{path}: no such file")
    with open(path, "rb") as fh:
        magic = fh.read(8)
    try:
        if magic.startswith(b"SIMPLE"):
            from astropy.io import fits
            with fits.open(path, memmap=False) as hdul:
                head = hdul[0].header
                attrs = {k[len("SLICERSIM "):]: v for k, v in head.items() if k.startswith("SLICERSIM ")}
                shape = tuple(int(s) for s in hdul["SCI"].shape[-2:])
            return attrs, shape
        import h5py
        with h5py.File(path, "r") as fh:
            attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in fh.attrs.items()}
            shape = tuple(int(s) for s in fh["SCI"].shape[-2:])
        return attrs, shape
    except (OSError, KeyError) as exc:
        raise RampFileError(f"{path}: not a slicersim ramp file ({one_line(exc)})") from None
