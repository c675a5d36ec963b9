"""Fast Monte Carlo (issue #8, item 6): PSF blocks cached across targets, noise at any vector width.

* A cached PSF block is the uncached one bit for bit (host arrays, device blocks, whole cubes).
* The cache key is the content of every input: a new field, a telescope ``update``, another
  wavelength grid, source position, oversampling, guiding... each computes a new block (and
  equals an uncached computation of the new state); the same inputs built anew hit.
* The cache stays within its byte bound (LRU eviction) and hands out read-only arrays.
* Noisy cubes are identical for every vector width, work-group size, chunking and buffer
  path (in place / scratch), and to the NumPy twin.
* ``limit_cpu_threads`` and the curve-file cache.
"""
import os
import subprocess
import sys

import numpy as np
import pytest

import slicersim
from slicersim.backends import noise as cn
from slicersim.backends import opencl, psf_cache
from slicersim.backends import psf as bpsf
from slicersim.errors import ParameterError, SlicersimError
from slicersim.memo import ByteLRU, cache_info, clear_caches, content_key, read_only
from slicersim.products.cube import psf_block
from slicersim.products.psf_profiles import get_psf_profile

from conftest import have_opencl

BACKENDS = ["numpy", pytest.param("opencl", marks=pytest.mark.needs_opencl)]
NB = 24                     # wavelength bins of the test blocks (the blue end: the hardest PSF)


@pytest.fixture(autouse=True)
def fresh_cache():
    """Every test starts from an empty PSF cache with the default bound, and leaves it so."""
    psf_cache.clear_psf_cache()
    limit = psf_cache.PSF_CACHE.max_bytes
    yield
    psf_cache.set_psf_cache_limit(limit)
    psf_cache.clear_psf_cache()


def _uncached(func, *args, **kwargs):
    """``func(*args)`` with the PSF cache bypassed (backends.psf called directly)."""
    info = psf_cache.psf_cache_info()
    with psf_cache.bypass():
        out = func(*args, **kwargs)
    assert psf_cache.psf_cache_info() == info                  # neither looked up nor stored
    return out


def _sn(**kwargs):
    return slicersim.LazuliSupernova(redshift=kwargs.pop("redshift", 1.0), **kwargs)


def _block(sim, backend, lo=0, hi=NB, **kwargs):
    return psf_block(sim, "airy", lo, hi, backend=backend, **kwargs)


# --------------------------------------------------------------------------- bit identity
@pytest.mark.parametrize("backend", BACKENDS)
def test_cached_block_equals_uncached_bit_for_bit(backend):
    sim = _sn().simulation
    ref = _uncached(_block, sim, backend)
    assert psf_cache.psf_cache_info()["entries"] == 0            # really uncached
    first = _block(sim, backend)                                   # miss: computed and stored
    again = _block(_sn(redshift=0.4).simulation, backend)         # another target: a hit
    info = psf_cache.psf_cache_info()
    assert (info["misses"], info["hits"], info["entries"]) == (1, 1, 1)
    assert info["nbytes"] == ref.nbytes
    np.testing.assert_array_equal(first, ref)
    np.testing.assert_array_equal(again, ref)
    assert ref.shape == (NB, 58, 116) and 0.5 < ref[-1].sum() < 1.0  # real PSF fractions
    # the same block computed directly by backends.psf, with the arguments the profile uses
    tel, spec = sim.telescope, sim.spectrograph
    common = dict(spatial_scale=spec.spatial_scale, guiding_sigma=tel.guiding_sigma,
                  instrumental_sigma=sim.instrumental_sigma, diameter=tel.diameter_ext)
    direct = bpsf.psf_cube(sim.lbda[:NB], spec.shape, sim.position, profile="airy",
                           sigma_ref_arcsec=tel.psf_sigma_ref, obscuration=tel.obscuration,
                           oversampling=bpsf.auto_oversampling(sim.lbda, **common), backend=backend, **common)
    np.testing.assert_array_equal(direct, ref)


