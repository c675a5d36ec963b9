"""Correlated read noise (NGHXRG model): PSD, group averaging, chunking, twins, bad input."""
import numpy as np
import pytest
from scipy import signal

from slicersim.backends import opencl
from slicersim.backends.correlated_assembly import GroupInputs, assemble_numpy, assemble_opencl
from slicersim.backends.correlated_noise import CorrelatedNoise, spectral_coefficients_numpy, spectral_coefficients_opencl
from slicersim.errors import EffectsError
from slicersim.physics.correlated_noise import (CorrelatedNoiseParameters, ReadoutGeometry, group_mean_variance,
                                                model_psd)


def test_lazuli_dwell_time():
    """tframe 2.83 s over 32 outputs × (128 + 12) × (4096 + 1) pixel times: τ ≈ 4.93 µs, ≈ 203 kHz."""
    g = ReadoutGeometry.from_params(CorrelatedNoiseParameters(), (4096, 4096), 2.83)
    assert g.row_len == 140 and g.frame_len == 140 * 4097
    assert g.dwell == pytest.approx(2.83 / 573580, rel=1e-12)
    assert 4.9e-6 < g.dwell < 4.95e-6 and 2.02e5 < 1 / g.dwell < 2.03e5
    assert g.scan_index(np.array([0, 127, 128, 255])).tolist() == [0, 127, 127, 0]


def _output_stream(block, geom, o):
    """Time stream of output o from m = 1, d = 0 group blocks (nroh = nfoh = 0: no gaps)."""
    x = np.arange(o * geom.ncol, (o + 1) * geom.ncol)
    s = np.empty((block.shape[0], geom.ny, geom.row_len))
    s[:, :, geom.scan_index(x)] = block[:, :, x]
    return s.ravel()


@pytest.mark.slow
@pytest.mark.parametrize("method", ["exact", "multirate"])
def test_psd_matches_model(method):
    """Welch PSD of output 1's reconstructed stream (odd output: reversed scan) vs the model in
    12 bands over four decades (0.1 Hz – 1 kHz, f_N = 1.45 kHz, crossover ν_c = 11 Hz inside).
    48 ramps of 128 frames (6 min each), Welch segments of 2¹⁷ samples: the MC error of each band ratio (scatter over ramps) is
    ≤ 3 % (asserted); each band must be within 10 %."""
    p = CorrelatedNoiseParameters(n_outputs=2, nroh=0, nfoh=0, f_min=0.01, pedestal=0, picture_frame=0)
    ps = []
    for ramp in range(48):
        gen = CorrelatedNoise(p, (256, 64), (128, 1, 0), 2.83, 3, method=method)
        x = _output_stream(gen.block(ramp, 0, 256), gen.geometry, 1)
        f, pxx = signal.welch(x, fs=1 / gen.geometry.dwell, nperseg=2**17)
        ps.append(pxx)
    ps = np.array(ps)
    model = model_psd(f, p, gen.geometry)
    edges = np.geomspace(0.1, 1000, 13)
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (f >= lo) & (f < hi)
        r = ps[:, sel].mean(1) / model[sel].mean()
        err = r.std(ddof=1) / np.sqrt(r.size)
        assert err < 0.03, (lo, hi, err)
        assert abs(r.mean() - 1) < 0.10, (method, lo, hi, r.mean(), err)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["exact", "multirate"])
def test_group_mean_variance(method):
    """Mean square of the group-averaged noise (m = 4 and 8, defaults + dropped frames) vs
    group_mean_variance (Fejér-weighted model PSD + pedestal and picture frame /m).  The MC
    error σ is the scatter over 60 ramps (heavy-tailed: the slow 1/f and pedestal are common to
    many pixels); pass if within 4σ + 2 %.  The "group" approximation must fail it (it loses
    the frame-to-frame correlation)."""
    p = CorrelatedNoiseParameters(n_outputs=4)
    for nmd in [(6, 4, 1), (4, 8, 0)]:
        v = np.array([(CorrelatedNoise(p, (128, 64), nmd, 2.83, 11, method=method).block(r, 0, 128)
                       .astype(float) ** 2).mean() for r in range(60)])
        pred = group_mean_variance(nmd[1], p, ReadoutGeometry.from_params(p, (128, 64), 2.83))
        ratio, err = v.mean() / pred, v.std(ddof=1) / np.sqrt(v.size) / pred
        assert err < 0.06
        assert abs(ratio - 1) < 4 * err + 0.02, (nmd, ratio, err)
    v = np.array([(CorrelatedNoise(p, (128, 64), (4, 8, 0), 2.83, 11, method="group").block(r, 0, 128)
                   .astype(float) ** 2).mean() for r in range(20)])
    assert v.mean() / group_mean_variance(8, p, ReadoutGeometry.from_params(p, (128, 64), 2.83)) < 0.7


