"""FITS ``CHECKSUM`` / ``DATASUM`` keywords (FITS standard 4.0, section 4.4.2.7 and appendix J) of
files written in pieces, as JWST files carry them; no physics here.

DATASUM is the 32-bit ones'-complement sum of an HDU's data (big-endian 32-bit words from the
start of the data unit); CHECKSUM the 16-character ASCII encoding of the complement of the sum of
header and data, so that the whole HDU sums to −0.  The sum is associative and commutative, so
blocks written in any order (each byte once) are summed as they are written, each at its phase
(offset modulo 4) in the data unit: the file is never read back.
"""
from __future__ import annotations

import os

import numpy as np

__all__ = ["ones_sum", "ones_add", "encode_checksum", "StreamedChecksums", "ZERO_CHECKSUM"]

#: the CHECKSUM value a header holds while its sum is computed
ZERO_CHECKSUM = "0" * 16
_CARD = 80
#: characters the encoding avoids (punctuation between the digits and the letters)
_EXCLUDE = frozenset(b":;<=>?@[\\]^_`")


def ones_add(a, b):
    """Ones'-complement sum of two 32-bit values (end-around carry)."""
    s = int(a) + int(b)
    while s >> 32:
        s = (s & 0xFFFFFFFF) + (s >> 32)
    return s


def ones_sum(data, phase=0):
    """Ones'-complement sum of ``data`` (bytes-like) as big-endian 32-bit words, the block starting
    ``phase`` bytes (0-3) after a word boundary; missing bytes count as zeros."""
    raw = np.frombuffer(memoryview(data).cast("B"), np.uint8)
    pad = (-(phase + raw.size)) % 4
    if phase or pad:
        raw = np.concatenate([np.zeros(phase, np.uint8), raw, np.zeros(pad, np.uint8)])
    words = raw.view(">u4")
    total = 0
    step = 1 << 28                           # < 2**32 words per partial sum: no uint64 overflow
    for i in range(0, words.size, step):
        total = ones_add(total, int(words[i:i + step].sum(dtype=np.uint64)))
    return total


def encode_checksum(value):
    """The 16-character CHECKSUM string of the complement of a 32-bit sum (FITS appendix J)."""
    value = ~int(value) & 0xFFFFFFFF
    asc = [0] * 16
    for i in range(4):
        byte = (value >> (24 - 8 * i)) & 0xFF
        quotient, remainder = byte // 4 + ord("0"), byte % 4
        ch = [quotient + remainder, quotient, quotient, quotient]
        changed = True
        while changed:
            changed = False
            for j in (0, 2):
                if ch[j] in _EXCLUDE or ch[j + 1] in _EXCLUDE:
                    ch[j], ch[j + 1] = ch[j] + 1, ch[j + 1] - 1
                    changed = True
        for j in range(4):
            asc[4 * j + i] = ch[j]
    return bytes(asc[15:] + asc[:15]).decode("ascii")


def checksum_cards():
    """The two cards every header written in pieces ends with (values set by :meth:`StreamedChecksums.finish`)."""
    return [("CHECKSUM", ZERO_CHECKSUM, "HDU checksum"), ("DATASUM", "0", "data unit checksum")]


def _card(key, value, comment):
    from astropy.io import fits
    return fits.Card(key, value, comment).image.encode("ascii")


def _replace_card(header, key, image):
    """``header`` (bytes, 80-character cards) with the card ``key`` replaced by ``image``."""
    name = key.encode("ascii").ljust(8)
    for start in range(0, len(header), _CARD):
        if header[start:start + 8] == name:
            return header[:start] + image + header[start + _CARD:]
    raise KeyError(key)  # internal: the header was built without checksum_cards()


class StreamedChecksums:
    """CHECKSUM and DATASUM of the HDUs of a file written in pieces.

    :meth:`add_hdu` registers a header (built with :func:`checksum_cards`) at its file offset,
    :meth:`add_data` sums each data block as it is written (offset relative to the data unit),
    :meth:`finish` rewrites every header in place with its two values.
    """

    def __init__(self):
        self._hdus = []                       # [header offset, header bytes, datasum]

    def add_hdu(self, offset, header):
        """Register the header written at ``offset``; returns its HDU number."""
        self._hdus.append([int(offset), bytes(header), 0])
        return len(self._hdus) - 1

    def add_data(self, hdu, data, offset):
        """Sum ``data`` written ``offset`` bytes after the start of HDU ``hdu``'s data unit."""
        entry = self._hdus[hdu]
        entry[2] = ones_add(entry[2], ones_sum(data, int(offset) % 4))

    def finish(self, pwrite):
        """Write every registered header again, its DATASUM and CHECKSUM set (``pwrite(bytes, offset)``)."""
        for offset, header, datasum in self._hdus:
            header = _replace_card(header, "DATASUM", _card("DATASUM", str(datasum), "data unit checksum"))
            header = _replace_card(header, "CHECKSUM", _card("CHECKSUM", ZERO_CHECKSUM, "HDU checksum"))
            total = ones_add(ones_sum(header), datasum)
            header = _replace_card(header, "CHECKSUM", _card("CHECKSUM", encode_checksum(total), "HDU checksum"))
            pwrite(header, offset)


def verify_datasums(path, hdul, error, chunk=1 << 26):
    """Check the DATASUM and CHECKSUM of every HDU of ``hdul`` (opened from ``path``) that carries
    them, reading its data from the file in blocks of ``chunk`` bytes (no copy of the data in
    memory): a data sum other than DATASUM, or an HDU (header and data) whose sum is not −0 (a
    header byte changed), raises ``error`` naming the extension.  So does a file with bytes after
    its last complete HDU (a file cut inside a header: astropy drops that HDU with a warning)."""
    size = os.path.getsize(path)
    if len(hdul):
        last = hdul.fileinfo(len(hdul) - 1)
        end = last["datLoc"] + int(last["datSpan"])
        if end < size:
            name = hdul[-1].name or f"HDU {len(hdul) - 1}"
            raise error(f"{path}: truncated or damaged FITS file: it has {size} bytes but its last complete HDU "
                        f"({name}) ends at byte {end}")
    with open(path, "rb") as fh:
        for index, hdu in enumerate(hdul):
            expected = hdu.header.get("DATASUM")
            checksum = hdu.header.get("CHECKSUM")
            if expected is None and checksum is None:
                continue
            info = hdul.fileinfo(index)
            if info["datLoc"] + int(info["datSpan"]) > size:
                return                    # a truncated file (FITS pads every HDU): the readers name it as such
            fh.seek(info["datLoc"])
            total, left = 0, int(info["datSpan"])
            while left > 0:
                block = fh.read(min(chunk, left))
                if not block:
                    break
                total = ones_add(total, ones_sum(block))
                left -= len(block)
            name = hdu.name or f"HDU {index}"
            if expected is not None and (left > 0 or str(total) != str(expected).strip()):
                raise error(f"{path}: checksum mismatch in extension {name} (DATASUM {expected}, data sum "
                            f"{total}): the file is corrupt")
            if checksum is not None:
                fh.seek(info["hdrLoc"])
                header = fh.read(info["datLoc"] - info["hdrLoc"])
                if ones_add(ones_sum(header), total) not in (0, 0xFFFFFFFF):     # −0: the HDU sums to zero
                    raise error(f"{path}: checksum mismatch in the header of extension {name} (CHECKSUM "
                                f"{str(checksum).strip()}): the file is corrupt")
