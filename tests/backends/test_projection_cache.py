"""Projection tables cached on disk (issue 9: peak memory of a full-detector ramp).

* A cache hit gives the tables and the detector image of a fresh build, bit for bit (NumPy
  and OpenCL builders), read back memory-mapped; the mapper then holds nothing in memory.
* The key is the content of what determines the tables: mapper geometry, slices, λ grid,
  oversampling, truncation, storage dtype, backend.
* A corrupt, truncated or half-written entry is detected (size, SHA-256, manifest), reported
  once and rebuilt; two writers of one key are safe; an unusable cache directory falls back
  to memory with one warning.
"""
import json
import os
import subprocess
import sys
import threading
import warnings

import numpy as np
import pytest

from slicersim.backends import projection
from slicersim.errors import ParameterError
from slicersim.instrument.mapper import SlicerMapper
from slicersim.io import table_cache
from slicersim.io.table_cache import ArrayCache, Chunks, TableCacheWarning

from conftest import have_opencl

BACKENDS = ["numpy", pytest.param("opencl", marks=pytest.mark.needs_opencl)]

SLICES = (20, 21, 22, 23)
NCOL = 6
EDGES = np.linspace(5200.0, 5800.0, 13)          # 12 bins
LBDA = 0.5 * (EDGES[1:] + EDGES[:-1])


@pytest.fixture(autouse=True)
def cache_dir(tmp_path, monkeypatch):
    """Every test has its own cache root (never the user's ~/.cache) and a fresh checksum memo."""
    root = tmp_path / "cache"
    monkeypatch.setenv("SLICERSIM_CACHE", str(root))
    table_cache._VERIFIED.clear()
    yield root / "projection"
    table_cache._VERIFIED.clear()


def _cube(seed=1):
    rng = np.random.default_rng(seed)
    return rng.uniform(0.5, 2.0, (LBDA.size, len(SLICES), NCOL))


def _image(mapper, backend, **kwargs):
    return mapper.project_cube(_cube(), LBDA, EDGES, SLICES, backend=backend, **kwargs)


def _entries(directory):
    return sorted(p.name for p in directory.iterdir() if not p.name.startswith(".")) if directory.exists() else []


def _count_builds(monkeypatch):
    calls = []
    real = projection.build_tables

    def counting(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)
    monkeypatch.setattr("slicersim.instrument.mapper_projection.build_tables", counting)
    return calls


# --------------------------------------------------------------------------- hit = build
@pytest.mark.parametrize("backend", BACKENDS)
def test_hit_gives_the_built_tables_and_image(cache_dir, monkeypatch, backend):
    builds = _count_builds(monkeypatch)
    reference = _image(SlicerMapper.default(table_cache=None), backend)        # today's path
    assert len(builds) == 1
    cold_mapper = SlicerMapper.default()
    cold = _image(cold_mapper, backend)                                         # miss: build, store
    assert len(builds) == 2 and len(_entries(cache_dir)) == 1
    assert not cold_mapper._cache                       # nothing held in memory by the mapper
    warm = _image(SlicerMapper.default(), backend)                              # hit (new mapper)
    assert len(builds) == 2
    assert np.array_equal(cold, reference) and np.array_equal(warm, reference)
    assert reference.sum() > 0

    # the tables themselves, field by field
    box = SlicerMapper.default().cell_boxes(SLICES, NCOL, EDGES)
    built = projection.build_tables(box, (len(SLICES), EDGES.size - 1, NCOL), backend=backend).host()
    loaded = SlicerMapper.default().projection_tables(SLICES, NCOL, EDGES, backend=backend)
    assert isinstance(loaded.pool, np.memmap) and not loaded.pool.flags.writeable
    for name in ("meta", "offset", "pool", "scale"):
        assert np.array_equal(getattr(loaded, name), getattr(built, name)), name
        assert getattr(loaded, name).dtype == getattr(built, name).dtype
    assert (loaded.grid, loaded.oversample, loaded.vw, loaded.row_range, loaded.pool_size) == \
        (built.grid, built.oversample, built.vw, built.row_range, built.pool_size)
    assert len(loaded.phases) == len(built.phases)
    for (f1, l1), (f2, l2) in zip(loaded.phases, built.phases):
        assert np.array_equal(f1, f2) and np.array_equal(l1, l2)


