"""Process-wide memoisation of pure quantities, bounded in bytes (no slicersim imports: every
layer may use it).

A value computed from explicit inputs only (a PSF cube from its wavelength grid, field,
telescope and options; a curve from its file) can be reused by every later target of a
process: a Monte Carlo loop builds a new model per target, so a cache on the model object
would never hit.  Such caches are keyed by the *content* of every input (:func:`content_key`:
arrays by their bytes, floats exactly), never by object identity, so a changed input can
never return a stale value, and an equal input built anew still hits.

* :class:`ByteLRU` — least-recently-used mapping bounded in bytes, thread-safe;
* :func:`content_key` — hashable key of nested arrays / numbers / strings / tuples / dicts;
* :func:`read_only` — a read-only view (what a cache returns: callers cannot corrupt it);
* :func:`clear_caches` — empty every registered cache (:func:`cache_info` describes them).
"""
from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict

import numpy as np

from slicersim import validation

__all__ = ["ByteLRU", "content_key", "read_only", "clear_caches", "cache_info"]

_REGISTRY: dict = {}


class ByteLRU:
    """Least-recently-used cache holding at most ``max_bytes`` bytes of values.

    ``put(key, value, nbytes)`` stores a value of ``nbytes`` bytes, evicting the least
    recently used entries first; a value larger than the bound is not stored.  ``get(key)``
    returns the value or None (and marks it recently used).  Registered under ``name``
    (:func:`clear_caches`, :func:`cache_info`).
    """

    def __init__(self, name, max_bytes):
        self.name = str(name)
        self._lock = threading.RLock()
        self._items: OrderedDict = OrderedDict()      # key -> (value, nbytes)
        self._nbytes = 0
        self.hits = self.misses = self.evictions = 0
        self.max_bytes = max_bytes
        _REGISTRY[self.name] = self

    @property
    def max_bytes(self):
        return self._max_bytes

    @max_bytes.setter
    def max_bytes(self, value):
        value = validation.integer(f"max_bytes ({self.name} cache)", value, low=0)
        with self._lock:
            self._max_bytes = value
            self._evict(0)

    @property
    def nbytes(self):
        """Bytes held now (≤ ``max_bytes``)."""
        return self._nbytes

    def __len__(self):
        return len(self._items)

    def __contains__(self, key):
        return key in self._items

    def get(self, key):
        with self._lock:
            item = self._items.get(key)
            if item is None:
                self.misses += 1
                return None
            self._items.move_to_end(key)
            self.hits += 1
            return item[0]

    def put(self, key, value, nbytes):
        """Store ``value`` (``nbytes`` bytes); returns True when it was stored."""
        nbytes = int(nbytes)
        with self._lock:
            self.discard(key)
            if nbytes > self._max_bytes:
                return False
            self._evict(nbytes)
            self._items[key] = (value, nbytes)
            self._nbytes += nbytes
            return True

    def discard(self, key):
        with self._lock:
            item = self._items.pop(key, None)
            if item is not None:
                self._nbytes -= item[1]

    def _evict(self, room):
        while self._items and self._nbytes + room > self._max_bytes:
            _, (_, nbytes) = self._items.popitem(last=False)
            self._nbytes -= nbytes
            self.evictions += 1

    def clear(self):
        """Drop every entry and reset the counters."""
        with self._lock:
            self._items.clear()
            self._nbytes = 0
            self.hits = self.misses = self.evictions = 0

    def info(self):
        """{"entries", "nbytes", "max_bytes", "hits", "misses", "evictions"}."""
        with self._lock:
            return {"entries": len(self._items), "nbytes": self._nbytes, "max_bytes": self._max_bytes,
                    "hits": self.hits, "misses": self.misses, "evictions": self.evictions}


def clear_caches():
    """Empty every registered :class:`ByteLRU` (PSF blocks, curve files, ...)."""
    for cache in list(_REGISTRY.values()):
        cache.clear()


def cache_info():
    """{name: ByteLRU.info()} of every registered cache."""
    return {name: cache.info() for name, cache in _REGISTRY.items()}


def _array_key(a):
    a = np.ascontiguousarray(a)
    if a.dtype.hasobject:
        raise TypeError("content_key cannot hash object arrays")  # internal: the caller keyed an unkeyable input
    digest = hashlib.blake2b(a.view(np.uint8).reshape(-1) if a.size else b"", digest_size=20).hexdigest()
    return ("array", a.dtype.str, a.shape, digest)


def content_key(value):
    """Hashable key of ``value`` from its content: arrays by dtype, shape and bytes; floats
    exactly (``float.hex``: 0.1 and 0.1 + 1e-17 differ, −0.0 and 0.0 differ); ints, bools,
    strings and None by value; tuples, lists and dicts (sorted) recursively.  Any other object
    raises TypeError (identity is never a key)."""
    if value is None or isinstance(value, (bool, np.bool_)):
        return ("none",) if value is None else ("bool", bool(value))
    if isinstance(value, (int, np.integer)):
        return ("int", int(value))
    if isinstance(value, (float, np.floating)):
        return ("float", float(value).hex())
    if isinstance(value, str):
        return ("str", value)
    if isinstance(value, bytes):
        return ("bytes", hashlib.blake2b(value, digest_size=20).hexdigest())
    if isinstance(value, np.ndarray):
        return _array_key(value)
    if isinstance(value, (tuple, list)):
        return ("seq", tuple(content_key(v) for v in value))
    if isinstance(value, dict):
        return ("dict", tuple(sorted((str(k), content_key(v)) for k, v in value.items())))
    raise TypeError(f"content_key: cannot key a {type(value).__name__} by content")  # internal: protocol of content_key


def read_only(array):
    """A read-only view of ``array`` (its base made read-only too, so the view cannot be made
    writeable again); what a cache hands out."""
    array.flags.writeable = False
    view = array.view()
    view.flags.writeable = False
    return view
