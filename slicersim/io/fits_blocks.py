"""FITS encoding primitives for files written in blocks (level-1b "uncal" files): 2880-byte
padding, header cards, IMAGE headers and big-endian storage with BZERO offsets, binary tables,
MJD arithmetic.  Formats only; no physics.
"""
from __future__ import annotations

import datetime as _dt
import io
import json
import math

import numpy as np

from slicersim.errors import RampFileError
from slicersim.io.fits_checksum import checksum_cards

__all__ = ["BLOCK", "IMAGE_TYPES", "padded", "ascii_text", "card_value", "mjd", "from_mjd", "header_bytes",
           "image_header", "to_storage", "table_bytes"]

BLOCK = 2880
_MJD0 = _dt.datetime(1858, 11, 17)
#: (BITPIX, BZERO, storage dtype) of each image dtype; the stored value is value − BZERO
IMAGE_TYPES = {"u1": (8, None, ">u1"), "i1": (8, -128, ">u1"), "u2": (16, 32768, ">i2"),
               "i2": (16, None, ">i2"), "u4": (32, 2**31, ">i4"), "i4": (32, None, ">i4"),
               "u8": (64, 2**63, ">i8"), "i8": (64, None, ">i8"), "f4": (-32, None, ">f4"),
               "f8": (-64, None, ">f8"), "b1": (8, None, ">u1")}


def padded(n):
    """``n`` bytes rounded up to whole 2880-byte FITS blocks."""
    return -(-int(n) // BLOCK) * BLOCK


def ascii_text(text):
    """``text`` as printable ASCII (non-ASCII and control characters escaped)."""
    return str(text).encode("ascii", "backslashreplace").decode("ascii").translate(
        {c: f"\\x{c:02x}" for c in range(32)})


def card_value(val):
    """A root attribute as a FITS header value (str, int, float, bool)."""
    if isinstance(val, bytes):
        val = val.decode("utf-8", "replace")
    if isinstance(val, np.ndarray):
        val = val.tolist() if val.ndim else val.item()
    if isinstance(val, np.generic):
        val = val.item()
    if isinstance(val, (dict, list, tuple)):
        val = json.dumps(val)
    if isinstance(val, bool):
        return val
    if isinstance(val, int):
        return val if -2**63 <= val < 2**63 else str(val)
    if isinstance(val, float):
        return val if math.isfinite(val) else str(val)
    return ascii_text(val)


def mjd(when):
    """MJD of a naive UTC datetime (calendar arithmetic, no leap seconds)."""
    return (when - _MJD0).total_seconds() / 86400.0


def from_mjd(mjd):
    return _MJD0 + _dt.timedelta(days=float(mjd))


def header_bytes(cards):
    from astropy.io import fits
    hdr = fits.Header()
    for key, val, *comment in list(cards) + checksum_cards():     # values set when the file is complete
        if len(key) > 8 and not key.startswith("HIERARCH "):
            key = "HIERARCH " + key
        hdr.append(fits.Card(key, val, comment[0] if comment else None), end=True)
    return hdr.tostring().encode("ascii")


def image_header(extname, dtype, shape, extra=()):
    """Header bytes of an IMAGE extension holding ``dtype`` values of ``shape`` (C order)."""
    kind = np.dtype(dtype).str[1:]
    if kind not in IMAGE_TYPES:
        raise RampFileError(f"{extname}: dtype {np.dtype(dtype)} cannot be stored in a FITS image")
    bitpix, bzero, _ = IMAGE_TYPES[kind]
    cards = [("XTENSION", "IMAGE", "Image extension"), ("BITPIX", bitpix), ("NAXIS", len(shape))]
    cards += [(f"NAXIS{i + 1}", int(n)) for i, n in enumerate(reversed(shape))]
    cards += [("PCOUNT", 0), ("GCOUNT", 1)]
    if bzero is not None:
        cards += [("BSCALE", 1), ("BZERO", bzero)]
    cards += [("EXTNAME", extname), ("EXTVER", 1)] + list(extra)
    return header_bytes(cards)


def to_storage(block):
    """Big-endian FITS storage (contiguous array) of a block: value − BZERO in the storage type."""
    block = np.ascontiguousarray(block)
    bitpix, bzero, store = IMAGE_TYPES[block.dtype.str[1:]]
    if bzero is None:
        return block.astype(store, copy=False)
    unsigned = np.dtype(f"u{abs(bitpix) // 8}")
    flip = unsigned.type(1 << (abs(bitpix) - 1))
    # v − BZERO in two's complement is v with its top bit flipped (int8: v + 128 likewise)
    out = np.bitwise_xor(block.view(unsigned), flip)
    return out.byteswap(inplace=True).view(unsigned.newbyteorder(">")) if out.dtype.byteorder != ">" else out


def table_bytes(array, extname, extra=()):
    """(header + data) bytes of a BINTABLE holding the structured ``array``."""
    from astropy.io import fits
    hdu = fits.BinTableHDU(data=np.asarray(array), name=extname)
    for key, val in extra:
        hdu.header[key] = val
    buf = io.BytesIO()
    fits.HDUList([fits.PrimaryHDU(), hdu]).writeto(buf, checksum=True)
    primary = fits.PrimaryHDU()
    primary.add_checksum()
    return buf.getvalue()[len(primary.header.tostring()):]