def test_same_mapper_second_call_skips_the_boxes(monkeypatch):
    mapper = SlicerMapper.default()
    first = _image(mapper, "numpy")
    monkeypatch.setattr(SlicerMapper, "cell_boxes", lambda *a, **k: pytest.fail("boxes recomputed on a hit"))
    assert np.array_equal(_image(mapper, "numpy"), first)
    assert np.array_equal(_image(SlicerMapper.default(), "numpy"), first)     # key from geometry only


# --------------------------------------------------------------------------- keys
def test_key_changes_with_what_determines_the_tables():
    m = SlicerMapper.default()
    grid = (len(SLICES), EDGES.size - 1, NCOL)

    def key(mapper=m, slices=SLICES, ncol=NCOL, edges=EDGES, oversample=(1, 1), **kw):
        g = (len(slices), (len(edges) - 1) * oversample[0], ncol * oversample[1])
        return projection.table_key(mapper._geometry(slices, ncol, edges), g, oversample,
                                    detector_shape=mapper.detector_shape, backend="numpy", **kw)

    base = key()
    assert key(SlicerMapper.default()) == base                     # same content, other object
    values = m.values.copy()
    values[3, 1, 2, 0] += 1e-9                                      # one node moved by 1e-9 px
    moved = SlicerMapper(m.slice_ids, m.fieldpos_nodes, m.lbda_nodes, values)
    variants = [key(moved), key(slices=(20, 21, 22, 24)), key(ncol=NCOL + 1),
                key(edges=EDGES * (1 + 1e-12)), key(oversample=(2, 1)), key(truncate=5.0),
                key(weights_dtype=np.float64), key(block=4),
                key(SlicerMapper(m.slice_ids, m.fieldpos_nodes, m.lbda_nodes, m.values, interpolation="triangles")),
                key(SlicerMapper(m.slice_ids, m.fieldpos_nodes, m.lbda_nodes, m.values, detector_shape=(4096, 4097)))]
    assert len(set(variants + [base])) == len(variants) + 1
    # the box array itself is a valid geometry too, and the backend is part of the key
    box = m.cell_boxes(SLICES, NCOL, EDGES)
    assert projection.table_key(box, grid, backend="numpy") != base
    if have_opencl():
        assert projection.table_key(box, grid, backend="opencl") != projection.table_key(box, grid, backend="numpy")


def test_moved_mapper_rebuilds(cache_dir, monkeypatch):
    builds = _count_builds(monkeypatch)
    m = SlicerMapper.default()
    _image(m, "numpy")
    values = m.values.copy()
    values[..., 0] += 0.25                                          # the spectra move by 1/4 px
    moved = SlicerMapper(m.slice_ids, m.fieldpos_nodes, m.lbda_nodes, values)
    img = _image(moved, "numpy")
    assert len(builds) == 2 and len(_entries(cache_dir)) == 2
    assert np.array_equal(img, _image(SlicerMapper(m.slice_ids, m.fieldpos_nodes, m.lbda_nodes, values,
                                                   table_cache=None), "numpy"))


# --------------------------------------------------------------------------- damage
def _pool_file(cache_dir):
    (entry,) = _entries(cache_dir)
    return cache_dir / entry / "pool.npy"


