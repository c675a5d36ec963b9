"""Memory allocation of the command-line process.

On Linux/glibc, arrays above 32 MiB (a 4096² float64 image is 128 MiB) are each mapped afresh and
returned to the system when freed, so every whole-detector temporary touches new pages: on the
2-core VM first touches cost ~2 ms per MiB, 3–6 s of system time in one ``reduce --spectra``.
:func:`keep_freed_memory` tells glibc to serve them from its heap and keep freed memory (up to
:data:`KEEP_BYTES` above the top of the heap) for the next one: the process's peak memory is
unchanged; memory freed stays with the process until it exits.

NumPy asks the kernel for transparent huge pages on every array of 4 MiB or more
(``madvise(MADV_HUGEPAGE)``); where the kernel's ``defrag`` setting is ``madvise`` (the common
default), each such first touch may stall in direct compaction.  On the 2-core VM that was 3.5–4 s
of the 5.5–6.5 s of system time of one ``reduce --spectra`` and 1 s of a ``ramp`` (user time
unchanged): :func:`no_huge_page_stalls` turns NumPy's request off, unless the user chose with
``NUMPY_MADVISE_HUGEPAGE``.

Only the ``slicersim`` command does both (a short-lived process); the library leaves the allocator
as it finds it.
"""
from __future__ import annotations

import ctypes
import os
import platform

#: freed memory glibc keeps at the top of the heap instead of returning it [bytes]
KEEP_BYTES = 1 << 30

_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4           # mallopt parameters (malloc.h)


def keep_freed_memory() -> bool:
    """Set glibc's ``M_MMAP_MAX`` to 0 and ``M_TRIM_THRESHOLD`` to :data:`KEEP_BYTES`; False (nothing
    done) on another C library or where ``mallopt`` is not found or refuses."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, KEEP_BYTES))


def no_huge_page_stalls() -> bool:
    """Turn off NumPy's transparent-huge-page request for large arrays; False (nothing done) where the
    environment sets ``NUMPY_MADVISE_HUGEPAGE`` (the user's choice stands) or this NumPy has no such
    switch."""
    if "NUMPY_MADVISE_HUGEPAGE" in os.environ:
        return False
    try:
        from numpy._core.multiarray import _set_madvise_hugepage
    except ImportError:
        try:
            from numpy.core.multiarray import _set_madvise_hugepage
        except ImportError:
            return False
    _set_madvise_hugepage(False)
    return True
