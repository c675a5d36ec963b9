"""Group-level raw-ramp files (HDF5), written in row blocks; no physics here.

Layout (one file per exposure)::

    /SCI            uint16  (nramps, ngroups, ny, nx)   group-averaged reads [ADU]
    /GROUPDQ        uint8   (nramps, ngroups, ny, nx)   JWST group flags (2 = SATURATED); sparse
    /PIXELDQ        uint32  (ny, nx)                    JWST pixel flags (1 DO_NOT_USE, 1024 DEAD, 2048 HOT)
    /truth/rate     float32 (ny, nx)   optional         input rate [e-/s]
    /truth/<name>   truth of the detector effects (``effects=``): cosmic_rays (compound: ramp,
                    frame, y, x, electrons), nonlinearity/coefficients, ..., see
                    :mod:`slicersim.products.effects`
    root attributes NINTS NGROUPS NFRAMES GROUPGAP TFRAME TGROUP READPATT GAIN READNOISE
                    SEED BUNIT SOFTWARE VERSION CONFIG (JSON) COMPLETE

SCI and GROUPDQ are chunked one group × a row block.  GROUPDQ is stored only where it carries
information: a group's block of rows with no flag is not written at all (HDF5 reads a chunk never
written as the fill value 0, GOOD: readers of every release see the same array), and the chunks
written are compressed losslessly (the ramps' ``compression``, else gzip level 1); the attribute
``SPARSE = True`` says so.  PIXELDQ (mostly 0) and ``truth/rate`` (a smooth rate map) are
compressed losslessly too (the ramps' ``compression``, else byte-shuffled gzip level 1;
``truth/rate`` always byte-shuffled gzip level 1): zlib's output depends on the data only, so the
file bytes do not depend on the run.  Files of earlier releases (GROUPDQ whole, uncompressed) are
read alike.  Every dataset carries HDF5's Fletcher-32
checksum (verified by HDF5 on each read: a flipped byte is a :class:`RampFileError` "checksum
mismatch", :func:`read_error`).  Files read here are inputs we did not write: external storage,
virtual datasets and external links are refused before any data are read (:func:`check_hdf5_input`).
The file is written
under a temporary name ``.NAME.tmp-PID-xxxx`` in the target directory and
linked to ``NAME`` only when complete (never replacing an existing file
unless asked); an interrupted writer leaves no file with the final name, and
its temporary is removed by the next writer in that directory.
"""
from __future__ import annotations

from slicersim import validation
from slicersim.errors import ParameterError, RampFileError

import contextlib
import json
import os
import shutil

import numpy as np

from slicersim.io.row_blocks import SIMULATED_ROWS, row_ranges
from slicersim.io.atomic import _HDF5_MARGIN, AtomicH5File, flush_chunks, is_temporary, one_line, remove_stale_temporaries

__all__ = ["RampWriter", "RampFileError", "compression_options", "read_ramps", "DQ", "is_temporary",
           "remove_stale_temporaries", "check_hdf5_input", "metadata_errors", "check_stored", "read_error", "open_hdf5_input", "soft_links",
           "MAX_COMPRESSION"]

#: JWST data-quality bit values
DQ = {"GOOD": 0, "DO_NOT_USE": 1, "SATURATED": 2, "JUMP_DET": 4, "DEAD": 1024, "HOT": 2048}

#: largest compression ratio assumed by the free-space check of a compressed ramp: noisy uint16
#: ramps compress ~2-3× losslessly (bit-shuffle + LZ4/Zstd); the check needs uncompressed / this
MAX_COMPRESSION = 4.0
#: h5py options of the flags (GROUPDQ, PIXELDQ) of uncompressed ramps: lossless, deterministic bytes
FLAG_FILTERS = {"compression": "gzip", "compression_opts": 1, "shuffle": True, "fletcher32": True}
#: h5py options of ``truth/rate``: byte-shuffled gzip level 1 (lossless; a mostly dark rate map stores
#: in a fraction of its 4 bytes per pixel)
TRUTH_FILTERS = {"compression": "gzip", "compression_opts": 1, "shuffle": True, "fletcher32": True}
#: most objects (groups, datasets) :func:`check_hdf5_input` visits in one input file
MAX_HDF5_OBJECTS = 100_000