@pytest.mark.needs_opencl
def test_cached_device_block_equals_uncached():
    sim = _sn().simulation
    profile = get_psf_profile("airy")
    ref = _uncached(profile.fused, sim, 0, NB, "opencl").to_host()
    first, second = profile.fused(sim, 0, NB, "opencl"), profile.fused(_sn(redshift=0.7).simulation, 0, NB, "opencl")
    assert isinstance(first, bpsf.DevicePSF) and second.buffer is first.buffer     # shared, not recomputed
    np.testing.assert_array_equal(first.to_host(), ref)
    np.testing.assert_array_equal(second.to_host(), ref)
    # a new OpenCL context cannot use buffers of the old one: recomputed, same values
    opencl.reset()
    third = profile.fused(sim, 0, NB, "opencl")
    assert third.buffer is not first.buffer
    np.testing.assert_array_equal(third.to_host(), ref)


@pytest.mark.slow
@pytest.mark.parametrize("backend", BACKENDS)
def test_noisy_airy_cubes_of_new_targets_identical_with_and_without_cache(backend):
    """The Monte Carlo loop: a new target per draw; every cube equals its uncached twin."""
    def loop():
        cubes = []
        for i, z in enumerate((0.5, 1.2)):
            sn = _sn(redshift=z)
            sn.change_detector(nmd=(61, 8, 0), nramps=3)
            cubes.append(tuple(sn.simulation.get_cube(seed=i + 1, psf_profile="airy", backend=backend)))
        return cubes
    ref = _uncached(loop)
    got = loop()
    assert psf_cache.psf_cache_info()["hits"] >= 1
    for a, b in zip(ref, got):
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)
    signal, variance, noisy = got[1]
    assert np.nanmax(signal) > 0 and np.any(noisy != signal)


# --------------------------------------------------------------------------- invalidation
def _changed(make, options):
    """(block of the changed state, uncached block of it, misses it caused)."""
    before = psf_cache.psf_cache_info()["misses"]
    sim, kwargs = make()
    kwargs["options"] = {**(options or {}), **kwargs.get("options", {})} or None
    got = _block(sim, "auto", **kwargs)
    misses = psf_cache.psf_cache_info()["misses"] - before
    return got, _uncached(_block, sim, "auto", **kwargs), misses


def _updated(**params):
    def make():
        sim = _sn().simulation
        sim.update(**params)
        return sim, {}
    return make


def _target(**kwargs):
    return lambda: (_sn(**kwargs).simulation, {})


CHANGES = {
    "wide field": _target(field="wide"),
    "telescope diameter (update)": _updated(diameter_ext=2.9),
    "central obscuration (update)": _updated(diameter_int=0.9),
    "guiding jitter (update)": _updated(guiding_sigma=0.011),
    "spatial scale (update)": _updated(spatial_scale=0.041),
    "wavelength grid (update)": _updated(dispersion_scale=1.1),
    "dispersion (update)": _updated(dispersion_resolution=1.9),
    "source position": _target(position=(1.5, -0.5)),
    "oversampling": lambda: (_sn().simulation, {"options": {"oversampling": (5, 4)}}),
    "grid rule": lambda: (_sn().simulation, {"options": {"grid": "gauss"}}),
    "wavelength block": lambda: (_sn().simulation, {"lo": 1, "hi": NB + 1}),
}


@pytest.mark.slow
@pytest.mark.parametrize("options", [None, {"oversampling": (4, 3)}], ids=["auto-oversampling", "fixed-oversampling"])
@pytest.mark.parametrize("change", list(CHANGES))
def test_every_dependency_changes_the_key(change, options):
    """Each change alone must miss, also with a fixed oversampling (with "auto", most changes
    also move the oversampling, which would hide a missing key part)."""
    base = _block(_sn().simulation, "auto", options=options)
    got, ref, misses = _changed(CHANGES[change], options)
    assert misses == 1, f"{change}: served from the cache"
    np.testing.assert_array_equal(got, ref)                         # the new state's true PSF
    assert got.shape != base.shape or np.any(got != base), f"{change}: PSF did not change"
    # the original inputs, built anew, still hit and give the original block
    hits = psf_cache.psf_cache_info()["hits"]
    np.testing.assert_array_equal(_block(_sn(redshift=0.3).simulation, "auto", options=options), base)
    assert psf_cache.psf_cache_info()["hits"] == hits + 1


BASE_ARGS = dict(lbda=np.linspace(4000.0, 4300.0, 6), shape=(15, 24), position=(0.3, -0.2), profile="airy",
                 sigma_ref_arcsec=0.03, spatial_scale=0.04, guiding_sigma=0.01, instrumental_sigma=0.4,
                 diameter=3.0, obscuration=0.2, oversampling=(4, 3), grid="exact")
