"""JWST level-1b ("uncal") FITS files of raw ramps, written in row blocks; no physics here.

Layout (readable by ``stdatamodels.jwst.datamodels.Level1bModel``, which validates it)::

    PRIMARY    header only: JWST exposure, subarray and time keywords; every slicersim root
               attribute as ``HIERARCH SLICERSIM <NAME>`` (the truth about the simulation)
    SCI        uint16 (nints, ngroups, ny, nx)  BITPIX 16, BZERO 32768    [DN = ADU]
    GROUPDQ    uint8  (nints, ngroups, ny, nx)  BITPIX 8                  JWST group flags, only with
               ``groupdq_flags`` "observed" or "truth" (flight level-1b files carry none)
    PIXELDQ    uint32 (ny, nx)                  BITPIX 32, BZERO 2**31    JWST pixel flags
    GROUP      binary table, nints·ngroups rows (group end times, sizes)  as in JWST uncal files
    INT_TIMES  binary table, nints rows (integration start/mid/end, MJD UTC)
    TRUTH_*    truth arrays: TRUTH_RATE (float32 image), TRUTH_CR (cosmic-ray table), any
               other ``write_dataset`` array as TRUTH_<NAME> (images; structured arrays as
               binary tables), each with H5PATH (its HDF5 name) and H5DTYPE (NumPy dtype)

``Level1bModel`` defines SCI, GROUP and INT_TIMES; GROUPDQ, PIXELDQ and TRUTH_* are kept by
it as ``extra_fits`` (and GROUPDQ/PIXELDQ are read by ``RampModel``).  SCI, GROUPDQ and
PIXELDQ are preallocated (sizes are known) and written in place, one group of a row block
at a time, so a 2 GB SCI is never held in memory; truth extensions are appended.

Every HDU carries CHECKSUM and DATASUM (FITS standard 4.0, as JWST files do), summed as the
blocks are written (:mod:`slicersim.io.fits_checksum`): ``fits.open(path, checksum=True)`` verifies them.

Instrument keywords (:mod:`slicersim.io.uncal_meta`, their one table): INSTRUME = LAZULI_IFS,
DETECTOR = H4RG-1, EXP_TYPE = LZ_IFU, READPATT = MACC_<m>_<d>, GAINEDN [e-/DN] and RDNCDSDN
[CDS DN] as pipelines use them; the simulation's own GAIN [ADU/e-] and READNOISE [e-/frame]
stay ``HIERARCH SLICERSIM`` cards.  JWST's schema enumerates the first four with JWST names
only: the file opens in ``Level1bModel``/``RampModel`` and a strict validation names just
those four; ``keywords=uncal_meta.JWST_STAND_IN`` (or any ``keywords=``) overrides them.
NOUTPUTS is omitted (the schema allows 1, 4, 5; an H4RG has 32 outputs).

Timing keywords follow the JWST keyword dictionary (archive.stsci.edu/jwst/keyword, build 11):
TGROUP = (NFRAMES + GROUPGAP)·TFRAME; EFFINTTM = (NGROUPS − 1)·TGROUP, the time between the
first and last group (the dictionary writes "(NGROUPS−1)·TGROUP + TGROUP0" without defining
TGROUP0, taken as 0 here after JWST Webb Office Hours, 22 Feb 2024: "the effective integration
time is the time interval between the first and last group"); TMEASURE = TGROUP·(NGROUPS − 1)·NINTS; EFFEXPTM = XPOSURE =
TFRAME·(NGROUPS·NFRAMES + (NGROUPS − 1)·GROUPGAP + DRPFRMS1)·NINTS (photon collection time);
DURATION = TELAPSE = EFFEXPTM + TFRAME·(DRPFRMS3·NINTS + NRSTSTRT + NRESETS·(NINTS − 1)).
Defaults: one reset frame before each integration (NRSTSTRT = NRESETS = 1), no dropped
frames before or between integrations (DRPFRMS1 = DRPFRMS3 = 0): slicersim ramps start at a
reset and their frames are n(m + d) − d, no trailing drops.  Root attributes of these names
override the defaults.  Times are UTC calendar arithmetic from EXPSTART (``start_mjd``,
attribute EXPSTART, else the time the file is written); barycentric and heliocentric
times are NaN (no target or observatory position is known here).
"""
from __future__ import annotations

import contextlib
import datetime as _dt
import json
import math
import os
import shutil
from dataclasses import dataclass

import numpy as np

from slicersim import validation
from slicersim.errors import RampFileError
from slicersim.io.atomic import _HDF5_MARGIN, one_line, publish, remove_stale_temporaries, temporary_path
from slicersim.io.fits_blocks import (BLOCK, IMAGE_TYPES, ascii_text, card_value, from_mjd, header_bytes,
                                      image_header, mjd, padded, table_bytes, to_storage)