@pytest.mark.parametrize("method", ["exact", "multirate", "group", "white"])
def test_chunk_independent_and_deterministic(method):
    p = CorrelatedNoiseParameters(n_outputs=4)
    kw = dict(segment_rows=16, taper_rows=4) if method in ("multirate", "group") else {}
    gen = CorrelatedNoise(p, (96, 64), (3, 2, 1), 2.83, 5, method=method, **kw)
    full = gen.block(1, 0, 96)
    parts = np.concatenate([gen.block(1, y0, y1) for y0, y1 in ((0, 7), (7, 30), (30, 33), (33, 96))], axis=1)
    np.testing.assert_array_equal(full, parts)
    again = CorrelatedNoise(p, (96, 64), (3, 2, 1), 2.83, 5, method=method, **kw).block(1, 0, 96)
    np.testing.assert_array_equal(full, again)
    other = gen.block(2, 0, 96)
    assert full.dtype == np.float32 and full.shape == (3, 96, 64)
    assert not np.array_equal(full, other)
    seed2 = CorrelatedNoise(p, (96, 64), (3, 2, 1), 2.83, 6, method=method, **kw).block(1, 0, 96)
    assert not np.array_equal(full, seed2)


@pytest.mark.parametrize("method", ["multirate", "group"])
def test_segment_cache_changes_nothing(method):
    """Segments cached between row blocks (any order, any cache size, ramps interleaved) give the
    values of a generator that caches nothing, and the cache keeps only what later blocks need."""
    p = CorrelatedNoiseParameters(n_outputs=4)
    kw = dict(segment_rows=16, taper_rows=4, method=method)
    ref = CorrelatedNoise(p, (96, 64), (3, 2, 1), 2.83, 5, cache_bytes=0, **kw)
    cached = CorrelatedNoise(p, (96, 64), (3, 2, 1), 2.83, 5, **kw)
    small = CorrelatedNoise(p, (96, 64), (3, 2, 1), 2.83, 5, cache_bytes=3 * 5 * 4 * 1500, **kw)
    order = [(0, 0, 11), (0, 11, 40), (1, 0, 20), (0, 40, 96), (0, 5, 17), (1, 20, 96), (0, 90, 96)]
    for ramp, y0, y1 in order:
        want = ref.block(ramp, y0, y1)
        for gen in (cached, small):
            np.testing.assert_array_equal(gen.block(ramp, y0, y1), want)
    assert ref._segment_cache == {}
    assert all(key[0] == 0 and key[2] >= (96 - 4) // 16 for key in cached._segment_cache)
    for gen in (cached, small):
        assert gen._cache_nbytes == sum(a.nbytes for _, a in gen._segment_cache.values()) <= gen.cache_bytes


@pytest.mark.needs_opencl_device
def test_a_cache_of_segment_cache_bytes_synthesises_each_segment_once(monkeypatch):
    """With the cache :func:`segment_cache_bytes` sizes (one segment of every group), blocks smaller than a
    segment synthesise each (group, segment) once (the default segments of 128 rows); a cache of a third of
    that synthesises most of them again for every block they span.  The ramp sampler's budget split gives
    the cache that size when the budget allows it."""
    from slicersim.backends.correlated_noise import segment_cache_bytes
    from slicersim.physics.effects import DetectorEffects
    from slicersim.physics.ramp import RampParameters
    from slicersim.products.ramps import _block_rows
    p = CorrelatedNoiseParameters(n_outputs=4)
    shape, nmd = (512, 64), (6, 2, 0)
    need = segment_cache_bytes(p, shape, nmd, 2.83)
    counts = {}
    for label, cache in (("full", need), ("third", need // 3)):
        gen = CorrelatedNoise(p, shape, nmd, 2.83, 5, cache_bytes=cache)
        made = []
        orig = gen._synthesize_segments
        monkeypatch.setattr(gen, "_synthesize_segments",
                            lambda ramp, todo, orig=orig, made=made: made.append(sum(m.size for _, m in todo))
                            or orig(ramp, todo))
        for y0 in range(0, 512, 16):
            gen.block(0, y0, y0 + 16)
        counts[label] = sum(made)
    nseg = gen._segment_geometry()[2]
    assert counts["full"] == nmd[0] * nseg                     # each once
    assert counts["third"] > 2 * counts["full"]
    fx = DetectorEffects.from_text("correlated_noise")
    lazuli = fx.params("correlated_noise")
    rp = RampParameters(nmd=(62, 8, 0))
    rows, cache = _block_rows(rp, fx, (4096, 4096), 2**30)
    assert cache >= segment_cache_bytes(lazuli, (4096, 4096), (62, 8, 0), rp.tframe) and cache <= 2**29


def test_spectral_draws_twin():
    """Kernel vs NumPy twin: the same Philox words; float32 Box–Muller with libm differences
    (OpenCL log/cospi/sinpi ≤ 4 ulp, NumPy's within 1 ulp): |Δ| ≤ 1e-5·amp (radius ≤ 5.8)."""
    rng = np.random.default_rng(0)
    amp = rng.uniform(0.5, 2.0, (2, 1001)).astype(np.float32)
    kind, hi = np.array([0, 1, 1]), np.array([0, 7, 2**31])
    stream, draw = np.array([0x12000000, 0x12030001, 5]), np.array([0, 3, 2**20])
    a = spectral_coefficients_numpy(amp, kind, hi, stream, draw, 99)
    b = spectral_coefficients_opencl(amp, kind, hi, stream, draw, 99)[:, :1001]
    np.testing.assert_allclose(b.real, a.real, atol=1e-5 * 2.0, rtol=0)
    np.testing.assert_allclose(b.imag, a.imag, atol=1e-5 * 2.0, rtol=0)
    z = a / amp[kind]
    assert abs(np.mean(np.abs(z[:, 1:]) ** 2) - 2.0) < 0.1          # E|z₀ + i z₁|² = 2


@pytest.mark.needs_opencl_device
def test_spectral_draws_identical_for_every_vector_width():
    """The float16 build interleaves its products by swizzles, the others by a loop: the same
    float operations per bin, so every width gives the same bits."""
    rng = np.random.default_rng(1)
    amp = rng.uniform(0.5, 2.0, (2, 777)).astype(np.float32)
    kind, hi = np.array([0, 1, 1, 0]), np.array([0, 7, 2**31, 3])
    stream, draw = np.array([0x12000000, 0x12030001, 5, 9]), np.array([0, 3, 2**20, 1])
    ref = spectral_coefficients_opencl(amp, kind, hi, stream, draw, 99, vector_width=16)[:, :777]
    for vw in (1, 4, 8):
        got = spectral_coefficients_opencl(amp, kind, hi, stream, draw, 99, vector_width=vw)[:, :777]
        assert np.array_equal(got.view(np.uint32), ref.view(np.uint32)), vw


@pytest.mark.needs_opencl_device
def test_generator_backends_agree():
    """multirate block on OpenCL vs NumPy (draws + assembly twins): within 1e-4 e- (float32
    rounding of the draws propagated through the FFT; the noise rms is ~5 e-)."""
    p = CorrelatedNoiseParameters(n_outputs=4)
    a = CorrelatedNoise(p, (64, 64), (3, 2, 0), 2.83, 8, backend="numpy").block(0, 5, 50)
    b = CorrelatedNoise(p, (64, 64), (3, 2, 0), 2.83, 8, backend="opencl").block(0, 5, 50)
    np.testing.assert_allclose(a, b, atol=1e-4, rtol=0)


@pytest.mark.needs_opencl_device
@pytest.mark.parametrize("nout, nx", [(4, 64), (8, 64), (4, 48), (4, 56)])
def test_assembly_twin(nout, nx):
    """The kernel's explicit lanes (16, 8, 4 or 1 columns per work item: the largest dividing
    the output width; odd outputs reversed) against the NumPy twin."""
    gen = CorrelatedNoise(CorrelatedNoiseParameters(n_outputs=nout), (64, nx), (2, 1, 0), 2.83, 1,
                          segment_rows=16, taper_rows=4)
    s_first, seg, win = gen._segments(0, 1, 10, 40)
    rng = np.random.default_rng(1)
    small = [rng.normal(size=(30, nout)).astype(np.float32) for _ in range(4)]
    args = (seg, win, s_first, 10, *small, rng.normal(size=nout).astype(np.float32), 0.7,
            gen._ey[10:40].copy(), gen._ex)
    a = assemble_numpy(gen, *args, out=np.empty((30, nx), np.float32))
    b = assemble_opencl(gen, *args, out=np.empty((30, nx), np.float32))
    np.testing.assert_allclose(a, b, atol=1e-5, rtol=1e-6)
    grouped = assemble_numpy(gen, GroupInputs(*args), out=np.empty((30, nx), np.float32))
    assert np.array_equal(grouped, a)                                  # one inputs object = its fields


def test_bad_input():
    with pytest.raises(EffectsError, match="c_pink"):
        CorrelatedNoiseParameters(c_pink=-1)
    with pytest.raises(EffectsError, match="pedestal"):
        CorrelatedNoiseParameters(pedestal=float("nan"))
    with pytest.raises(EffectsError, match="divisible"):
        CorrelatedNoise(CorrelatedNoiseParameters(n_outputs=32), (64, 100), (2, 1, 0), 2.83, 0)
    with pytest.raises(EffectsError, match="method"):
        CorrelatedNoise(CorrelatedNoiseParameters(n_outputs=4), (64, 64), (2, 1, 0), 2.83, 0, method="fast")
    with pytest.raises(EffectsError, match="n_outputs"):
        CorrelatedNoiseParameters(n_outputs=0)
    gen = CorrelatedNoise(CorrelatedNoiseParameters(n_outputs=4), (64, 64), (2, 1, 0), 2.83, 0)
    with pytest.raises(EffectsError, match="rows"):
        gen.block(0, 10, 70)


def test_fft_length_is_the_smallest_5_smooth():
    from slicersim.backends.correlated_noise import fft_length

    def smooth(k):
        for p in (2, 3, 5):
            while k % p == 0:
                k //= p
        return k == 1
    for n in list(range(1, 400)) + [23100, 23101, 65537]:
        m = fft_length(n)
        assert m >= n and smooth(m) and not any(smooth(k) for k in range(n, m)), n


@pytest.mark.parametrize("shape, nmd, nfoh", [((64, 32), (5, 3, 2), 1), ((40, 16), (4, 1, 3), 0)])
def test_low_part_equals_interpolation_at_every_read(shape, nmd, nfoh):
    """The low part's group means (rows interpolated in bulk, read frames as strided slices) equal
    the direct formula: gather the two neighbouring low samples of each read's row starts."""
    gen = CorrelatedNoise(CorrelatedNoiseParameters(n_outputs=4, nfoh=nfoh), shape, nmd, 2.83, 3,
                          backend="numpy", low_rows=3)
    got = gen._low_coefficients(2)
    captured = []
    synth = gen._synthesize
    gen._synthesize = lambda *a: captured.append(synth(*a)) or captured[-1]
    gen._low_coefficients(2)
    low = np.concatenate(captured)
    g, q = gen.geometry, gen.low_rows
    n, m, _ = nmd
    reads = np.flatnonzero(gen.frames_group >= 0).reshape(n, m)
    at = (reads[:, :, None] * g.frame_rows + np.arange(g.ny + 1)).astype(np.int64)
    i0 = at // q
    w = ((at - i0 * q) / q).astype(np.float32)
    for s, row in enumerate(low):
        a = row[i0]
        expected = ((row[i0 + 1] - a) * w + a).mean(axis=1, dtype=np.float64).astype(np.float32)
        assert np.array_equal(got[s], expected)


@pytest.mark.needs_opencl_device
def test_device_copy_path_equals_zero_copy(monkeypatch):
    """Batching the groups' segment draws and FFTs changes no bit; the GPU branch of the block
    assembly and of the spectral draws (device copies, scratch buffers, one work item per column)
    forced on the CPU device gives the zero-copy path's noise: several row blocks, segments cached
    across them."""
    from slicersim.backends import correlated_noise as cn
    p = CorrelatedNoiseParameters(n_outputs=4)
    kw = dict(segment_rows=16, taper_rows=4, backend="opencl")

    def blocks(gen):
        return np.concatenate([gen.block(0, y0, min(64, y0 + 11)) for y0 in range(0, 64, 11)], axis=1)
    ref = blocks(CorrelatedNoise(p, (64, 64), (5, 2, 0), 2.83, 4, **kw))       # all groups in one batch
    monkeypatch.setattr(cn, "SYNTH_BYTES", 1)                      # one group per synthesis batch
    assert np.array_equal(blocks(CorrelatedNoise(p, (64, 64), (5, 2, 0), 2.83, 4, **kw)), ref)
    monkeypatch.setattr(opencl, "device_type", lambda device=None: "GPU")
    got = blocks(CorrelatedNoise(p, (64, 64), (5, 2, 0), 2.83, 4, **kw))
    np.testing.assert_allclose(got, ref, rtol=0, atol=2e-6 * np.abs(ref).max())
    assert np.abs(ref).max() > 0 and not np.array_equal(ref[0], ref[1])


@pytest.mark.needs_opencl_device
def test_no_zero_copy_buffer_is_released_while_a_block_is_launched(monkeypatch):
    """Campaign workers aborted in PoCL ("PTHREAD ERROR in can_run_command(): Invalid argument", 5 worker
    deaths in 12 minutes of a 20-SN survey with effects): the zero-copy buffer cache was emptied when a
    window's insertion crossed its limit, between setting the segment as argument 0 and the launch, so
    the launch named a freed buffer (or read freed host memory).  With a limit of 0 (an eviction at every
    chance), every buffer a launch names is still held by the cache when it is launched, and the noise
    equals the NumPy twin's."""
    from slicersim.backends import correlated_noise as cn
    p = CorrelatedNoiseParameters(n_outputs=4)
    monkeypatch.setattr(cn, "SYNTH_BYTES", 1)                      # one group per batch
    monkeypatch.setattr(cn, "_MAX_WORK_BUFFERS", 0)
    gen = CorrelatedNoise(p, (64, 64), (6, 1, 0), 2.83, 4, segment_rows=16, taper_rows=4, backend="opencl")
    named, launches, real_array, real_launch = [], [], cn.CorrelatedNoise._device_array, opencl.launch_prepared

    def device_array(self, array, tag, gpu):
        buf = real_array(self, array, tag, gpu)
        named.append(buf)
        return buf

    def launch(kernel, *args, **kw):
        held = [v[1] for v in gen._work_buffers.values()]
        launches.append(all(any(b is h for h in held) for b in named[-2:]))
        return real_launch(kernel, *args, **kw)
    monkeypatch.setattr(cn.CorrelatedNoise, "_device_array", device_array)
    monkeypatch.setattr(opencl, "launch_prepared", launch)
    got = np.concatenate([gen.block(0, y0, min(64, y0 + 16)) for y0 in range(0, 64, 16)], axis=1)
    assert len(launches) == 4 * 6 and all(launches)
    ref = CorrelatedNoise(p, (64, 64), (6, 1, 0), 2.83, 4, segment_rows=16, taper_rows=4, backend="numpy")
    want = np.concatenate([ref.block(0, y0, min(64, y0 + 16)) for y0 in range(0, 64, 16)], axis=1)
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-5 * np.abs(want).max())