VARIANTS = dict(lbda=np.linspace(4000.0, 4300.0, 6) + [0, 0, 0, 1e-9, 0, 0], shape=(15, 22), position=(0.3, -0.25),
                profile="gaussian", sigma_ref_arcsec=0.031, spatial_scale=0.0401, guiding_sigma=0.0101,
                instrumental_sigma=0.41, diameter=3.01, obscuration=0.21, oversampling=(4, 4), grid="gauss")


class _Wavelengths:
    """An array-like without content key (``content_key`` refuses it)."""

    def __init__(self, values):
        self.values = values

    def __array__(self, dtype=None, copy=None):
        return np.asarray(self.values, dtype=dtype)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("name", list(VARIANTS))
def test_every_argument_of_psf_cube_is_in_the_key(name, backend):
    """Unit level: each argument of ``backends.psf.psf_cube`` alone changes the key (at the
    model level several of them move together, e.g. the diameter and σ_ref)."""
    base_args = {**BASE_ARGS, "profile": "gaussian"} if name == "sigma_ref_arcsec" else BASE_ARGS  # (Gaussian only)
    base = psf_cache.psf_cube(**base_args, backend=backend)
    np.testing.assert_array_equal(base, bpsf.psf_cube(**base_args, backend=backend))
    args = {**base_args, name: VARIANTS[name]}
    misses = psf_cache.psf_cache_info()["misses"]
    got = psf_cache.psf_cube(**args, backend=backend)
    assert psf_cache.psf_cache_info()["misses"] == misses + 1, f"{name}: served from the cache"
    direct = bpsf.psf_cube(**args, backend=backend)
    np.testing.assert_array_equal(got, direct)
    assert got.shape != base.shape or np.any(got != base)
    # an argument that cannot be keyed by content is computed, not cached
    entries = psf_cache.psf_cache_info()["entries"]
    odd = psf_cache.psf_cube(**{**args, "lbda": _Wavelengths(args["lbda"])}, backend=backend)
    np.testing.assert_array_equal(odd, direct)
    assert psf_cache.psf_cache_info()["entries"] == entries
    # the base arguments as new objects (a copied array, a list for the shape) still hit
    again = psf_cache.psf_cube(**{**base_args, "lbda": base_args["lbda"].copy(),
                                  "position": list(base_args["position"])}, backend=backend)
    assert psf_cache.psf_cache_info()["hits"] >= 1
    np.testing.assert_array_equal(again, base)


def test_update_back_and_forth_hits_the_original_and_same_wavelengths_share_blocks():
    sn = _sn()
    sim = sn.simulation
    base = _block(sim, "auto")
    sim.update(diameter_ext=2.0)
    assert np.any(_block(sim, "auto") != base)
    sim.update(diameter_ext=3.0)
    info = psf_cache.psf_cache_info()
    np.testing.assert_array_equal(_block(sim, "auto"), base)
    assert psf_cache.psf_cache_info()["hits"] == info["hits"] + 1
    # a grid whose first bins are the same wavelengths (same bluest bin: same oversampling) may share them
    sim.update(spectral_range=(4000.0, 16000.0))
    assert sim.lbda.size < 510
    misses = psf_cache.psf_cache_info()["misses"]
    np.testing.assert_array_equal(_block(sim, "auto"), base)
    assert psf_cache.psf_cache_info()["misses"] == misses


def test_key_covers_backend_and_options():
    sim = _sn().simulation
    _block(sim, "numpy")
    if have_opencl():
        _block(sim, "opencl")
        assert psf_cache.psf_cache_info()["entries"] == 2
    ref = _block(sim, "numpy", options={"grid": "reference"})
    assert psf_cache.psf_cache_info()["misses"] == (3 if have_opencl() else 2)
    np.testing.assert_array_equal(ref, _uncached(_block, sim, "numpy", options={"grid": "reference"}))