def compression_options(compression):
    """h5py dataset keyword arguments for ``compression``.

    None (default, uncompressed), ``"gzip"`` or ``"gzip:<level>"``, ``"lz4"``
    (Blosc2/LZ4 with bit-shuffle, via hdf5plugin), ``"zstd"`` (Blosc2/Zstd with
    bit-shuffle), ``"bitshuffle-lz4"`` (bitshuffle filter with LZ4).
    Every option set carries ``fletcher32=True`` (a checksum per chunk, verified on read).
    """
    return {**_compression_filters(compression), "fletcher32": True}


def _compression_filters(compression):
    if compression in (None, "none", False):
        return {}
    if str(compression).startswith("gzip"):
        level = str(compression).split(":")[1] if ":" in str(compression) else "4"
        if not level.isdigit() or not 0 <= int(level) <= 9:
            raise RampFileError(f"compression {compression!r}: the gzip level must be an integer 0-9")
        return {"compression": "gzip", "compression_opts": int(level), "shuffle": True}
    try:
        import hdf5plugin
    except ImportError as exc:
        raise RampFileError(f"compression {compression!r} needs the 'hdf5plugin' package") from exc
    if compression == "lz4":
        return dict(hdf5plugin.Blosc2(cname="lz4", clevel=5, filters=hdf5plugin.Blosc2.BITSHUFFLE))
    if compression == "zstd":
        return dict(hdf5plugin.Blosc2(cname="zstd", clevel=3, filters=hdf5plugin.Blosc2.BITSHUFFLE))
    if compression == "bitshuffle-lz4":
        return dict(hdf5plugin.Bitshuffle(cname="lz4"))
    raise RampFileError(f"unknown compression {compression!r}: None, 'gzip[:level]', 'lz4', 'zstd', "
                        "'bitshuffle-lz4'")