from slicersim.io.fits_checksum import StreamedChecksums
from slicersim.io.rampfile import open_hdf5_input, read_dataset, soft_links
from slicersim.io.row_blocks import RowBlocks, rows_per_block
from slicersim.io.uncal_meta import (DETECTOR, EXP_TYPE, GROUPDQ_FLAGS, INSTRUMENT, TELESCOPE, group_sigma_dn,  # noqa: F401
                                    instrument_keywords, observed_saturation, saturation_reference)
from slicersim.io.uncal_read import read_uncal, read_uncal_truth  # noqa: F401  (public here as before)

__all__ = ["UncalWriter", "UncalOptions", "write_uncal_from_hdf5", "read_uncal", "read_uncal_truth", "truth_extname",
           "DEFAULT_KEYWORDS", "GROUPDQ_FLAGS", "observed_saturation"]

_DAY0 = _dt.datetime(2000, 1, 1)                 # GROUP end_day counts days from here
#: primary keywords written unless ``keywords=`` or a root attribute says otherwise
DEFAULT_KEYWORDS = {"TELESCOP": TELESCOPE, "INSTRUME": INSTRUMENT, "DETECTOR": DETECTOR, "EXP_TYPE": EXP_TYPE,
                    "ORIGIN": "slicersim", "TIMESYS": "UTC", "TIMEUNIT": "s",
                    "DATAMODL": "Level1bModel", "ZEROFRAM": False, "DATAPROB": False,
                    "FASTAXIS": 1, "SLOWAXIS": 2}
_TIMING_DEFAULTS = {"NRSTSTRT": 1, "NRESETS": 1, "DRPFRMS1": 0, "DRPFRMS3": 0}
_ALIASES = {"rate": "TRUTH_RATE", "cosmic_rays": "TRUTH_CR"}
_GROUP_DTYPE = [("integration_number", ">i4"), ("group_number", ">i2"), ("end_day", ">i2"),
                ("end_milliseconds", ">i4"), ("end_submilliseconds", ">i2"), ("group_end_time", "S26"),
                ("number_of_columns", ">i2"), ("number_of_rows", ">i2"), ("number_of_gaps", ">i2"),
                ("completion_code_number", ">i2"), ("completion_code_text", "S36"),
                ("bary_end_time", ">f8"), ("helio_end_time", ">f8")]
_INT_TIMES_DTYPE = [("integration_number", ">i4")] + [
    (f"int_{w}_{s}", ">f8") for s in ("MJD_UTC", "BJD_TDB") for w in ("start", "mid", "end")]


def truth_extname(name):
    """FITS EXTNAME of a truth dataset: ``truth/rate`` → TRUTH_RATE, ``cosmic_rays`` → TRUTH_CR,
    ``truth/nonlinearity/coefficients`` → TRUTH_NONLINEARITY_COEFFICIENTS."""
    key = str(name).strip("/")
    key = key[len("truth/"):] if key.startswith("truth/") else key
    if not key:
        raise RampFileError(f"dataset name {name!r} is empty")
    return _ALIASES.get(key, "TRUTH_" + key.upper().replace("/", "_"))


@validation.checked_fields
@dataclass(frozen=True, kw_only=True)
class UncalOptions:
    """Keywords of :class:`UncalWriter` beyond those it shares with the HDF5 RampWriter: ``keywords``
    (primary keywords overriding :data:`DEFAULT_KEYWORDS`), ``groupdq_flags`` (:data:`GROUPDQ_FLAGS`:
    what GROUPDQ holds), ``start_mjd`` [MJD UTC], ``detector_shape``
    (ny, nx), ``substrt`` 1-based (y, x) of the first pixel, ``extra_bytes`` for the disk-space check."""

    keywords: dict | None = None
    groupdq_flags: str = "none"
    start_mjd: float | None = None
    detector_shape: tuple | None = None
    substrt: tuple = (1, 1)
    extra_bytes: int = 0

    def __post_init__(self):
        validation.choice("groupdq_flags", self.groupdq_flags, GROUPDQ_FLAGS)