# --------------------------------------------------------------------------- bound and safety
def test_byte_bound_is_respected_with_lru_eviction():
    sim = _sn().simulation
    one = _block(sim, "auto", 0, 8).nbytes
    psf_cache.set_psf_cache_limit(int(2.5 * one))
    blocks = [np.array(_block(sim, "auto", lo, lo + 8)) for lo in (0, 8, 16, 24)]
    info = psf_cache.psf_cache_info()
    assert info["nbytes"] <= info["max_bytes"] == int(2.5 * one)
    assert info["entries"] == 2 and info["evictions"] == 2
    np.testing.assert_array_equal(_block(sim, "auto", 24, 32), blocks[3])        # most recent: a hit
    misses = psf_cache.psf_cache_info()["misses"]
    np.testing.assert_array_equal(_block(sim, "auto", 0, 8), blocks[0])          # evicted: recomputed
    assert psf_cache.psf_cache_info()["misses"] == misses + 1
    # a block larger than the whole bound is returned but not stored
    big = _block(sim, "auto", 0, 40)
    assert big.shape[0] == 40 and psf_cache.psf_cache_info()["nbytes"] <= int(2.5 * one)
    # shrinking the bound evicts at once; 0 disables the cache
    psf_cache.set_psf_cache_limit(one)
    assert psf_cache.psf_cache_info()["nbytes"] <= one
    psf_cache.set_psf_cache_limit(0)
    assert psf_cache.psf_cache_info()["entries"] == 0
    _block(sim, "auto", 0, 8)
    assert psf_cache.psf_cache_info()["entries"] == 0
    psf_cache.set_psf_cache_limit(psf_cache.PSF_CACHE_MAX_BYTES)
    assert psf_cache.PSF_CACHE_MAX_BYTES == 256 * 2**20


def test_returned_arrays_cannot_corrupt_the_cache():
    sim = _sn().simulation
    first = _block(sim, "auto")
    ref = first.copy()
    assert not first.flags.writeable
    with pytest.raises(ValueError):
        first[0, 0, 0] = 1.0
    with pytest.raises(ValueError):
        first.setflags(write=True)
    with pytest.raises(ValueError):
        np.multiply(first, 2.0, out=first)
    mine = np.array(first)                                          # a copy is the caller's own
    mine *= 0.0
    again = _block(sim, "auto")
    np.testing.assert_array_equal(again, ref)
    assert again is not first and not again.flags.writeable
    # the extraction weights (psf_cells) too
    p = get_psf_profile("airy").cells(sim, sim.aperture)
    assert not p.flags.writeable
    with pytest.raises(ValueError):
        p[...] = 0.0
    np.testing.assert_array_equal(get_psf_profile("airy").cells(sim, sim.aperture),
                                  _uncached(get_psf_profile("airy").cells, sim, sim.aperture))


def test_clear_caches_and_info():
    _block(_sn().simulation, "auto")
    assert cache_info()["psf"]["entries"] == 1
    clear_caches()
    assert cache_info()["psf"]["entries"] == 0 and cache_info()["curves"]["entries"] == 0


def test_content_key_and_lru():
    assert content_key(0.1) != content_key(np.nextafter(0.1, 1.0))
    assert content_key(0.0) != content_key(-0.0)
    assert content_key(np.float64(2.5)) == content_key(2.5)
    a = np.linspace(4000, 17000, 11)
    assert content_key(a) == content_key(a.copy())
    b = a.copy()
    b[5] = np.nextafter(b[5], 0)
    assert content_key(a) != content_key(b)
    assert content_key(a) != content_key(a.astype(np.float32)) != content_key(a.reshape(1, -1))
    assert content_key({"x": 1, "y": (2, None)}) == content_key({"y": (2, None), "x": 1})
    with pytest.raises(TypeError):
        content_key(object())
    lru = ByteLRU("test-lru", 100)
    try:
        assert lru.put("a", 1, 40) and lru.put("b", 2, 40)
        assert lru.get("a") == 1                      # "a" recently used: "b" goes first
        assert lru.put("c", 3, 40)
        assert "b" not in lru and lru.get("a") == 1 and lru.get("c") == 3 and lru.nbytes == 80
        assert not lru.put("d", 4, 101) and "d" not in lru
        with pytest.raises(ValueError):
            lru.max_bytes = -1
    finally:
        from slicersim import memo
        memo._REGISTRY.pop("test-lru", None)
    view = read_only(np.arange(3.0))
    with pytest.raises(ValueError):
        view[0] = 1.0


# --------------------------------------------------------------------------- noise
def _noise_inputs(n, seed=3):
    g = np.random.default_rng(seed)
    e = g.uniform(0, 1e4, n)
    v = g.uniform(0, 1e3, n)
    k = min(n, 5)          # variance 0, +inf, NaN expectation, NaN variance
    e[:k], v[:k] = [1.0, 2.0, np.nan, 4.0, 5.0][:k], [0.0, np.inf, 1.0, np.nan, 2.0][:k]
    return e, v