class RampWriter(AtomicH5File):
    """Stream a raw ramp to HDF5 in row blocks (context manager).

    Parameters
    ----------
    path : output file name
    nramps, ngroups : int;  shape : (ny, nx)
    attrs : dict of root attributes (values JSON-serialisable or scalars)
    row_block : rows per chunk;  compression : see :func:`compression_options`
    truth_rate : bool, reserve /truth/rate
    extra_bytes : further bytes (truth of detector effects) for the disk-space check
    overwrite : replace an existing ``path`` (default: refuse with :class:`RampFileError`)

    The file is written as ``.NAME.tmp-PID-xxxx`` in the target directory (created with the
    user's umask) and linked to ``NAME`` only when complete, which fails if ``NAME`` appeared
    meanwhile (two writers: one wins, the other gets a clear error).  Any error, SIGINT or
    exception inside the ``with`` block removes the temporary.  Temporaries of killed writers
    are removed by the next writer in the same directory.
    """

    error_class = RampFileError
    _dataset_names = ("sci", "groupdq", "pixdq", "truth")

    def __init__(self, path, nramps, ngroups, shape, attrs=None, row_block=64, compression=None,
                 truth_rate=False, pixeldq=True, overwrite=False, extra_bytes=0, rows=None):
        super().__init__(path, overwrite)
        #: row ranges of a file of some rows (``simulate(rows=)``): lazy truth arrays are computed and
        #: written on those rows only
        self.rows = rows
        self.extra_bytes = int(extra_bytes)
        self.nramps, self.ngroups = int(nramps), int(ngroups)
        self.shape = tuple(int(s) for s in shape)
        self.attrs = dict(attrs or {})
        self.row_block = int(max(1, min(row_block, self.shape[0])))
        self.compression = compression_options(compression)
        self.truth_rate, self.pixeldq = truth_rate, pixeldq

    # ------------------------------------------------------------------ lifecycle
    def expected_bytes(self):
        """Uncompressed size of SCI + GROUPDQ (of the rows written) (+ PIXELDQ, truth rate, ``extra_bytes``)
        [bytes]."""
        held = self.shape[0] if self.rows is None else sum(b - a for a, b in self.rows)
        n = self.nramps * self.ngroups * held * self.shape[1]
        return n * 3 + self.shape[0] * self.shape[1] * (4 * self.pixeldq + 4 * self.truth_rate) + self.extra_bytes

    def check(self):
        """Refuse early (before any simulation or allocation): missing or read-only directory,
        existing file without ``overwrite``, not enough free disk space: for the uncompressed file,
        or for a compressed one its uncompressed size / :data:`MAX_COMPRESSION` (the compression
        reached is measured on the first ramp written, :meth:`write_block`)."""
        super().check()
        directory = os.path.dirname(self.path) or "."
        remove_stale_temporaries(directory)          # a killed writer's temporary holds disk space
        self._check_space(self.expected_bytes() / (MAX_COMPRESSION if self._compressed else 1.0),
                          "" if not self._compressed else f" (compressed at most {MAX_COMPRESSION:g}×)")
        return self

    @property
    def _compressed(self):
        return "compression" in self.compression

    def _flag_filters(self):
        """h5py options of GROUPDQ and PIXELDQ: the ramps' compression, else byte-shuffled gzip
        level 1 (flags are mostly 0: a full-detector PIXELDQ of 64 MiB stores in well under 1 MiB)."""
        return self.compression if self._compressed else FLAG_FILTERS

    def _check_space(self, need, how="", held=0):
        """RampFileError when ``need`` bytes (+ margin) exceed the free space plus ``held`` bytes
        (those already written by this writer) of the output directory."""
        directory = os.path.dirname(self.path) or "."
        need = need + _HDF5_MARGIN
        free = shutil.disk_usage(directory).free + held
        if need > free:
            raise RampFileError(f"not enough disk space in {directory}: need {need / 1e9:.3g} GB{how} "
                                f"for {self.path}, {free / 1e9:.3g} GB free")

    def _check_measured_space(self):
        """After the first ramp of a compressed file: its size on disk projected to every ramp
        must fit (the compression of noisy ramps is measured, not assumed)."""
        self._h5(self.file.flush)
        written = os.fstat(self._fd).st_size if self._fd is not None else 0
        self._check_space(written * self.nramps + self.extra_bytes,
                          f" (measured compression on the first of {self.nramps} ramps)", held=written)

    def _populate(self, file):
        dims = (self.nramps, self.ngroups) + self.shape
        chunks = (1, 1, self.row_block, self.shape[1])
        self.sci = file.create_dataset("SCI", dims, dtype="u2", chunks=chunks, **self.compression)
        self.groupdq = file.create_dataset("GROUPDQ", dims, dtype="u1", chunks=chunks, fillvalue=0,
                                           **self._flag_filters())
        self.groupdq.attrs["SPARSE"] = True          # chunks without a flag are not stored: read as 0
        if self.pixeldq:
            self.pixdq = file.create_dataset("PIXELDQ", self.shape, dtype="u4",
                                             chunks=(self.row_block, self.shape[1]), **self._flag_filters())
        if self.truth_rate:
            self.truth = file.create_dataset("truth/rate", self.shape, dtype="f4",
                                             chunks=(self.row_block, self.shape[1]), **TRUTH_FILTERS)
        for key, val in self.attrs.items():
            file.attrs[key] = val if not isinstance(val, (dict, list, tuple)) else json.dumps(val)
        file.attrs["COMPLETE"] = False

    # ------------------------------------------------------------------ writing
    def write_block(self, ramp, row0, sci, groupdq=None):
        """Write groups (ngroups, nrows, nx) of one ramp starting at detector row ``row0``."""
        rows = slice(row0, row0 + sci.shape[1])

        def put():
            self.sci[ramp, :, rows, :] = sci
            if groupdq is not None:
                for g in _flagged_groups(groupdq):      # GROUPDQ only where it carries information
                    self.groupdq[ramp, g, rows, :] = groupdq[g]
        self._h5(put)
        last = self.shape[0] if self.rows is None else self.rows[-1][1]      # the first ramp's last row
        if self._compressed and self.nramps > 1 and ramp == 0 and rows.stop >= last:
            self._check_measured_space()

    def write_pixeldq(self, pixeldq):
        self._h5(self.pixdq.__setitem__, Ellipsis, np.asarray(pixeldq, dtype=np.uint32))
        self._h5(flush_chunks, self.pixdq)

    def write_truth(self, rate):
        self._h5(self.truth.__setitem__, Ellipsis, np.asarray(rate, dtype=np.float32))
        self._h5(flush_chunks, self.truth)

    def _close_file(self):
        """Flush the chunks of SCI and GROUPDQ (then of every dataset, in a fixed order) before the
        file closes: where compressed chunks land must not depend on when the last handle to a
        dataset is released (:func:`~slicersim.io.atomic.flush_chunks`)."""
        if self._file is not None and (self._fh is None or self._fh.error is None):
            for name in self._dataset_names:
                dset = self.__dict__.get(name)
                if dset is not None:
                    flush_chunks(dset)
        super()._close_file()

    def write_dataset(self, name, array, attrs=None):
        """Write ``truth/<name>`` (any array, structured arrays as compound datasets) with attributes.

        ``array`` may be a lazy (k, ny, nx) array-like (``shape``, ``dtype``, ``[:, y0:y1]``): it is
        then written in blocks of rows, never whole in memory."""
        lazy = not isinstance(array, np.ndarray) and hasattr(array, "shape") and len(getattr(array, "shape")) == 3
        if not lazy:
            array = np.asarray(array)

        def put():
            if lazy:
                k, ny, nx = array.shape
                rows = max(1, min(ny, LAZY_BLOCK_BYTES // max(1, k * nx * np.dtype(array.dtype).itemsize)))
                first = np.asarray(array[:, 0:rows]) if 0 not in array.shape else None
                # compressed (lossless) when the first block shows it is worth it, as an in-memory array
                filters = {key: v for key, v in _compression_for(first).items() if key not in ("chunks", "fletcher32")} \
                    if first is not None else {}
                ds = self.file.create_dataset(f"truth/{name}", array.shape, dtype=array.dtype,
                                              chunks=(1, rows, nx), fletcher32=0 not in array.shape, **filters)
                for y0 in range(0, ny, rows):
                    if y0 == 0:
                        ds[:, 0:rows] = first
                        continue
                    for a, b in ((y0, min(ny, y0 + rows)),) if self.rows is None else self.rows:
                        a, b = max(a, y0), min(b, y0 + rows)         # the rows of this block the file holds
                        if a < b:
                            ds[:, a:b] = array[:, a:b]
            else:
                kwargs = _compression_for(array)
                ds = self.file.create_dataset(f"truth/{name}", data=array, **kwargs)
            for key, val in (attrs or {}).items():
                ds.attrs[key] = val if not isinstance(val, (dict, list, tuple)) else json.dumps(val)
            flush_chunks(ds)
        self._h5(put)


def _flagged_groups(groupdq):
    """Indices of the groups of a (ngroups, rows, nx) GROUPDQ block holding any flag."""
    flat = np.asarray(groupdq).reshape(len(groupdq), -1)
    return np.flatnonzero(flat.any(axis=1))


def _compression_for(array, probe_bytes=1 << 20, worth=0.75):
    """h5py options for a truth array (chunked with a Fletcher-32 checksum): byte-shuffled gzip-1 when a zlib probe of its first
    ``probe_bytes`` (shuffled) compresses below ``worth`` of its size, else none (noise-like
    float maps barely compress and gzip would cost ~1 s per 64 MB)."""
    if array.ndim == 0 or array.size == 0:                  # no chunks: no checksum either
        return {}
    if array.size <= 4096 or array.dtype.kind not in "biufV":
        return {"chunks": True, "fletcher32": True}
    import zlib
    flat = np.ascontiguousarray(array).reshape(-1)
    head = flat[:max(1, probe_bytes // flat.itemsize)]
    shuffled = head.view(np.uint8).reshape(-1, flat.itemsize).T.tobytes()
    if len(zlib.compress(shuffled, 1)) >= worth * len(shuffled):
        return {"chunks": True, "fletcher32": True}
    return {"chunks": True, "compression": "gzip", "compression_opts": 1, "shuffle": True, "fletcher32": True}


def read_error(exc, path, dset):
    """The :class:`RampFileError` for an h5py ``exc`` (OSError) raised while reading the h5py dataset
    ``dset`` of ``path``: "checksum mismatch in dataset NAME of PATH" when a filter failed on a
    dataset with Fletcher-32 checksums (HDF5 reports a failed checksum as "filter returned failure
    during read": the bytes on disk are not those written), else "cannot read dataset NAME of PATH"."""
    text = one_line(exc)
    name = dset.name.lstrip("/") if hasattr(dset, "name") else str(dset)
    failed_filter = "fletcher" in text.lower() or "checksum" in text.lower() or "filter" in text.lower()
    if failed_filter and getattr(dset, "fletcher32", False):
        return RampFileError(f"checksum mismatch in dataset {name} of {path}: the file is corrupt "
                             f"(HDF5: {text})")
    return RampFileError(f"cannot read dataset {name} of {path} ({text})")


def read_dataset(dset, path, key=Ellipsis):
    """``dset[key]`` with h5py's read errors (a failed checksum) as one :func:`read_error`."""
    try:
        return dset[key]
    except OSError as exc:
        raise read_error(exc, path, dset) from None


def simulated_rows(fh, path):
    """The row ranges of a ramp file holding only some detector rows (its ``SIMULATED_ROWS`` attribute,
    :data:`~slicersim.io.row_blocks.SIMULATED_ROWS`), or None for a whole-detector file.  RampFileError
    naming ``path`` when the attribute is not valid ranges inside SCI's rows."""
    import h5py
    if SIMULATED_ROWS not in fh.attrs:
        return None
    raw = fh.attrs[SIMULATED_ROWS]
    sci = fh.get("SCI")
    ny = int(sci.shape[2]) if isinstance(sci, h5py.Dataset) and sci.ndim == 4 else 0
    try:
        value = json.loads(raw if isinstance(raw, str) else bytes(raw).decode())
        return row_ranges(value, ny, SIMULATED_ROWS)
    except (ValueError, TypeError, UnicodeDecodeError, ParameterError) as exc:
        raise RampFileError(f"{path}: attribute {SIMULATED_ROWS} is not a list of [y0, y1) row ranges inside "
                            f"SCI's {ny} rows ({one_line(exc)})") from None


def check_hdf5_input(fh, path, datasets=("SCI",), partial_rows=False):
    """Refuse (RampFileError naming ``path`` and the object) an HDF5 input that would read bytes
    from outside itself or is not the layout asked for, before any data are read:

    * an external link anywhere in the file (soft links stay inside the file and are followed);
    * a dataset with external storage (its bytes in another file) or a virtual dataset (a view
      of other files' datasets);
    * an object of ``datasets`` that exists but is not a dataset (a group named SCI);
    * a SCI dataset whose declared shape is not stored in the file (:func:`check_stored`: a few
      bytes declaring 10⁵ × 10⁵ pixels would be read as that many zeros);
    * a file holding only some detector rows (:func:`simulated_rows`) unless ``partial_rows`` (the
      reader then reads only those rows; with ``partial_rows`` the rows listed must be stored).
    """
    with metadata_errors(path):
        ranges = simulated_rows(fh, path)
        if ranges is not None and not partial_rows:
            raise RampFileError(f"{path}: holds only detector rows {_ranges_text(ranges)} (a streaming campaign's "
                                "ramp, simulated for its reduction): read it with fit_ramps or slicersim reduce")
        _check_objects(fh, path, datasets, ranges)


def _ranges_text(ranges):
    return ", ".join(f"{a}:{b}" for a, b in ranges)


@contextlib.contextmanager
def metadata_errors(path):
    """HDF5's failed metadata checksum (a changed byte in an attribute, a dataset's layout or a group, in a
    file written with checksummed object headers, :data:`slicersim.io.atomic.HDF5_LIBVER`) as one
    :class:`RampFileError`, the same line as a failed data checksum; other errors pass."""
    try:
        yield
    except (KeyError, OSError, RuntimeError) as exc:
        if isinstance(exc, RampFileError) or "checksum" not in str(exc).lower():
            raise
        raise RampFileError(f"checksum mismatch in the metadata (attributes, layout) of {path}: the file is "
                            f"corrupt (HDF5: {one_line(exc)})") from None


def _check_objects(fh, path, datasets, ranges=None):
    """:func:`check_hdf5_input`'s walk; every object's attributes are read once, so a failed metadata
    checksum is found here, before any value is used."""
    import h5py
    dict(fh.attrs)
    for name in datasets:
        obj = fh.get(name, getlink=True)
        if obj is None or isinstance(obj, h5py.ExternalLink):
            continue
        try:
            target = fh.get(name)
        except (RuntimeError, KeyError, OSError) as exc:      # a soft link to itself, or a loop of them
            raise RampFileError(f"{path}: {name} is a soft link that does not resolve to an object "
                                f"({one_line(exc)})") from None
        if not isinstance(target, h5py.Dataset):
            raise RampFileError(f"{path}: {name} is {_kind_of(target)}, not a dataset")
    if "SCI" in datasets and isinstance(fh.get("SCI"), h5py.Dataset):
        check_stored(fh["SCI"], path, "SCI", ranges)
    seen, todo = set(), [fh]
    while todo:
        group = todo.pop()
        for key in group:
            where = f"{group.name.rstrip('/')}/{key}".lstrip("/")
            link = group.get(key, getlink=True)
            if isinstance(link, h5py.ExternalLink):
                raise RampFileError(f"{path}: {where} is an external link to {link.filename}:{link.path} "
                                    "(inputs must hold their own data)")
            if isinstance(link, h5py.SoftLink):
                continue                         # inside the file: its target is visited as itself
            obj = group.get(key)
            if obj is None or obj.id in seen:
                continue
            seen.add(obj.id)
            if len(seen) > MAX_HDF5_OBJECTS:
                raise RampFileError(f"{path}: more than {MAX_HDF5_OBJECTS} HDF5 objects: not a ramp file")
            dict(obj.attrs)                      # verifies the object header's checksum
            if isinstance(obj, h5py.Group):
                todo.append(obj)
            elif isinstance(obj, h5py.Dataset):
                _check_storage(obj, path, where)


def check_stored(dset, path, where, ranges=None):
    """Refuse (RampFileError naming ``path``, the dataset and its declared shape) a dataset whose data
    were never written: chunks missing from a chunked dataset, no storage for a contiguous one.  HDF5
    reads such a dataset as its fill value, so a file of a few bytes declaring (1, 4, 10⁵, 10⁵) would
    allocate 80 GB of zeros before anything else could be said.  ``ranges``: row ranges of axis 2 (a
    file of some detector rows, :func:`simulated_rows`): only the chunks holding them are needed."""
    if dset.size == 0 or dset.is_virtual:
        return
    nbytes = dset.size * dset.dtype.itemsize
    if dset.chunks is None:
        stored, total = int(dset.id.get_storage_size() > 0), 1
        what = "has no storage for it"
    else:
        counts = [-(-s // c) for s, c in zip(dset.shape, dset.chunks)]
        if ranges is not None and dset.ndim == 4:
            stored, total = _stored_row_chunks(dset, ranges)
        else:
            total = int(np.prod(counts, dtype=np.float64))
            stored = int(dset.id.get_num_chunks())
        what = f"stores {stored} of its {total} chunks" + ("" if ranges is None else
                                                           f" of rows {_ranges_text(ranges)}")
    if stored < total:
        marker = dset.file.attrs.get("COMPLETE", None)
        head = "incomplete file (no completion marker): " if marker is not None and not marker else ""
        raise RampFileError(f"{path}: {head}dataset {where} declares shape {tuple(dset.shape)} {dset.dtype} "
                            f"({nbytes / 2**30:.3g} GiB) but the file {what}: its data were never written "
                            "(an incomplete or forged file)")


def _stored_row_chunks(dset, ranges):
    """(stored, needed): the chunks of a 4-D dataset holding the rows ``ranges`` (axis 2), each looked up
    by its coordinates: a count of all chunks would pass an attribute naming other rows than those written
    (the absent rows read as zeros)."""
    import itertools
    c = dset.chunks[2]
    ys = sorted({k * c for a, b in ranges for k in range(a // c, (b - 1) // c + 1)})
    offsets = [range(0, n, step) for n, step in zip(dset.shape, dset.chunks)]
    offsets[2] = ys
    needed = list(itertools.product(*offsets))
    if hasattr(dset.id, "chunk_iter"):             # one pass over the chunk index (HDF5 ≥ 1.12.3, h5py ≥ 3.8)
        held = set()
        dset.id.chunk_iter(lambda info: held.add(tuple(info.chunk_offset)))
        return sum(o in held for o in needed), len(needed)
    return sum(dset.id.get_chunk_info_by_coord(o).byte_offset is not None for o in needed), len(needed)


def _kind_of(obj):
    import h5py
    return "a group" if isinstance(obj, h5py.Group) else "a dangling link" if obj is None else \
        f"a {type(obj).__name__}"


def _check_storage(dset, path, where):
    """A dataset's bytes must be in this file: no external storage, no virtual dataset."""
    if dset.is_virtual:
        raise RampFileError(f"{path}: dataset {where} is a virtual dataset (its data are in other files); "
                            "inputs must hold their own data")
    if dset.id.get_create_plist().get_external_count() > 0:
        raise RampFileError(f"{path}: dataset {where} has external storage (its bytes are in another file); "
                            "inputs must hold their own data")


#: bytes of a lazy truth array (nonlinearity coefficients) computed and written at once
LAZY_BLOCK_BYTES = 16 << 20

#: HDF5 chunk cache of every dataset of a ramp file opened for reading (h5py's default is 1 MiB): the
#: reduction reads row blocks narrower than the chunks (20 rows of a 49-row SCI chunk, of a 170-row
#: compressed nonlinearity chunk), and a chunk that does not stay cached is read and decompressed
#: again for every block: 16 of 20 CPU-s of reading in one effects reduction on the 2-core VM
READ_CHUNK_CACHE = {"rdcc_nbytes": 64 << 20, "rdcc_nslots": 100003}


def open_hdf5_input(path, what="an HDF5 ramp file", datasets=("SCI",), chunk_cache=True):
    """The h5py File of an input we did not write, checked: a regular file (not a FIFO, device or
    directory; no size bound: ramps are large) and :func:`check_hdf5_input`.  RampFileError naming ``path`` otherwise.
    ``chunk_cache``: :data:`READ_CHUNK_CACHE` (reads in row blocks); False: h5py's default (whole reads,
    for which a cache only holds a second copy)."""
    import h5py
    if isinstance(path, (str, os.PathLike)) and not os.path.lexists(path):
        raise RampFileError(f"{os.fspath(path)}: no such file")
    path = validation.regular_file("ramp file", path, error=RampFileError)
    if is_temporary(path):
        raise RampFileError(f"{path}: incomplete file (temporary of an unfinished or killed writer)")
    try:
        with metadata_errors(path):
            fh = h5py.File(path, "r", **(READ_CHUNK_CACHE if chunk_cache else {}))
    except RampFileError:
        raise
    except OSError as exc:
        raise RampFileError(f"{path}: not {what} ({one_line(exc)})") from exc
    try:
        check_hdf5_input(fh, path, datasets)
    except BaseException:
        fh.close()
        raise
    return fh


def read_ramps(path):
    """Read a complete ramp file whole (checked by ``open_hdf5_input``).

    Parameters
    ----------
    path : str or path-like
        The HDF5 ramp file.

    Returns
    -------
    sci : numpy.ndarray of shape (nramps, ngroups, ny, nx)
        The ramps SCI [ADU].
    groupdq : numpy.ndarray of shape (nramps, ngroups, ny, nx)
        Their group data-quality flags GROUPDQ.
    pixeldq : numpy.ndarray of shape (ny, nx) or None
        The pixel data-quality flags PIXELDQ, None when the file has none.
    attrs : dict
        The file's root attributes.

    Raises
    ------
    slicersim.errors.RampFileError
        An incomplete or foreign file, or a failed checksum.
    """
    path = os.fspath(path)
    with open_hdf5_input(path, "an HDF5 ramp file (incomplete file?)", chunk_cache=False) as fh:
        if not fh.attrs.get("COMPLETE", False):
            raise RampFileError(f"{path}: incomplete file (no completion marker)")
        if "SCI" not in fh or "GROUPDQ" not in fh:
            raise RampFileError(f"{path}: not a slicersim ramp file (no SCI/GROUPDQ)")
        check_hdf5_input(fh, path, ("SCI", "GROUPDQ", "PIXELDQ"))
        sci = fh["SCI"]
        validation.memory(f"{path}: dataset SCI of shape {tuple(sci.shape)} read whole (with GROUPDQ)",
                          sci.size * 3 + (fh["PIXELDQ"].size * 4 if "PIXELDQ" in fh else 0),
                          hint="read it by row blocks (fit_ramps, slicersim reduce)")
        attrs = {k: fh.attrs[k] for k in fh.attrs}
        pix = read_dataset(fh["PIXELDQ"], path) if "PIXELDQ" in fh else None
        return read_dataset(fh["SCI"], path), read_dataset(fh["GROUPDQ"], path), pix, attrs


def soft_links(group, prefix=""):
    """Paths of the soft links under an h5py ``group`` (``visititems`` does not follow them, so a
    reader walking the file that way would miss what they point to)."""
    import h5py
    for name in group:
        link = group.get(name, getlink=True)
        if isinstance(link, h5py.SoftLink):
            yield prefix + name
        elif isinstance(link, h5py.HardLink) and isinstance(group[name], h5py.Group):
            yield from soft_links(group[name], prefix + name + "/")
