"""The target's truth beside its products: ``truth/target`` of ramp and reduced files; no physics.

One compound (table) dataset, small and 1-D, on the simulation's native wavelength bins:

==============  =======================  ===================================================
column          unit                     content
==============  =======================  ===================================================
lbda            Angstrom                 bin centre (observer frame)
dlbda           Angstrom                 bin width
flambda         erg/s/cm2/Angstrom       the point source's input F_λ (NaN outside its model)
rate            electron/s               expected point-source rate per bin, as the simulation
                                         computes it (F_λ → photons → × QE, after the LSF)
etc_variance    (electron/s)2            the ETC's variance of the extracted rate per bin for
                                         the readout used (all ramps)
==============  =======================  ===================================================

and its attributes: ``target_id``, ``redshift``, ``phase`` with ``phase_frame = "rest"`` (rest-frame
days from B-band peak), ``peak_absmag``, ``band``, ``magsys``, ``source``, ``x1``, ``c``, ``field``,
``position_x``, ``position_y`` [native cells from the field centre], ``cell_scale`` [arcsec per native
cell], the readout (``nmd``, ``nramps``) and ``unit_<column>`` for each column.  Attributes a target
does not have (x1 of a Hsiao SN) are left out.  HDF5 files hold it as the compound dataset
``truth/target`` (chunked, Fletcher-32, flushed as every truth dataset); level-1b FITS files as the
binary table TRUTH_TARGET, its attributes as ``HIERARCH SLICERSIM <NAME>`` keywords of it.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field

import numpy as np

from slicersim.errors import RampFileError

__all__ = ["TargetTruth", "COLUMNS", "UNITS", "TRUTH_NAME", "read_target_truth", "write_target_truth"]

#: dataset name under the file's ``truth/`` group
TRUTH_NAME = "target"
#: columns of the table, in order, and their units
COLUMNS = ("lbda", "dlbda", "flambda", "rate", "etc_variance")
UNITS = {"lbda": "Angstrom", "dlbda": "Angstrom", "flambda": "erg/s/cm2/Angstrom", "rate": "electron/s",
         "etc_variance": "(electron/s)2"}
#: units of the scalar attributes
ATTR_UNITS = {"phase": "day (rest frame, from B-band peak)", "position_x": "native cell", "position_y": "native cell",
              "cell_scale": "arcsec", "peak_absmag": "mag"}


@dataclass
class TargetTruth:
    """A target's truth: ``attrs`` (scalars: redshift, phase, ...; see the module docstring) and the
    1-D arrays ``lbda`` [Å], ``dlbda`` [Å], ``flambda`` [erg/s/cm²/Å], ``rate`` [e-/s per bin],
    ``etc_variance`` [(e-/s)² per bin], all of one length."""

    attrs: dict
    lbda: np.ndarray
    dlbda: np.ndarray
    flambda: np.ndarray
    rate: np.ndarray
    etc_variance: np.ndarray = field(default=None)

    def __post_init__(self):
        n = np.size(self.lbda)
        if self.etc_variance is None:
            self.etc_variance = np.full(n, np.nan)
        for name in COLUMNS:
            arr = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1)
            if arr.size != n:
                raise RampFileError(f"target truth: {name} has {arr.size} values, lbda {n}")
            setattr(self, name, arr)
        self.attrs = {k: _scalar(v) for k, v in dict(self.attrs).items() if v is not None and _finite_or_text(v)}

    def table(self):
        """The structured array (n,) of :data:`COLUMNS` (float64)."""
        out = np.zeros(self.lbda.size, dtype=[(c, "<f8") for c in COLUMNS])
        for c in COLUMNS:
            out[c] = getattr(self, c)
        return out

    def file_attrs(self):
        """The attributes written with the table: ``attrs`` and a ``unit_<name>`` per column and unit-bearing
        attribute."""
        units = {f"unit_{c}": UNITS[c] for c in COLUMNS}
        units.update({f"unit_{k}": u for k, u in ATTR_UNITS.items() if k in self.attrs})
        return {**self.attrs, **units}

    def edges(self):
        """Bin edges [Å] (n + 1,) from the centres and widths."""
        return np.append(self.lbda - 0.5 * self.dlbda, self.lbda[-1] + 0.5 * self.dlbda[-1])


def _scalar(value):
    if isinstance(value, (np.generic,)):
        value = value.item()
    if isinstance(value, (list, tuple, np.ndarray)):
        return json.dumps(np.asarray(value).tolist())
    return value


def _finite_or_text(value):
    if isinstance(value, (str, bytes, bool, np.bool_)):
        return True
    try:
        return bool(np.all(np.isfinite(np.asarray(value, dtype=float))))
    except (TypeError, ValueError):
        return True


def write_target_truth(writer, truth):
    """Write ``truth`` (a :class:`TargetTruth`) as ``truth/target`` with a writer that has
    ``write_dataset(name, array, attrs)`` (:class:`~slicersim.io.rampfile.RampWriter`,
    :class:`~slicersim.io.uncal.UncalWriter`) or ``write(name, data, attrs)`` (an
    :class:`~slicersim.io.atomic.AtomicH5File`: reduced files)."""
    if hasattr(writer, "write_dataset"):
        writer.write_dataset(TRUTH_NAME, truth.table(), truth.file_attrs())
    else:
        writer.write(f"truth/{TRUTH_NAME}", truth.table(), attrs=truth.file_attrs(), chunks=True, fletcher32=True)


def _decoded(value):
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    if isinstance(value, np.generic):
        value = value.item()
    return value


def _from_text(value):
    """A FITS keyword value written as text: back to int/float where it reads as one."""
    if not isinstance(value, str):
        return value
    for kind in (int, float):
        try:
            return kind(value)
        except ValueError:
            pass
    return value


def _truth_of(table, attrs):
    names = set(table.dtype.names or ())
    if not {"lbda", "dlbda", "flambda", "rate"} <= names:
        raise RampFileError(f"truth/{TRUTH_NAME} lacks columns {sorted({'lbda', 'dlbda', 'flambda', 'rate'} - names)}")
    plain = {k: v for k, v in attrs.items() if not k.startswith("unit_")}
    return TargetTruth(plain, *(table[c] for c in ("lbda", "dlbda", "flambda", "rate")),
                       etc_variance=table["etc_variance"] if "etc_variance" in names else None)


def read_target_truth(path):
    """The :class:`TargetTruth` of a ramp or reduced file (HDF5 ``truth/target``, or a level-1b FITS
    file's TRUTH_TARGET table), None when the file has none; RampFileError when it cannot be read."""
    path = os.fspath(path)
    if path.lower().endswith((".fits", ".fit")):
        return _read_fits(path)
    import h5py
    try:
        with h5py.File(path, "r") as fh:
            dset = fh.get(f"truth/{TRUTH_NAME}")
            if dset is None:
                return None
            return _truth_of(dset[()], {k: _decoded(v) for k, v in dset.attrs.items()})
    except OSError as exc:
        raise RampFileError(f"cannot read truth/{TRUTH_NAME} of {path} ({' '.join(str(exc).split())})") from None


def _read_fits(path):
    from astropy.io import fits
    try:
        with fits.open(path, memmap=False) as hdul:
            if "TRUTH_TARGET" not in hdul:
                return None
            hdu = hdul["TRUTH_TARGET"]
            attrs = {}
            for card in hdu.header.cards:
                key = card.keyword
                if key.upper().startswith("SLICERSIM "):
                    attrs[key[len("SLICERSIM "):].lower()] = _from_text(card.value)
            data = hdu.data
            table = np.zeros(len(data), dtype=[(c, "<f8") for c in data.names])
            for c in data.names:
                table[c] = data[c]
    except OSError as exc:
        raise RampFileError(f"cannot read TRUTH_TARGET of {path} ({' '.join(str(exc).split())})") from None
    return _truth_of(table, attrs)