@pytest.mark.slow
@pytest.mark.needs_opencl
@pytest.mark.parametrize("n", [1, 7, 8 * 97 + 5, 20000])
def test_noisy_cube_identical_for_every_vector_width_and_path(n):
    e, v = _noise_inputs(n)
    ref = cn.noisy_cube(e, v, 2**63 + 11, backend="numpy", first_index=1234)
    assert ref[0] == 1.0 and np.count_nonzero(np.isnan(ref)) == min(max(n - 1, 0), 3)
    for vw in (1, 2, 4, 8, 16):
        for wg in (None, 3, 64):
            got = cn.noisy_cube(e, v, 2**63 + 11, backend="opencl", vector_width=vw, work_group=wg,
                                first_index=1234)
            np.testing.assert_array_equal(got, ref, err_msg=f"vector_width={vw}, work_group={wg}")
        # read-only inputs go through the scratch buffers; out= receives the draw in place
        ro_e, ro_v = read_only(e.copy()), read_only(v.copy())
        out = np.full(n, -1.0)
        assert cn.noisy_cube(ro_e, ro_v, 2**63 + 11, backend="opencl", vector_width=vw, first_index=1234,
                             max_bytes=24 * 300, out=out) is out
        np.testing.assert_array_equal(out, ref, err_msg=f"scratch path, vector_width={vw}")
    if n > 5:
        assert np.isfinite(ref[5:]).all() and np.all(ref[5:] != e[5:])


def test_noisy_cube_out_argument_is_checked():
    e, v = _noise_inputs(10)
    for bad in (np.empty(9), np.empty(10, np.float32), np.empty(20)[::2], read_only(np.empty(10))):
        with pytest.raises(ValueError, match="out must be"):
            cn.noisy_cube(e, v, 1, out=bad)
    with pytest.raises(ValueError, match="≥ 0"):
        cn.noisy_cube(e, np.where(np.arange(10) == 7, -1.0, v), 1)
    with pytest.raises(ValueError, match="≥ 0"):                     # a NaN does not hide a negative
        cn.noisy_cube(e, np.where(np.arange(10) == 0, np.nan, np.where(np.arange(10) == 9, -1.0, v)), 1)


@pytest.mark.slow
@pytest.mark.needs_opencl
def test_noisy_airy_cube_identical_for_every_vector_width_and_chunking(monkeypatch):
    """``get_cube`` draws the noise at the device's preferred width: the cube must not depend on
    it (nor on the λ chunking).  (The PSF kernels' own vector layout may move the expectation by
    an ulp, so only the noise draw's width is forced here.)"""
    sn = _sn(redshift=0.8)
    sn.change_detector(nmd=(16, 8, 0), nramps=2)
    sim = sn.simulation
    ref = sim.get_cube(seed=99, psf_profile="airy")
    assert cn.check_vector_width(None) == opencl.preferred_vector_width(16)    # the device's width
    real, used = cn.check_vector_width, []

    def forced(vector_width, *args, **kwargs):
        used.append(vw)
        return real(vw if vector_width is None else vector_width, *args, **kwargs)
    monkeypatch.setattr(cn, "check_vector_width", forced)
    for vw in (1, 2, 4, 8, 16):
        got = sim.get_cube(seed=99, psf_profile="airy", max_bytes=(40 if vw == 2 else 300) * 2**20,
                           progress=False)
        for a, b in zip(ref, got):
            np.testing.assert_array_equal(a, b, err_msg=f"vector width {vw}")
    assert sorted(set(used)) == [1, 2, 4, 8, 16] and used.count(2) > 1       # vw 2: several λ chunks
    monkeypatch.setattr(cn, "check_vector_width", real)
    signal, variance, noisy = ref
    np.testing.assert_array_equal(noisy, cn.noisy_cube(signal, variance, 99, backend="numpy"))
    s32, v32, n32 = sim.get_cube(seed=99, psf_profile="airy", dtype=np.float32)
    np.testing.assert_array_equal(n32, cn.noisy_cube(s32, v32, 99, backend="numpy").astype(np.float32))
    assert np.any(noisy != signal)


# --------------------------------------------------------------------------- threads, curves
def test_limit_cpu_threads_validates():
    for bad in (0, -1, 1.5, "2", True, None):
        with pytest.raises(ParameterError):
            opencl.limit_cpu_threads(bad)