@pytest.mark.parametrize("damage", ["flip", "truncate", "manifest", "missing"])
def test_damaged_entry_is_detected_and_rebuilt(cache_dir, monkeypatch, damage):
    reference = _image(SlicerMapper.default(), "numpy")
    path = _pool_file(cache_dir)
    if damage == "flip":                    # same size: only the checksum can tell
        with open(path, "r+b") as fh:
            fh.seek(os.path.getsize(path) // 2)
            byte = fh.read(1)
            fh.seek(-1, 1)
            fh.write(bytes([byte[0] ^ 0x40]))
    elif damage == "truncate":
        os.truncate(path, os.path.getsize(path) - 100)
    elif damage == "manifest":
        (path.parent / "manifest.json").write_text("{not json")
    else:
        path.unlink()
    table_cache._VERIFIED.clear()           # as a new process would
    builds = _count_builds(monkeypatch)
    with pytest.warns(TableCacheWarning, match="damaged"):
        img = _image(SlicerMapper.default(), "numpy")
    assert len(builds) == 1 and np.array_equal(img, reference)
    table_cache._VERIFIED.clear()
    with warnings.catch_warnings():
        warnings.simplefilter("error")      # the rebuilt entry is sound
        assert np.array_equal(_image(SlicerMapper.default(), "numpy"), reference)
    assert len(builds) == 1


def test_entry_of_another_key_is_refused(cache_dir):
    _image(SlicerMapper.default(), "numpy")
    (entry,) = _entries(cache_dir)
    manifest = json.loads((cache_dir / entry / "manifest.json").read_text())
    manifest["key"] = "0" * 64
    (cache_dir / entry / "manifest.json").write_text(json.dumps(manifest))
    with pytest.warns(TableCacheWarning, match="damaged"):
        assert ArrayCache(cache_dir).load(entry) is None
    assert _entries(cache_dir) == []


# --------------------------------------------------------------------------- writers
def test_two_writers_of_one_key(tmp_path, monkeypatch):
    """Both writers inside their write at once: one rename wins, the other keeps the winner's
    entry; both report success and the entry reads back sound."""
    cache = ArrayCache(tmp_path / "c")
    barrier = threading.Barrier(2, timeout=30)
    real = table_cache._write_npy

    def slow(path, arr):
        out = real(path, arr)
        if path.name == "a.npy":
            barrier.wait()
        return out
    monkeypatch.setattr(table_cache, "_write_npy", slow)
    data = {"a": np.arange(1000.0), "b": np.arange(7, dtype=np.int32)}
    results = []
    threads = [threading.Thread(target=lambda: results.append(cache.store("k1", data, {"n": 1})))
               for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert results == [True, True]
    assert sorted(os.listdir(tmp_path / "c")) == ["k1"]            # no temporaries left
    table_cache._VERIFIED.clear()
    arrays, meta = cache.load("k1")
    assert meta == {"n": 1} and np.array_equal(arrays["a"], data["a"]) and np.array_equal(arrays["b"], data["b"])


_WRITER = """
import sys, numpy as np
from slicersim.instrument.mapper import SlicerMapper
edges = np.linspace(5200.0, 5800.0, 13)
cube = np.random.default_rng(1).uniform(0.5, 2.0, (12, 4, 6))
img = SlicerMapper.default().project_cube(cube, 0.5 * (edges[1:] + edges[:-1]), edges, (20, 21, 22, 23),
                                          backend="numpy")
np.save(sys.argv[1], img)
"""


@pytest.mark.slow
def test_two_processes_build_the_same_tables(cache_dir, tmp_path):
    env = dict(os.environ, SLICERSIM_DEVICE="none")
    outs = [tmp_path / f"img{i}.npy" for i in range(2)]
    procs = [subprocess.Popen([sys.executable, "-c", _WRITER, str(o)], env=env) for o in outs]
    assert [p.wait(timeout=300) for p in procs] == [0, 0]
    reference = _image(SlicerMapper.default(table_cache=None), "numpy")
    for o in outs:
        assert np.array_equal(np.load(o), reference)
    assert len(_entries(cache_dir)) == 1
    assert not [n for n in os.listdir(cache_dir) if n.startswith(".")]


# --------------------------------------------------------------------------- unusable directory
def test_unwritable_directory_falls_back_to_memory_with_one_warning(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    monkeypatch.setenv("SLICERSIM_CACHE", str(blocker / "cache"))     # mkdir fails (even as root)
    reference = _image(SlicerMapper.default(table_cache=None), "numpy")
    mapper = SlicerMapper.default()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        first = _image(mapper, "numpy")
        other = mapper.project_cube(_cube()[:6], LBDA[:6], EDGES[:7], SLICES, backend="numpy")
    mine = [w for w in caught if issubclass(w.category, TableCacheWarning)]
    assert len(mine) == 1 and "not usable" in str(mine[0].message)
    assert np.array_equal(first, reference) and other.sum() > 0
    assert len(mapper._cache) == 2                  # kept in memory instead...
    mapper.release_tables()
    assert not mapper._cache                        # ...and released before a ramp


def test_cache_off_and_explicit_directory(tmp_path, monkeypatch):
    monkeypatch.setenv("SLICERSIM_CACHE", "off")
    assert projection.default_table_cache() is None
    mapper = SlicerMapper.default()
    _image(mapper, "numpy")
    assert len(mapper._cache) == 1                  # today's behaviour: in memory
    explicit = SlicerMapper.default(table_cache=tmp_path / "mine")
    _image(explicit, "numpy")
    assert len(_entries(tmp_path / "mine")) == 1 and not explicit._cache
    with pytest.raises(ParameterError, match="table cache must be"):
        SlicerMapper.default(table_cache=3)


# --------------------------------------------------------------------------- the store itself
def test_array_cache_round_trip_chunks_and_alignment(tmp_path):
    cache = ArrayCache(tmp_path)
    big = np.arange(10_000, dtype=np.float32)
    pieces = Chunks(np.float32, (10_000,), (big[i:i + 3000] for i in range(0, 10_000, 3000)))
    assert cache.store("abc", {"streamed": pieces, "plain": big.reshape(100, 100), "empty": np.zeros(0)},
                       {"x": [1, 2]})
    table_cache._VERIFIED.clear()
    arrays, meta = cache.load("abc")
    assert meta == {"x": [1, 2]}
    assert np.array_equal(arrays["streamed"], big) and arrays["plain"].shape == (100, 100)
    assert arrays["empty"].size == 0
    assert isinstance(arrays["plain"], np.memmap) and arrays["plain"].offset % 4096 == 0
    assert cache.load("missing") is None
    with pytest.raises(ValueError):
        cache.path("../etc")
    with pytest.raises(ValueError):             # a stream shorter than its declared shape
        cache.store("short", {"a": Chunks(np.float64, (10,), [np.zeros(3)])})
    assert cache.load("short") is None and _entries(tmp_path) == ["abc"]


def test_array_cache_evicts_least_recently_used(tmp_path):
    cache = ArrayCache(tmp_path, max_bytes=3 * 80_000 + 3 * 12_000)
    data = {"a": np.zeros(10_000)}                   # 80 kB (+ header, manifest)
    for key in ("k1", "k2", "k3"):
        assert cache.store(key, data)
    os.utime(tmp_path / "k1" / "manifest.json", (1, 1))
    os.utime(tmp_path / "k2" / "manifest.json", (2, 2))
    cache.load("k1")                                 # used now: k2 is the oldest
    assert cache.store("k4", data)
    assert _entries(tmp_path) == ["k1", "k3", "k4"]
    assert cache.size() <= cache.max_bytes


def test_stale_temporaries_of_dead_writers_are_removed(tmp_path):
    cache = ArrayCache(tmp_path)
    cache.store("k1", {"a": np.zeros(3)})
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True, check=True).stdout.strip()
    stale = tmp_path / f".k2.tmp-{dead}-{table_cache._host_tag()}abcd1234"
    stale.mkdir()
    (stale / "a.npy").write_bytes(b"half")
    cache.store("k3", {"a": np.zeros(3)})
    assert not stale.exists() and _entries(tmp_path) == ["k1", "k3"]