class UncalWriter:
    """Stream a raw ramp to a JWST level-1b FITS file in row blocks (context manager).

    Parameters (as :class:`slicersim.io.rampfile.RampWriter`)
    ----------
    path : output file;  nramps (= NINTS), ngroups : int;  shape : (ny, nx)
    attrs : root attributes (NINTS NGROUPS NFRAMES GROUPGAP TFRAME TGROUP READPATT GAIN ...);
        NFRAMES, GROUPGAP and TFRAME are required by the time the ``with`` block starts
    row_block : rows per block in :func:`write_uncal_from_hdf5` (the writer takes any block)
    compression : None only (a level-1b file is uncompressed)
    truth_rate : bool, count a TRUTH_RATE image in the disk-space check
    extra_bytes : further bytes (truth of detector effects) for the disk-space check
    pixeldq : bool, preallocate PIXELDQ
    groupdq : bool, accept the simulator's GROUPDQ blocks (False: they are refused); whether a
        GROUPDQ extension is written, and what it holds, is ``groupdq_flags``
    groupdq_flags : "none" (default: no GROUPDQ, as flight level-1b files), "observed" (SATURATED
        from the observed DN, :func:`observed_saturation`) or "truth" (the simulator's flags)
    overwrite : replace an existing ``path`` (default: refuse with :class:`RampFileError`)
    keywords : primary keywords overriding the defaults (:data:`DEFAULT_KEYWORDS`)
    start_mjd : exposure start [MJD UTC] (default: attribute EXPSTART, else now)
    detector_shape : (ny, nx) of the whole detector (default ``shape``): SUBARRAY FULL or GENERIC;
        substrt : 1-based (SUBSTRT2, SUBSTRT1) = (y, x) of the first pixel

    The file is written as ``.NAME.tmp-PID-xxxx`` and linked to ``NAME`` only when complete
    (two writers: one wins, the other gets a clear error); any error or exception in the
    ``with`` block removes the temporary; temporaries of killed writers are removed by the
    next writer in the directory.
    """

    error_class = RampFileError
    durable = True

    def __init__(self, path, nramps, ngroups, shape, attrs=None, row_block=64, compression=None,
                 truth_rate=False, pixeldq=True, groupdq=True, overwrite=False, **options):
        opts = UncalOptions(**options)
        keywords, start_mjd, detector_shape, substrt = opts.keywords, opts.start_mjd, opts.detector_shape, opts.substrt
        self.path = os.path.abspath(os.fspath(path))
        self.extra_bytes = int(opts.extra_bytes)
        self.overwrite = bool(overwrite)
        self.nramps, self.ngroups = int(nramps), int(ngroups)
        self.shape = tuple(int(s) for s in shape)
        if self.nramps < 1 or self.ngroups < 1 or len(self.shape) != 2 or min(self.shape) < 1:
            raise RampFileError(f"{self.path}: need nramps ≥ 1, ngroups ≥ 1 and a 2-D shape, got "
                                f"{nramps}, {ngroups}, {tuple(shape)}")
        if compression not in (None, "none", False):
            raise RampFileError(f"compression {compression!r}: a JWST level-1b file is uncompressed "
                                "(use the HDF5 format to compress)")
        self.attrs = dict(attrs or {})
        self.row_block = int(max(1, min(row_block, self.shape[0])))
        self.truth_rate, self.pixeldq = bool(truth_rate), bool(pixeldq)
        self.groupdq_flags = opts.groupdq_flags
        self.accepts_groupdq = bool(groupdq)
        self.groupdq = self.groupdq_flags == "observed" or (self.groupdq_flags == "truth" and bool(groupdq))
        self.keywords = dict(keywords or {})
        self.start_mjd = start_mjd
        self.detector_shape = self.shape if detector_shape is None else tuple(int(s) for s in detector_shape)
        self.substrt = tuple(int(s) for s in substrt)
        self._fd = self._tmp = None
        self._offsets = {}
        self._end = 0
        self._extnames = set()
        self._sums, self._hdu_of = StreamedChecksums(), {}     # CHECKSUM / DATASUM of every HDU

    # ------------------------------------------------------------------ sizes and checks
    def _pixels(self):
        return self.nramps * self.ngroups * self.shape[0] * self.shape[1]

    def expected_bytes(self):
        """File size [bytes]: data, TRUTH_RATE when ``truth_rate``, and ``extra_bytes`` (other truth)."""
        plane = self.shape[0] * self.shape[1]
        rows = self.nramps * self.ngroups
        size = 8 * BLOCK + padded(2 * self._pixels()) + self.groupdq * padded(self._pixels())
        size += self.pixeldq * padded(4 * plane) + self.truth_rate * padded(4 * plane)
        return size + padded(rows * 112) + padded(self.nramps * 56) + self.extra_bytes

    def timing(self):
        """JWST timing keywords from the root attributes (see the module docstring) [s, frames]."""
        attrs = {**_TIMING_DEFAULTS, **self.attrs}
        missing = [k for k in ("NFRAMES", "GROUPGAP", "TFRAME") if k not in attrs]
        if missing:
            raise RampFileError(f"{self.path}: a JWST level-1b file needs the readout timing: root "
                                f"attribute(s) {', '.join(missing)} missing")
        try:
            m, d = int(attrs["NFRAMES"]), int(attrs["GROUPGAP"])
            tframe = float(attrs["TFRAME"])
            resets = {k: int(attrs[k]) for k in _TIMING_DEFAULTS}
        except (TypeError, ValueError) as exc:
            raise RampFileError(f"{self.path}: timing attributes must be numbers ({exc})") from exc
        if m < 1 or d < 0 or not (math.isfinite(tframe) and tframe > 0) or min(resets.values()) < 0:
            raise RampFileError(f"{self.path}: need NFRAMES ≥ 1, GROUPGAP ≥ 0, TFRAME > 0 s and "
                                f"reset/drop counts ≥ 0, got {m}, {d}, {tframe}, {resets}")
        for key, val in (("NINTS", self.nramps), ("NGROUPS", self.ngroups)):
            if key in attrs and int(attrs[key]) != val:
                raise RampFileError(f"{self.path}: attribute {key} = {attrs[key]} but the data have {val}")
        n, nint = self.ngroups, self.nramps
        tgroup = (m + d) * tframe
        frames = n * m + (n - 1) * d                          # frames of one integration
        effexptm = tframe * (frames + resets["DRPFRMS1"]) * nint
        duration = effexptm + tframe * (resets["DRPFRMS3"] * nint + resets["NRSTSTRT"]
                                        + resets["NRESETS"] * (nint - 1))
        return {"NFRAMES": m, "GROUPGAP": d, "TFRAME": tframe, "TGROUP": tgroup, "FRMDIVSR": m,
                "EFFINTTM": (n - 1) * tgroup, "EFFEXPTM": effexptm, "DURATION": duration,
                "TMEASURE": (n - 1) * tgroup * nint, "XPOSURE": effexptm, "TELAPSE": duration,
                "FRAMES_PER_INT": frames, **resets}

    def check(self):
        """Refuse early (before any allocation): missing or read-only directory, a directory at
        ``path``, an existing file without ``overwrite``, not enough free disk space, attributes
        without the readout timing (when attributes are given)."""
        directory = os.path.dirname(self.path) or "."
        if not os.path.isdir(directory):
            raise RampFileError(f"output directory does not exist: {directory}")
        if not os.access(directory, os.W_OK):
            raise RampFileError(f"output directory is not writable: {directory}")
        if os.path.isdir(self.path):
            raise RampFileError(f"output path is a directory: {self.path}")
        if not self.overwrite and os.path.lexists(self.path):
            raise RampFileError(f"output file exists: {self.path} (pass overwrite=True / --overwrite "
                                "to replace it)")
        remove_stale_temporaries(directory)          # a killed writer's temporary holds disk space
        need = self.expected_bytes() + _HDF5_MARGIN
        free = shutil.disk_usage(directory).free
        if need > free:
            raise RampFileError(f"not enough disk space in {directory}: need {need / 1e9:.3g} GB "
                                f"for {self.path}, {free / 1e9:.3g} GB free")
        if self.attrs:
            self.timing()
        return self

    # ------------------------------------------------------------------ lifecycle
    def __enter__(self):
        self.check()
        timing = self.timing()
        directory = os.path.dirname(self.path)
        remove_stale_temporaries(directory)
        for _ in range(100):
            tmp = temporary_path(self.path)
            try:
                self._fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o666)
            except FileExistsError:
                continue
            except OSError as exc:
                raise RampFileError(f"cannot create {self.path}: {one_line(exc)}") from exc
            self._tmp = tmp
            break
        else:  # pragma: no cover
            raise RampFileError(f"cannot create a temporary file in {directory}")
        try:
            self._layout(timing)
        except BaseException:
            self._abort()
            raise
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is not None:
            self._abort()
            return False
        try:
            self._sums.finish(self._pwrite)
            if self.durable:
                os.fsync(self._fd)
            os.close(self._fd)
            self._fd = None
            tmp, self._tmp = self._tmp, None
            try:
                publish(tmp, self.path, self.overwrite, RampFileError)
            except BaseException:
                self._tmp = tmp
                raise
        except BaseException as err:
            self._abort()
            if isinstance(err, OSError) and not isinstance(err, RampFileError):
                raise RampFileError(f"cannot finish {self.path}: {one_line(err)}") from err
            raise
        return False

    def _abort(self):
        fd, tmp, self._fd, self._tmp = self._fd, self._tmp, None, None
        if fd is not None:
            with contextlib.suppress(OSError):
                os.close(fd)
        if tmp is not None:
            with contextlib.suppress(FileNotFoundError):
                os.remove(tmp)

    def _pwrite(self, data, offset):
        view, done = memoryview(data).cast("B"), 0
        try:
            while done < len(view):
                done += os.pwrite(self._fd, view[done:], offset + done)
        except OSError as exc:
            raise RampFileError(f"writing {self.path} failed: {one_line(exc)}") from exc

    def _append(self, data):
        self._pwrite(data, self._end)
        self._end += memoryview(data).nbytes

    def _reserve(self, name, header, nbytes):
        """Write an extension header at the end and reserve its (zero) data area."""
        self._hdu_of[name] = self._sums.add_hdu(self._end, header)
        self._append(header)
        self._offsets[name] = self._end
        self._end += padded(nbytes)
        self._extnames.add(name)
        try:
            os.ftruncate(self._fd, self._end)
        except OSError as exc:
            raise RampFileError(f"writing {self.path} failed: {one_line(exc)}") from exc

    # ------------------------------------------------------------------ headers
    def _start_mjd(self):
        start = self.start_mjd if self.start_mjd is not None else self.attrs.get("EXPSTART")
        return mjd(_dt.datetime.now(_dt.timezone.utc).replace(tzinfo=None)) if start is None else float(start)

    def _primary_cards(self, timing, t0):
        ny, nx = self.shape
        y0, x0 = self.substrt
        full = self.shape == self.detector_shape and self.substrt == (1, 1)
        t_end = t0 + timing["DURATION"] / 86400.0
        begin, end = from_mjd(t0), from_mjd(t_end)
        cards = {"SIMPLE": True, "BITPIX": 8, "NAXIS": 0, "EXTEND": True,
                 "DATE": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%f")[:23],
                 "FILENAME": ascii_text(os.path.basename(self.path)), **DEFAULT_KEYWORDS,
                 "DATE-OBS": begin.strftime("%Y-%m-%d"), "TIME-OBS": begin.strftime("%H:%M:%S.%f")[:12],
                 "DATE-BEG": begin.isoformat(timespec="milliseconds"),
                 "DATE-END": end.isoformat(timespec="milliseconds"),
                 "EXPSTART": t0, "EXPMID": 0.5 * (t0 + t_end), "EXPEND": t_end,
                 "NINTS": self.nramps, "NGROUPS": self.ngroups, "INTSTART": 1, "INTEND": self.nramps}
        for key in ("NFRAMES", "GROUPGAP", "FRMDIVSR", "TFRAME", "TGROUP", "EFFINTTM", "EFFEXPTM",
                    "DURATION", "TMEASURE", "NRSTSTRT", "NRESETS", "DRPFRMS1", "DRPFRMS3"):
            cards[key] = timing[key]
        if "TSAMPLE" in self.attrs:
            cards["TSAMPLE"] = float(self.attrs["TSAMPLE"])
        for key in ("FASTAXIS", "SLOWAXIS"):
            if key in self.attrs:
                cards[key] = int(self.attrs[key])
        cards.update({"SUBARRAY": "FULL" if full else "GENERIC", "SUBSTRT1": x0, "SUBSTRT2": y0,
                      "SUBSIZE1": nx, "SUBSIZE2": ny})
        comments = {}
        for key, val, comment in instrument_keywords(self.attrs):
            cards[key], comments[key] = val, comment
        for key, val in self.keywords.items():
            cards[str(key).upper()] = card_value(val)
            comments.pop(str(key).upper(), None)
        out = [(k, v, comments[k]) if k in comments else (k, v) for k, v in cards.items()]
        out += [(f"HIERARCH SLICERSIM {ascii_text(k).upper()}", card_value(v)) for k, v in self.attrs.items()]
        return out

    def _layout(self, timing):
        t0 = self._start_mjd()
        ny, nx = self.shape
        dims = (self.nramps, self.ngroups, ny, nx)
        primary = header_bytes(self._primary_cards(timing, t0))
        self._sums.add_hdu(self._end, primary)
        self._append(primary)
        bunit = str(self.attrs.get("BUNIT", "DN"))
        sci_cards = [("BUNIT", "DN" if bunit.upper() in ("ADU", "DN") else ascii_text(bunit)),
                     ("MJD-BEG", t0), ("MJD-AVG", t0 + timing["DURATION"] / 172800.0),
                     ("MJD-END", t0 + timing["DURATION"] / 86400.0),
                     ("XPOSURE", timing["XPOSURE"]), ("TELAPSE", timing["TELAPSE"])]
        self._reserve("SCI", image_header("SCI", np.uint16, dims, sci_cards), 2 * self._pixels())
        if self.groupdq:
            self._reserve("GROUPDQ", image_header("GROUPDQ", np.uint8, dims), self._pixels())
        if self.pixeldq:
            self._reserve("PIXELDQ", image_header("PIXELDQ", np.uint32, self.shape), 4 * ny * nx)
        group, int_times = self._time_tables(timing, t0)
        self._append(table_bytes(group, "GROUP"))
        self._append(table_bytes(int_times, "INT_TIMES"))
        self._extnames.update({"GROUP", "INT_TIMES"})

    def _time_tables(self, timing, t0):
        """GROUP (one row per group: end time of its last frame) and INT_TIMES (start of the first
        frame, end of the last group, midpoint) of each integration."""
        n, m, d, tf = self.ngroups, timing["NFRAMES"], timing["GROUPGAP"], timing["TFRAME"]
        frames = timing["FRAMES_PER_INT"]
        period = timing["DRPFRMS1"] + frames + timing["DRPFRMS3"] + timing["NRESETS"]
        first = timing["NRSTSTRT"] + timing["DRPFRMS1"] + period * np.arange(self.nramps)   # [frames]
        group_end = first[:, None] + np.arange(n)[None, :] * (m + d) + m                    # [frames]
        group = np.zeros(self.nramps * n, dtype=_GROUP_DTYPE)
        group["integration_number"] = np.repeat(np.arange(1, self.nramps + 1), n)
        group["group_number"] = np.tile(np.arange(1, n + 1), self.nramps)
        ends = [from_mjd(t0) + _dt.timedelta(seconds=float(f * tf)) for f in group_end.ravel()]
        since = [e - _DAY0 for e in ends]
        group["end_day"] = [s.days for s in since]
        group["end_milliseconds"] = [s.seconds * 1000 + s.microseconds // 1000 for s in since]
        group["end_submilliseconds"] = [s.microseconds % 1000 for s in since]
        group["group_end_time"] = [e.strftime("%Y-%m-%dT%H:%M:%S.%f").encode() for e in ends]
        group["number_of_columns"], group["number_of_rows"] = self.shape[1], self.shape[0]
        group["completion_code_text"] = b"COMPLETE"
        group["bary_end_time"] = group["helio_end_time"] = np.nan
        int_times = np.zeros(self.nramps, dtype=_INT_TIMES_DTYPE)
        int_times["integration_number"] = np.arange(1, self.nramps + 1)
        start = t0 + first * tf / 86400.0
        end = t0 + (first + frames) * tf / 86400.0
        int_times["int_start_MJD_UTC"], int_times["int_end_MJD_UTC"] = start, end
        int_times["int_mid_MJD_UTC"] = 0.5 * (start + end)
        for key in ("int_start_BJD_TDB", "int_mid_BJD_TDB", "int_end_BJD_TDB"):
            int_times[key] = np.nan
        return group, int_times

    # ------------------------------------------------------------------ writing
    def write_block(self, ramp, row0, sci, groupdq=None, saturation=None):
        """Write groups (ngroups, nrows, nx) of one ramp starting at detector row ``row0``.

        ``groupdq``: the simulator's flags (kept with ``groupdq_flags="truth"`` only);
        ``saturation``: the level [DN] (scalar or (nrows, nx)) of ``groupdq_flags="observed"``
        (default: :meth:`saturation_level`, from the root attributes)."""
        ny, nx = self.shape
        sci = np.asarray(sci)
        if sci.ndim != 3 or sci.shape[0] != self.ngroups or sci.shape[2] != nx:
            raise RampFileError(f"{self.path}: SCI block must be (ngroups={self.ngroups}, rows, nx={nx}), "
                                f"got {sci.shape}")
        nrows = sci.shape[1]
        if not (0 <= int(ramp) < self.nramps and 0 <= int(row0) and row0 + nrows <= ny):
            raise RampFileError(f"{self.path}: block ramp {ramp}, rows {row0}..{row0 + nrows} outside "
                                f"{self.nramps} ramps × {ny} rows")
        sci = self._as(sci, np.uint16, "SCI")
        if groupdq is not None:
            groupdq = self._as(np.asarray(groupdq), np.uint8, "GROUPDQ")
            if groupdq.shape != sci.shape:
                raise RampFileError(f"{self.path}: GROUPDQ block {groupdq.shape} ≠ SCI block {sci.shape}")
            if not self.accepts_groupdq:
                raise RampFileError(f"{self.path}: no GROUPDQ extension (groupdq=False)")
        if self.groupdq_flags == "observed":
            groupdq = observed_saturation(sci, self.saturation_level() if saturation is None else saturation)
        elif self.groupdq_flags == "none":
            groupdq = None                                 # the truth's flags are not an observable
        for g in range(self.ngroups):
            pix = ((int(ramp) * self.ngroups + g) * ny + int(row0)) * nx
            self._data("SCI", to_storage(sci[g]), 2 * pix)
            if groupdq is not None:
                self._data("GROUPDQ", to_storage(groupdq[g]), pix)

    def saturation_level(self):
        """The saturation level [DN] of observed flags from the root attributes: BIAS + GAIN·FULLWELL
        (linear: the nonlinearity truth is not read here) capped at SATURATION, less the margin of
        :func:`~slicersim.io.uncal_meta.saturation_reference`; SATURATION (else 65535) without them."""
        a = self.attrs
        saturation = float(a.get("SATURATION", 65535))
        try:
            plateau = float(a["BIAS"]) + float(a["GAIN"]) * float(a["FULLWELL"])
            sigma = group_sigma_dn(a["GAIN"], a["READNOISE"], a["NFRAMES"], a.get("KTC_NOISE", 0.0))
        except (KeyError, TypeError, ValueError):
            return saturation
        return float(saturation_reference(plateau, saturation, sigma))

    def _data(self, name, data, offset):
        """Write ``data`` ``offset`` bytes into the data unit of extension ``name`` (summed for DATASUM)."""
        self._pwrite(data, self._offsets[name] + offset)
        self._sums.add_data(self._hdu_of[name], data, offset)

    def _as(self, arr, dtype, what):
        if arr.dtype == dtype:
            return arr
        info = np.iinfo(dtype)
        if arr.dtype.kind not in "uib" or (arr.size and (arr.min() < info.min or arr.max() > info.max)):
            raise RampFileError(f"{self.path}: {what} values must be integers in [{info.min}, {info.max}] "
                                f"(got dtype {arr.dtype})")
        return arr.astype(dtype)

    def write_pixeldq(self, pixeldq):
        """Write the PIXELDQ flags (ny, nx) [JWST bit values]."""
        if not self.pixeldq:
            raise RampFileError(f"{self.path}: no PIXELDQ extension (pixeldq=False)")
        if not hasattr(pixeldq, "shape"):
            pixeldq = np.asarray(pixeldq)
        if tuple(pixeldq.shape) != self.shape:
            raise RampFileError(f"{self.path}: PIXELDQ must be {self.shape}, got {tuple(pixeldq.shape)}")
        step = max(1, (256 << 10) // (4 * self.shape[1]))        # rows per 256 KiB (h5py datasets too)
        for y0 in range(0, self.shape[0], step):
            flags = self._as(np.asarray(pixeldq[y0:y0 + step]), np.uint32, "PIXELDQ")
            self._data("PIXELDQ", to_storage(flags), 4 * y0 * self.shape[1])

    def write_truth(self, rate):
        """Append the input rate image (ny, nx) as TRUTH_RATE (float32, e-/s)."""
        rate = np.asarray(rate, dtype=np.float32)
        if rate.shape != self.shape:
            raise RampFileError(f"{self.path}: truth rate must be {self.shape}, got {rate.shape}")
        self.write_dataset("truth/rate", rate)

    def write_dataset(self, name, array, attrs=None):
        """Append ``array`` (an image, or a structured array as a binary table) as TRUTH_<NAME>.

        ``array`` may be an h5py dataset: images are copied in slices of the first axis.
        ``attrs``: string/number attributes, kept as HIERARCH keywords of the extension."""
        extname = truth_extname(name)
        if not hasattr(array, "dtype"):
            array = np.asarray(array)
        if extname in self._extnames:                      # every truth EXTNAME starts with TRUTH_
            raise RampFileError(f"{self.path}: extension {extname} (dataset {name!r}) already written")
        dtype, shape = np.dtype(array.dtype), tuple(array.shape)
        h5path = str(name).strip("/")
        h5path = h5path if h5path.startswith("truth/") else f"truth/{h5path}"    # as RampWriter.write_dataset
        extra = [("H5PATH", ascii_text(h5path)), ("H5DTYPE", json.dumps(dtype.descr) if dtype.names else str(dtype))]
        extra += [(f"HIERARCH SLICERSIM {key}", ascii_text(str(val))[:60]) for key, val in (attrs or {}).items()]
        if dtype.names:
            self._append(table_bytes(np.asarray(array[()]), extname, extra))
        else:
            if dtype.str[1:] not in IMAGE_TYPES:
                raise RampFileError(f"{self.path}: dataset {name!r} of dtype {dtype} cannot be written "
                                    "to FITS (integers, floats 32/64, booleans or structured arrays)")
            nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
            header = image_header(extname, dtype, shape, extra)
            hdu = self._sums.add_hdu(self._end, header)
            self._append(header)
            start = self._end
            row = max(1, (16 << 20) // max(1, nbytes // max(1, shape[0]))) if shape else 1
            blocks = (array[i:i + row] for i in range(0, shape[0], row)) if shape else [array[()]]
            for block in blocks:
                data = to_storage(np.asarray(block).astype(dtype, copy=False))
                self._sums.add_data(hdu, data, self._end - start)
                self._append(data)
            self._append(bytes(padded(self._end - start) - (self._end - start)))
        self._extnames.add(extname)


def write_uncal_from_hdf5(h5_path, fits_path, overwrite=False, max_bytes=64 << 20, **writer_options):
    """Convert a slicersim HDF5 ramp file (:mod:`slicersim.io.rampfile`) into a JWST level-1b
    FITS file, block by block (at most ``max_bytes`` bytes of SCI + GROUPDQ at a time, at least one
    row; ``memory_budget`` is its deprecated name).  ``writer_options``: :class:`UncalOptions` fields.

    Root attributes become keywords; /SCI, /GROUPDQ, /PIXELDQ the extensions of those names;
    every other dataset (``truth/rate``, ``truth/cosmic_rays``, ...) a TRUTH_* extension.
    Returns the absolute path of the FITS file."""
    import h5py
    if "memory_budget" in writer_options:
        validation.renamed_keyword(writer_options, "memory_budget", "max_bytes", "write_uncal_from_hdf5")
        max_bytes = writer_options.pop("max_bytes")
    max_bytes = validation.positive_int("max_bytes", max_bytes)
    h5_path = os.fspath(h5_path)
    with open_hdf5_input(h5_path, "an HDF5 ramp file", ("SCI", "GROUPDQ", "PIXELDQ")) as fh:
        if not fh.attrs.get("COMPLETE", False):
            raise RampFileError(f"{h5_path}: incomplete file (no completion marker)")
        if "SCI" not in fh:
            raise RampFileError(f"{h5_path}: not a slicersim ramp file (no SCI)")
        sci, gdq = fh["SCI"], fh.get("GROUPDQ")
        nints, ngroups, ny, nx = sci.shape
        attrs = {k: fh.attrs[k] for k in fh.attrs if k != "COMPLETE"}
        links = list(soft_links(fh))
        if links:                                   # never written by slicersim; visititems would skip them
            raise RampFileError(f"{h5_path}: {links[0]} is a soft link: a ramp file to convert holds its datasets "
                                "themselves (copy the data in place of the link)")
        others = []
        fh.visititems(lambda name, obj: others.append(name) if isinstance(obj, h5py.Dataset)
                      and name not in ("SCI", "GROUPDQ", "PIXELDQ") else None)
        per_row = max(1, ngroups * nx * 3)
        rows = rows_per_block(max(max_bytes, per_row), per_row, ny)
        truth_rate = "truth/rate" in others
        if "DETECTOR_NY" in attrs and "SUBSTRT1" in attrs and "substrt" not in writer_options:   # a window
            writer_options = {**writer_options, "detector_shape": (int(attrs["DETECTOR_NY"]), int(attrs["DETECTOR_NX"])),
                              "substrt": (int(attrs["SUBSTRT2"]), int(attrs["SUBSTRT1"]))}
        writer = UncalWriter(fits_path, nints, ngroups, (ny, nx), attrs=attrs, row_block=rows,
                             truth_rate=truth_rate, pixeldq="PIXELDQ" in fh, groupdq=gdq is not None,
                             overwrite=overwrite, **writer_options)
        with writer as w:
            if "PIXELDQ" in fh:
                w.write_pixeldq(read_dataset(fh["PIXELDQ"], h5_path))
            for name in others:
                dset = fh[name]
                keep = {k: _text(v) for k, v in dset.attrs.items()} if name == "truth/target" else None  # its units
                w.write_dataset(name, dset if dset.ndim == 3 else read_dataset(dset, h5_path), attrs=keep)
            for ramp, y0, y1 in RowBlocks(ny, rows, nouter=nints, progress=False):
                block = np.s_[ramp, :, y0:y1, :]
                w.write_block(ramp, y0, read_dataset(sci, h5_path, block),
                              None if gdq is None else read_dataset(gdq, h5_path, block))
    return writer.path


def _text(value):
    """An HDF5 attribute as a keyword value (bytes decoded)."""
    return value.decode("utf-8", "replace") if isinstance(value, bytes) else value