_THREADS_CHILD = """
import os, sys
from slicersim.backends import opencl
from slicersim.errors import SlicersimError
assert opencl.limit_cpu_threads(1) == 1 and os.environ["POCL_MAX_PTHREAD_COUNT"] == "1"
dev = opencl.get_device()
if "pocl" not in (dev.platform.name + dev.platform.version).lower() or opencl.device_type(dev) != "CPU":
    print("NOT-POCL-CPU"); sys.exit(0)
assert int(dev.max_compute_units) == 1, dev.max_compute_units
assert opencl.limit_cpu_threads(1) == 1              # same setting: a no-op
try:
    opencl.limit_cpu_threads(2)
except SlicersimError as exc:
    assert "POCL_MAX_PTHREAD_COUNT" in str(exc) and "before any OpenCL use" in str(exc), exc
    print("OK")
else:
    print("NO-ERROR")
"""


@pytest.mark.needs_opencl
def test_limit_cpu_threads_before_and_after_the_context():
    env = {k: v for k, v in os.environ.items() if k != "POCL_MAX_PTHREAD_COUNT"}
    res = subprocess.run([sys.executable, "-c", _THREADS_CHILD], env=env, capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr
    if "NOT-POCL-CPU" in res.stdout:
        pytest.skip("the selected OpenCL device is not PoCL's CPU device")
    assert res.stdout.strip() == "OK", res.stdout + res.stderr


def test_curve_files_are_cached_by_content(tmp_path):
    from slicersim.io.curves import CURVE_CACHE, read_curve
    path = tmp_path / "t.csv"
    path.write_text("wavelength,t\n4000,0.5\n5000,0.6\n6000,0.7\n")
    lbda, cols = read_curve(str(path))
    np.testing.assert_array_equal(cols["t"], [0.5, 0.6, 0.7])
    cols["t"][:] = -1.0                                   # the caller's copy: the cache is unharmed
    lbda[:] = 0.0
    hits = CURVE_CACHE.hits
    lbda2, cols2 = read_curve(str(path))
    assert CURVE_CACHE.hits == hits + 1
    np.testing.assert_array_equal(cols2["t"], [0.5, 0.6, 0.7])
    np.testing.assert_array_equal(lbda2, [4000, 5000, 6000])
    path.write_text("wavelength,t\n4000,0.5\n5000,0.9\n6000,0.7\n")      # same path, new content
    np.testing.assert_array_equal(read_curve(str(path))[1]["t"], [0.5, 0.9, 0.7])
    path.write_text("wavelength,t\r\n4000,0.1\r\n5000,0.2\r\n")           # CRLF as open() reads it
    np.testing.assert_array_equal(read_curve(str(path))[1]["t"], [0.1, 0.2])


def test_cache_limits_are_checked_integers():
    from slicersim.backends.psf_cache import PSF_CACHE, set_psf_cache_limit
    from slicersim.errors import ParameterError
    from slicersim.io.table_cache import ArrayCache
    before = PSF_CACHE.max_bytes
    with pytest.raises(ParameterError, match=r"max_bytes \(.* cache\) must be an integer ≥ 0"):
        set_psf_cache_limit(-1)
    with pytest.raises(ParameterError, match=r"max_bytes \(.* cache\) must be an integer"):
        set_psf_cache_limit(1.5e3 + 0.5)
    assert PSF_CACHE.max_bytes == before                       # a failed change changes nothing
    with pytest.raises(ParameterError, match=r"max_bytes \(table cache\) must be an integer ≥ 0"):
        ArrayCache("/tmp/unused", max_bytes=-5)


@pytest.mark.needs_opencl
def test_cached_psf_cells_behaves_like_uncached_without_fp64(monkeypatch):
    """P5: the cache key resolved precision="double" even for the NumPy-only Gaussian psf_cells and
    raised where the uncached call computes."""
    from slicersim.backends import psf as P, psf_cache as pc
    monkeypatch.setattr(opencl, "device_supports_fp64", lambda: False)
    kw = dict(spatial_scale=0.04, guiding_sigma=0.01, instrumental_sigma=1.0, sigma_ref_arcsec=0.03,
              precision="double")
    args = (np.linspace(3700, 17000, 4), (3, 5), (0, 0), (np.array([0]), np.array([1])), "gaussian")
    raw = P.psf_cells(*args, **kw)
    np.testing.assert_array_equal(pc.psf_cells(*args, **kw), raw)
