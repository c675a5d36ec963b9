"""Raw-ramp generator: kernel vs NumPy twin, reproducibility, closed-loop statistics, files."""
import math
import os
import re

import numpy as np
import pytest

from slicersim.backends import opencl
from slicersim.physics.readout import variance_rauscher07
from slicersim.backends.ramp import simulate_block_numpy, simulate_block_opencl
from slicersim.products.ramps import (RampParameters, fit_slopes,
                             frame_mean_charge, simulate)
from slicersim.errors import RampFileError
from slicersim.io.rampfile import read_ramps

from conftest import have_opencl
from slicersim.targets import Lazuli3DFlat
from slicersim.errors import ReadoutError
from slicersim.targets import LazuliTarget
import h5py
from slicersim.physics.readout import variance_kubik16

#: the statistical tests run for both precisions of the samplers (issue 12); single needs OpenCL
BOTH_PRECISIONS = ["double", pytest.param("single", marks=pytest.mark.needs_opencl_device)]


def _seed(seed, precision):
    """Another seed for single: both precisions draw the same Philox words, so the same seed would make
    single's pass follow from double's instead of being independent evidence."""
    return seed if precision == "double" else seed + 1000


def _mu(rate, p):
    return frame_mean_charge(rate, 0.0, 0.0, p.roic_glow, p.tframe)


@pytest.mark.needs_opencl
@pytest.mark.parametrize("nmd", [(5, 3, 2), (4, 1, 0), (7, 8, 1)])
def test_kernel_equals_numpy_twin_bit_for_bit(nmd):
    """Same integers: both paths use the same Philox keys and the same IEEE operations."""
    rng = np.random.default_rng(1)
    rate = 10 ** rng.uniform(-4, 4.4, 2501)            # sparse, inversion, PTRS and saturating pixels
    p = RampParameters(nmd=nmd, ktc_noise=7.0, roic_glow=0.01, gauss_min_mean=np.inf)
    dead = rng.random(rate.size) < 0.01
    a = simulate_block_numpy(_mu(rate, p), dead, 17, 3, 1234, p)
    b = simulate_block_opencl(_mu(rate, p), dead, 17, 3, 1234, p)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert a[1].any(), "some pixels must saturate in this test"


@pytest.mark.needs_opencl
def test_gaussian_approximation_twin():
    """Gaussian-path kernel = NumPy twin (its moments: test_ramp_gaussian_path_moments below)."""
    p = RampParameters(nmd=(6, 2, 0), gauss_min_mean=50.0, ron=0.0, roic_glow=0.0, bias=0.0, full_well=1e9)
    rate = np.full(3001, 40.0)                           # mu = 113 e-/frame: Gaussian path
    a = simulate_block_numpy(_mu(rate, p), np.zeros(rate.size, bool), 0, 0, 9, p)
    b = simulate_block_opencl(_mu(rate, p), np.zeros(rate.size, bool), 0, 0, 9, p)
    assert np.array_equal(a[0], b[0])


@pytest.mark.needs_opencl
@pytest.mark.parametrize("row", [4000, 4095])
def test_bright_paths_at_the_end_of_a_4096_detector_bit_for_bit(row):
    """Bright pixels (PTRS 10 … 3e3 e-/frame, rounded Gaussian ≥ 3e3, full well reached in the first
    frames) mixed with dark and lit ones, at the pixel indices of a 4096² detector's last rows (the
    H200's wrong 4096² reduction was first suspected there; run 7: the kernel was right, the fit's
    read-back was not): kernel = twin, SCI and GROUPDQ."""
    gen = np.random.default_rng(row)
    rate = np.concatenate([10 ** gen.uniform(0.6, 5.0, 700), gen.choice([0.0, 0.005, 0.1, 1.0], 300)])
    rate = rate[gen.permutation(rate.size)]
    p = RampParameters(nmd=(8, 4, 1), ktc_noise=20.0, roic_glow=0.003, gauss_min_mean=3e3)
    mu = _mu(rate, p)
    assert ((mu >= 10) & (mu < 3e3)).sum() > 200 and (mu >= 3e3).sum() > 200 and (mu * 4 > p.full_well).any()
    dead = gen.random(rate.size) < 0.01
    a = simulate_block_numpy(mu, dead, row * 4096 + 3096, 2, 2**64 - 5, p)
    b = simulate_block_opencl(mu, dead, row * 4096 + 3096, 2, 2**64 - 5, p)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert a[1][0].any() and (a[1][-1] != 0).mean() > 0.1     # saturated from the first group on


@pytest.mark.needs_opencl
@pytest.mark.parametrize("work_group", [None, 1, 7, 64])
def test_identical_for_any_work_group_and_chunking(work_group):
    rate = np.random.default_rng(2).uniform(0, 50, (37, 41))
    ref = simulate(rate, (6, 4, 1), nramps=2, seed=77, backend="numpy")
    got = simulate(rate, (6, 4, 1), nramps=2, seed=77, backend="opencl", work_group=work_group,
                   max_bytes=41 * 8 * (9 + 3 * 6) * 2)    # ~8 rows per block
    assert np.array_equal(ref, got)


@pytest.mark.slow
@pytest.mark.needs_opencl
@pytest.mark.parametrize("npix", [1, 13, 1001])
def test_vector_lanes_any_width_and_odd_pixel_counts(npix):
    """Lane widths 1–16 and work groups 1/3/default give the twin's integers when the pixel count
    is not a multiple of the width (the last lanes repeat a pixel), with sparse, dense inversion,
    PTRS, Gaussian, dead and saturating pixels mixed in the same lanes."""
    gen = np.random.default_rng(npix)
    rate = 10 ** gen.uniform(-3, 4.5, npix)
    rate[gen.random(npix) < 0.3] = 0.004                  # dark pixels between bright ones
    p = RampParameters(nmd=(6, 4, 2), ktc_noise=5.0, gauss_min_mean=300.0)
    dead = gen.random(npix) < 0.05
    ref = simulate_block_numpy(_mu(rate, p), dead, 5, 1, 99, p)
    for vw, wg in [(1, None), (2, 3), (4, 1), (8, None), (16, 3), (16, None)]:
        got = simulate_block_opencl(_mu(rate, p), dead, 5, 1, 99, p, vector_width=vw, work_group=wg)
        assert np.array_equal(ref[0], got[0]) and np.array_equal(ref[1], got[1]), (vw, wg)


@pytest.mark.needs_opencl
def test_sparse_full_well_clipping_twin_and_statistics():
    """A 6 e- full well reached inside sparse windows (the rare clipped branch): kernel = twin, and
    the clipped group sums and flags have the dense sampler's mean, variance and flag rate."""
    nmd, npix = (6, 4, 2), 6000
    kw = dict(full_well=6.0, ron=0.0, bias=0.0, gain=4.0, roic_glow=0.0)   # ADU = sum of the 4 reads
    ps, pd = RampParameters(nmd=nmd, sparse_max_group=64.0, **kw), RampParameters(nmd=nmd, sparse_max_group=0.0, **kw)
    mu = np.full(npix, 0.25)                                   # 1.5 e- per window
    dead = np.zeros(npix, bool)
    a = simulate_block_numpy(mu[:500], dead[:500], 0, 0, 3, ps)
    b = simulate_block_opencl(mu[:500], dead[:500], 0, 0, 3, ps)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    (ss, fs), (sd, fd) = (simulate_block_opencl(mu, dead, 0, 0, 7, q) for q in (ps, pd))
    assert ss.max() == sd.max() == 24 and fs[-1].mean() > 0.5        # clipped at 4 × 6 e-
    for g in range(nmd[0]):
        xs, xd = ss[g].astype(float), sd[g].astype(float)
        err = math.sqrt((xs.var() + xd.var()) / npix)
        assert abs(xs.mean() - xd.mean()) < 4 * err + 1e-9
        assert abs(xs.var() - xd.var()) < 4 * math.sqrt(2.0 / npix) * (xs.var() + xd.var()) / 2 + 1e-9
        f = (fd[g] == 2).mean()
        assert abs((fs[g] == 2).mean() - f) < 4 * math.sqrt(2 * f * (1 - f) / npix) + 1e-9


@pytest.mark.parametrize("sparse_max_group", [0.0, 64.0])
def test_group_means_follow_the_poisson_process(sparse_max_group):
    """No read noise, ADU = Σ of the m reads: E = mμ(s + (m+1)/2), Var = m²μ(s + (m+1)(2m+1)/(6m)),
    Cov(g < h) = m²μ(s_g + (m+1)/2), s = g(m+d) frames before group g — for both samplers (d > 0:
    an event in a dropped frame is first seen by the next group)."""
    nmd, tf, mu, npix = (5, 4, 3), 2.83, 0.3, 40000
    n, m, d = nmd
    sci = simulate(np.full((200, 200), mu / tf), nmd, seed=4, ron=0.0, bias=0.0, gain=float(m), dark=0.0,
                   roic_glow=0.0, sparse_max_group=sparse_max_group)[0].reshape(n, -1).astype(float)
    for g in range(n):
        s = g * (m + d)
        mean, var = m * mu * (s + (m + 1) / 2), m * m * mu * (s + (m + 1) * (2 * m + 1) / (6 * m))
        assert abs(sci[g].mean() - mean) < 4 * math.sqrt(var / npix), g
        assert abs(sci[g].var() - var) < 4 * var * math.sqrt(2.0 / npix), g
    cov = m * m * mu * (1 * (m + d) + (m + 1) / 2)
    v1, v3 = sci[1].var(), sci[3].var()
    assert abs(np.cov(sci[1], sci[3])[0, 1] - cov) < 4 * math.sqrt((v1 * v3 + cov**2) / npix)


@pytest.mark.parametrize("precision", BOTH_PRECISIONS)
@pytest.mark.parametrize("nmd", [(16, 8, 0), (8, 4, 2)])
def test_sparse_sampler_slope_variance_matches_rauscher07(nmd, precision):
    """2 e-/s forced onto the sparse sampler (≈ 45 and 34 e- per window): Rauscher07 within 3 σ."""
    npix, rate, ron, tf = 22500, 2.0, 12.0, 2.83
    n, m, d = nmd
    sci = simulate(np.full((150, 150), rate), nmd, seed=_seed(12, precision), ron=ron, dark=0.0, roic_glow=0.0,
                   sparse_max_group=64.0, precision=precision)[0]
    tint = (n - 1) * (m + d) * tf
    est = fit_slopes(sci.reshape(n, -1), nmd, tf) * tint
    expected = variance_rauscher07(rate, nmd, tf, math.sqrt(ron**2 + m / 12.0), 0.0)
    var = est.var(ddof=1)
    assert abs(var - expected) < 3 * var * math.sqrt(2.0 / (npix - 1)), f"{var:.1f} vs {expected:.1f}"
    assert abs(est.mean() / tint - rate) < 4 * math.sqrt(var / npix) / tint


def test_bad_tuning_parameters_are_refused():
    with pytest.raises(ValueError, match="sparse_max_group"):
        simulate(np.ones((2, 2)), (3, 1, 0), sparse_max_group=-1.0)
    if have_opencl(fp64=False) and "GPU" not in opencl.device_type():
        with pytest.raises(ValueError, match="work_group"):
            simulate(np.ones((2, 2)), (3, 1, 0), backend="opencl", work_group=4096)


def test_seed_changes_output_and_same_seed_repeats():
    rate = np.full((8, 9), 3.0)
    a = simulate(rate, (4, 2, 0), seed=1)
    assert np.array_equal(a, simulate(rate, (4, 2, 0), seed=1))
    assert not np.array_equal(a, simulate(rate, (4, 2, 0), seed=2))


READOUTS = [(16, 8, 0), (8, 4, 2), (12, 1, 0), (5, 8, 4), (32, 1, 3)]


@pytest.mark.parametrize("precision", BOTH_PRECISIONS)
@pytest.mark.parametrize("nmd", READOUTS)
def test_slope_variance_matches_rauscher07(nmd, precision):
    """Empirical variance of least-squares slopes × t_int = Rauscher07 within 3 σ of its MC error.

    The 1/12 ADU² rounding noise of each group mean is added to the read noise
    (σ_eff² = σ² + m/12 for gain 1).  Kubik16 against the same Monte Carlo:
    test_ramp_slope_variance_matches_kubik16_for_few_groups (below).
    """
    npix, rate, ron, tf = 40000, 2.0, 12.0, 2.83
    sci = simulate(np.full((200, 200), rate), nmd, seed=_seed(11, precision), ron=ron, dark=0.0, roic_glow=0.0,
                   precision=precision)[0]
    n, m, d = nmd
    tint = (n - 1) * (m + d) * tf
    est = fit_slopes(sci.reshape(n, -1), nmd, tf) * tint
    ron_eff = math.sqrt(ron**2 + m / 12.0)
    expected = variance_rauscher07(rate, nmd, tf, ron_eff, 0.0)
    var = est.var(ddof=1)
    mc_err = var * math.sqrt(2.0 / (npix - 1))
    assert abs(var - expected) < 3 * mc_err, f"{nmd}: {var:.2f} vs Rauscher {expected:.2f} ± {mc_err:.2f}"
    assert abs(est.mean() / tint - rate) < 4 * math.sqrt(var / npix) / tint


@pytest.mark.parametrize("precision", BOTH_PRECISIONS)
@pytest.mark.parametrize("rate", [0.01, 0.1, 1.0, 10.0, 100.0, 1000.0])
def test_slopes_unbiased_over_five_decades(rate, precision):
    nmd, tf = ((10, 4, 0) if rate < 100 else (10, 1, 0)), 2.83      # below the full well
    sci = simulate(np.full((100, 100), rate), nmd, seed=_seed(5, precision), ron=5.0, dark=0.0, roic_glow=0.0,
                   precision=precision)[0]
    est = fit_slopes(sci.reshape(nmd[0], -1), nmd, tf)
    err = est.std(ddof=1) / math.sqrt(est.size)
    assert abs(est.mean() - rate) < 4 * err, f"rate {rate}: {est.mean()} ± {err}"


def test_sparse_path_statistics_unchanged():
    """Dark pixels: the count-then-place sampler gives the dense sampler's statistics."""
    nmd, tf = (8, 8, 1), 2.83
    rate = np.full((150, 150), 0.02)
    kw = dict(seed=21, ron=0.0, dark=0.0, roic_glow=0.0, bias=0.0)
    sparse = simulate(rate, nmd, sparse_max_group=1.0, **kw)[0].reshape(nmd[0], -1).astype(float)
    dense = simulate(rate, nmd, sparse_max_group=0.0, **kw)[0].reshape(nmd[0], -1).astype(float)
    for g in (0, 3, 7):
        for arr in (sparse, dense):
            pass
        ms, md = sparse[g].mean(), dense[g].mean()
        err = math.sqrt(sparse[g].var() / sparse[g].size + dense[g].var() / dense[g].size)
        assert abs(ms - md) < 4 * err
        vs, vd = sparse[g].var(), dense[g].var()
        assert abs(vs - vd) < 4 * vd * math.sqrt(2 / sparse[g].size) + 1e-3
    # total charge of the last group is Poisson(mu F) with mu = rate t_f (no reads noise, no rounding)
    total_expect = 0.02 * tf * (8 * 9 - 1 - 0.5 * 7)   # mean of the last group's 8 frames
    assert sparse[-1].mean() == pytest.approx(total_expect, rel=0.05)


def test_saturation_flags_and_full_well():
    """A 1000 e-/s pixel saturates after ~22 frames: flagged from that group on; slopes from the
    unflagged groups stay unbiased; a faint pixel is never flagged."""
    nmd, tf = (10, 4, 0), 2.83
    rate = np.concatenate([np.full((50, 100), 1000.0), np.full((50, 100), 1.0)])
    sci, gdq = simulate(rate, nmd, seed=8, ron=5.0, return_dq=True)
    sci, gdq = sci[0].reshape(10, -1), gdq[0].reshape(10, -1)
    bright, faint = slice(0, 5000), slice(5000, None)
    first = np.argmax(gdq[:, bright] == 2, axis=0)
    full_well_time = (65535 - 2000) / 1000.0                 # s
    assert np.all(gdq[-1, bright] == 2) and not gdq[:, faint].any()
    assert np.all(np.abs(first * 4 * tf - full_well_time) < 2 * 4 * tf)
    assert np.all(np.diff(gdq[:, bright].astype(int), axis=0) >= 0)   # flags are sticky
    assert sci[:, bright].max() <= 65535 - 2000 + 2000
    naive = fit_slopes(sci[:, bright], nmd, tf)
    honoured = fit_slopes(sci[:, bright], nmd, tf, groupdq=gdq[:, bright])
    assert abs(np.nanmean(honoured) - 1000.0) < 2.0 and np.nanmean(naive) < 800


def test_hdf5_file_layout_and_data_volume(tmp_path):
    from slicersim.instrument.detector import Detector
    rate = np.random.default_rng(0).uniform(0, 100, (64, 48))
    path = simulate(rate, (5, 4, 1), nramps=2, seed=9, out=tmp_path / "ramp.h5", truth=True)
    sci, gdq, pdq, attrs = read_ramps(path)
    assert sci.shape == (2, 5, 64, 48) and sci.dtype == np.uint16
    assert gdq.shape == sci.shape and gdq.dtype == np.uint8 and pdq.dtype == np.uint32
    assert attrs["READPATT"] == "MACC(5,4,1)" and attrs["NGROUPS"] == 5 and attrs["NFRAMES"] == 4
    assert attrs["GROUPGAP"] == 1 and attrs["NINTS"] == 2 and attrs["SEED"] == 9
    assert np.array_equal(sci, simulate(rate, (5, 4, 1), nramps=2, seed=9))
    det = Detector(shape=(64, 48))
    assert sci.nbytes / 1e9 == pytest.approx(det.data_volume((5, 4, 1), 2))
    assert os.listdir(tmp_path) == ["ramp.h5"]              # no temporary left


@pytest.mark.parametrize("compression", ["gzip", "lz4", "bitshuffle-lz4"])
def test_compressed_files_roundtrip(tmp_path, compression):
    rate = np.full((32, 32), 5.0)
    path = simulate(rate, (4, 2, 0), seed=1, out=tmp_path / f"r_{compression}.h5", compression=compression)
    sci, *_ = read_ramps(path)
    assert np.array_equal(sci, simulate(rate, (4, 2, 0), seed=1))


def test_read_only_directory_fails_cleanly(tmp_path):
    if os.geteuid() == 0:
        # root ignores permission bits: use a path under a file instead (not a directory)
        target = tmp_path / "not_a_dir" / "ramp.h5"
        (tmp_path / "not_a_dir").write_text("x")
    else:
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        target = ro / "ramp.h5"
    with pytest.raises(RampFileError):
        simulate(np.ones((4, 4)), (3, 1, 0), out=target)
    assert not os.path.exists(target)


def test_interrupted_writer_leaves_no_complete_file(tmp_path, monkeypatch):
    import slicersim.products.ramps as ramps
    calls = {"n": 0}
    real = ramps.simulate_block_numpy

    def dying(*args, **kw):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt("killed")
        return real(*args, **kw)
    monkeypatch.setattr(ramps, "simulate_block_numpy", dying)
    out = tmp_path / "ramp.h5"
    with pytest.raises(KeyboardInterrupt):
        ramps.simulate(np.ones((16, 8)), (3, 1, 0), out=out, backend="numpy", max_bytes=8 * 8 * 40)
    assert not out.exists()
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("kwargs, err", [
    (dict(nmd=(1, 8, 0)), "n, groups per ramp"), (dict(nmd=(4, 0, 0)), "m, frames"),
    (dict(nmd=(4, 2, -1)), "dropped"), (dict(nramps=0), "nramps"),
    (dict(nmd=(2.7, 1, 0)), r"nmd\[0\].*2\.7"), (dict(nramps=1.5), "nramps"),
])
def test_invalid_readouts(kwargs, err):
    from slicersim.errors import ReadoutError
    args = dict(nmd=(4, 2, 0), nramps=1) | kwargs
    with pytest.raises(ReadoutError, match=err):
        simulate(np.ones((2, 2)), **args)


@pytest.mark.parametrize("rate, err", [
    (np.full((2, 2), np.nan), "rate has 4 non-finite"), (-np.ones((2, 2)), "rate must be ≥ 0"),
    (np.ones(4), "rate must have 2 dimension"), (np.ones((2, 2), complex), "rate must be an array of real"),
    (np.zeros((2, 2), [("a", float)]), "rate must be an array of real"), (np.empty((0, 3)), "rate must be a non-empty"),
    ([["a", "b"]], "rate must be an array of real")])
def test_invalid_rates(rate, err):
    from slicersim.errors import ParameterError
    with pytest.raises(ParameterError, match=err):
        simulate(rate, (3, 1, 0), seed=0)


def test_memory_busting_request_is_refused():
    with pytest.raises(MemoryError):
        simulate(np.ones((64, 64)), (64, 8, 0), nramps=100, max_bytes=10_000)


def test_full_disk_is_refused_before_writing(tmp_path, monkeypatch):
    import shutil
    from collections import namedtuple
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10**6, 10**6 - 1000, 1000))
    out = tmp_path / "big.h5"
    with pytest.raises(RampFileError, match="disk space"):
        simulate(np.ones((64, 64)), (8, 1, 0), out=out)
    assert not list(tmp_path.iterdir())


def test_write_error_mid_file_leaves_nothing(tmp_path, monkeypatch):
    """An OSError while writing (e.g. the disk filling up) ends in RampFileError and no file."""
    from slicersim.io import rampfile as rampio
    real = rampio.RampWriter.write_block
    calls = {"n": 0}

    def failing(self, *args, **kw):
        calls["n"] += 1
        if calls["n"] == 2:
            raise RampFileError("writing failed (disk full?): [Errno 28] No space left on device")
        return real(self, *args, **kw)
    monkeypatch.setattr(rampio.RampWriter, "write_block", failing)
    with pytest.raises(RampFileError, match="No space"):
        simulate(np.ones((16, 8)), (3, 1, 0), out=tmp_path / "r.h5", max_bytes=8 * 8 * 40)
    assert not list(tmp_path.iterdir())


# ---------------------------------------------------------------- issue 24: one call form, validation, seeds
def _small_rate(n=32):
    y, x = np.mgrid[:n, :n]
    return 0.01 * (x + 1) * (y % 5) + 50.0 * ((x == 7) & (y == 9))


@pytest.mark.parametrize("effects, digest", [(None, "ee8fe4d340f3e69c5d05"),
                                             ("cosmic_rays,ipc,nonlinearity", "266a922fbdd8604b45aa")])
@pytest.mark.parametrize("backend", ["numpy", "opencl"])
def test_seed_0_gives_the_pinned_ramps(backend, effects, digest):
    """seed=0 gives pinned ramps on both backends.  Re-pinned (issue 30) when the sparse sampler
    went to one Philox block per two group windows (32-bit words, exact low-bit refinement):
    seed=S ramps differ from those of slicersim before that change (were 8c8130cf60878e7ce722 and
    cd6190bc9798d82cb67b)."""
    import hashlib
    sci, dq = simulate(_small_rate(), (5, 2, 1), nramps=2, seed=0, backend=backend, return_dq=True,
                       progress=False, ktc_noise=3.0, effects=effects)
    assert hashlib.sha256(sci.tobytes() + dq.tobytes()).hexdigest()[:20] == digest


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["numpy", "opencl"])
@pytest.mark.parametrize("effects", [None, "cosmic_rays,ipc,nonlinearity,bad_pixels", "all"])
def test_keyword_form_is_bit_identical_to_readout_form(tmp_path, backend, effects):
    """simulate(rate, nmd=..., tframe=..., ...) and simulate(rate, RampParameters(...), io=..., run=...)
    give the same SCI, GROUPDQ, PIXELDQ and attributes for several seeds, in memory and in files."""
    import h5py

    from slicersim.products.ramps import RampIO, RampParameters, RampResult, RunOptions
    rate = np.random.default_rng(3).gamma(0.5, 2.0, (64, 64))
    rate[5, 5] = 5e3
    loose = dict(nmd=(5, 2, 1), nramps=2, tframe=3.0, ron=9.0, ktc_noise=4.0, dark=1e-2, gain=1.5)
    readout = RampParameters(**loose)
    for seed in (0, 7, 2**63 + 11):
        old = simulate(rate, seed=seed, backend=backend, effects=effects, return_dq=True, progress=False,
                       max_bytes=150_000, **loose)
        new = simulate(rate, readout, seed=seed, backend=backend, effects=effects, io=RampIO(return_dq=True),
                       run=RunOptions(progress=False, max_bytes=150_000))
        assert isinstance(new, RampResult) and new.seed == seed
        assert np.array_equal(old[0], new.sci) and np.array_equal(old[1], new.groupdq)
    paths = [simulate(rate, seed=5, backend=backend, effects=effects, out=tmp_path / "old.h5", progress=False,
                      **loose),
             simulate(rate, readout, seed=5, backend=backend, effects=effects, out=tmp_path / "new.h5",
                      run=RunOptions(progress=False)).path]
    with h5py.File(paths[0]) as a, h5py.File(paths[1]) as b:
        for name in ("SCI", "GROUPDQ", "PIXELDQ", "truth/rate"):
            assert np.array_equal(a[name][...], b[name][...]), name
        assert {k: str(v) for k, v in a.attrs.items()} == {k: str(v) for k, v in b.attrs.items()}


def test_default_seed_is_fresh_and_recorded(tmp_path):
    """seed=None (the default) draws a new seed per call, recorded in SEED and returned: two default
    calls differ, and each is reproduced from its file's SEED."""
    import h5py

    from slicersim.products.ramps import RampParameters
    rate = np.full((8, 8), 2.0)
    a = simulate(rate, (4, 2, 0), out=tmp_path / "a.h5", progress=False)
    b = simulate(rate, (4, 2, 0), out=tmp_path / "b.h5", progress=False)
    assert type(a) is str
    with h5py.File(a) as fa, h5py.File(b) as fb:
        seed_a, seed_b = int(fa.attrs["SEED"]), int(fb.attrs["SEED"])
        sci_a = fa["SCI"][...]
        assert seed_a != seed_b and not np.array_equal(sci_a, fb["SCI"][...])
    assert np.array_equal(sci_a, simulate(rate, (4, 2, 0), seed=seed_a))
    result = simulate(rate, RampParameters(nmd=(4, 2, 0)))
    assert result.attrs["SEED"] == result.seed
    assert np.array_equal(result.sci, simulate(rate, (4, 2, 0), seed=result.seed))


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(nmd=(2.7, 1, 0)), "ReadoutError", r"nmd\[0\]"),
    (dict(seed=1.5), "ParameterError", "seed"),
    (dict(seed=-1), "ParameterError", "seed"),
    (dict(backend="cuda"), "ParameterError", "backend"),
    (dict(precision="quad"), "ParameterError", "precision"),
    (dict(tframe=-2.0), "ParameterError", "tframe"),
    (dict(ron=float("nan")), "ParameterError", "ron"),
    (dict(gain="1"), "ParameterError", "gain"),
    (dict(saturation=70000), "ParameterError", "saturation"),
    (dict(dark=-1e-3), "ParameterError", "dark"),
    (dict(dark=np.full((3, 3), 1e-3)), "ParameterError", "dark"),
    (dict(file_format="fits", out="x.fits"), "ParameterError", "file_format"),
    (dict(max_bytes=0), "ParameterError", "max_bytes"),
    (dict(return_dq="yes"), "ParameterError", "return_dq"),
    (dict(dead_pixels=np.zeros((3, 3), bool)), "ParameterError", "dead_pixels"),
    (dict(nmdd=(4, 2, 0)), "ParameterError", "nmdd.*did you mean 'nmd'"),
])
def test_bad_arguments_are_slicersim_errors_naming_the_parameter(kwargs, error, match):
    from slicersim import errors
    args = dict(nmd=(4, 2, 0)) | kwargs
    with pytest.raises(getattr(errors, error), match=match) as info:
        simulate(np.ones((4, 4)), **args)
    assert isinstance(info.value, errors.SlicersimError)


def test_readout_form_refuses_loose_keywords_and_accepts_quantities():
    import astropy.units as u

    from slicersim.errors import ParameterError
    from slicersim.products.ramps import RampParameters
    p = RampParameters(nmd=(4, 2, 0), tframe=2830 * u.ms, ron=12 * u.electron, dark=2.8e-3 * u.electron / u.s)
    assert p.tframe == pytest.approx(2.83) and p.ron == 12.0
    with pytest.raises(ParameterError, match="ron.*readout"):
        simulate(np.ones((4, 4)), p, ron=3.0)
    with pytest.raises(ParameterError, match="io must be a RampIO"):
        simulate(np.ones((4, 4)), p, io={"overwrite": True})
    with pytest.raises(ParameterError, match="io=, run= and maps= go with readout=RampParameters"):
        simulate(np.ones((4, 4)), (4, 2, 0), run=None, io=None, maps=object())
    with pytest.raises(ParameterError, match="tframe"):
        RampParameters(nmd=(4, 2, 0), tframe=3 * u.m)
    ref = simulate(np.ones((4, 4)), p, seed=3).sci
    assert np.array_equal(ref, simulate(np.ones((4, 4)), (4, 2, 0), seed=3))


def test_memory_budget_is_the_deprecated_name_of_max_bytes():
    rate = np.ones((4, 4))
    with pytest.warns(DeprecationWarning, match="memory_budget.*max_bytes"):
        old = simulate(rate, (3, 1, 0), seed=1, memory_budget=2**20)
    assert np.array_equal(old, simulate(rate, (3, 1, 0), seed=1, max_bytes=2**20))
    from slicersim.errors import ParameterError
    with pytest.raises(ParameterError, match="max_bytes"):
        simulate(rate, (3, 1, 0), seed=1, memory_budget=2**20, max_bytes=2**20)


def test_get_ramps_checks_the_seed_before_the_detector_image(monkeypatch):
    """Target.get_ramps: seed defaults to None (fresh, recorded); a bad seed is a ParameterError naming
    it, raised before the (slow) full-detector image is built."""
    import inspect

    from slicersim.errors import ParameterError
    from slicersim.targets import LazuliSupernova
    tgt = LazuliSupernova(1.0)
    assert inspect.signature(tgt.get_ramps).parameters["seed"].default is None

    def no_image(*args, **kwargs):
        raise AssertionError("the detector image was built before the seed was checked")
    monkeypatch.setattr(type(tgt), "get_detector_image", no_image)
    for bad in (1.5, -2, "7"):
        with pytest.raises(ParameterError, match="seed"):
            tgt.get_ramps(nmd=(4, 2, 0), seed=bad)


@pytest.fixture(scope="module")
def qth():
    return Lazuli3DFlat.from_qth()


@pytest.mark.parametrize("nramps", [0, -1, 1.5, "2", True])
def test_get_ramps_refuses_bad_ramp_counts(qth, nramps):
    with pytest.raises(ReadoutError, match="nramps must be an integer"):
        qth.get_ramps(nramps=nramps)


from model_state import (BACKENDS, LBDA, TFRAME, short_range_toml, short_target,  # noqa: E402,F401
                         sloped)


@pytest.mark.slow
@pytest.mark.needs_opencl      # the NumPy ramp sampler needs ~2 min for 4096² pixels
def test_get_ramps_file_shapes_and_attributes(short_target, tmp_path):
    det = short_target.simulation.detector
    image = short_target.get_detector_image(backend="opencl")
    path = short_target.get_ramps(out=str(tmp_path / "ramps.h5"), nmd=(3, 1, 0), nramps=1, seed=3,
                                  backend="opencl")
    with h5py.File(path, "r") as f:
        assert f["SCI"].shape == f["GROUPDQ"].shape == (1, 3, 4096, 4096)
        assert f["SCI"].dtype == np.uint16 and f["PIXELDQ"].shape == (4096, 4096)
        a = f.attrs
        assert (a["NGROUPS"], a["NFRAMES"], a["GROUPGAP"], a["NINTS"]) == (3, 1, 0, 1)
        assert a["READPATT"] == "MACC(3,1,0)" and a["SEED"] == 3 and bool(a["COMPLETE"])
        assert a["TFRAME"] == det.tframe and a["READNOISE"] == det.ron and a["GAIN"] == det.gain
        assert a["DARK"] == det.dark and a["ROIC_GLOW"] == det.roic_glow
        assert a["THERMAL_DARK"] == pytest.approx(short_target.simulation.thermal_dark, rel=1e-12)
        truth = f["truth/rate"][...]
        # the truth image is the detector image, stored at the file's precision (float32: 6e-8)
        np.testing.assert_allclose(truth, image,
                                   rtol=np.finfo(truth.dtype).eps, atol=0)
        sci = f["SCI"][0].astype(float)
    # mean charge accumulated between group 0 and 2 (two frames) over all pixels:
    # (rate + dark + thermal dark + glow / t_f) · 2 t_f · gain, known to ±4 standard errors
    diff = (sci[2] - sci[0]).ravel()
    rate = image.mean()
    d_eff = det.dark + short_target.simulation.thermal_dark + det.roic_glow / det.tframe
    expected = (rate + d_eff) * 2 * det.tframe * det.gain
    assert abs(diff.mean() - expected) < 4 * diff.std() / math.sqrt(diff.size)


@pytest.mark.parametrize("backend", BACKENDS)
def test_ramp_gaussian_path_moments(backend):
    """Rounded-Gaussian frame increments (μ = 113 e-/frame > gauss_min_mean), no read noise, m = 2:
    group-mean difference g1 − g0 = (x1 + 2 x2 + x3)/2 → mean 2μ, variance (1+4+1)/4 μ = 1.5 μ
    (+ rounding ~1/6 ADU²); last − first = x1/2 + x2…x10 + x11/2 → mean 10 μ, variance 9.5 μ."""
    from slicersim.backends.ramp import simulate_block_numpy, simulate_block_opencl
    from slicersim.products.ramps import RampParameters, frame_mean_charge
    p = RampParameters(nmd=(6, 2, 0), gauss_min_mean=50.0, ron=0.0, roic_glow=0.0, bias=0.0, full_well=1e9)
    npix = 20001
    mu_frame = frame_mean_charge(np.full(npix, 40.0), 0.0, 0.0, 0.0, p.tframe)
    mu = 40.0 * p.tframe
    assert mu_frame[0] == pytest.approx(mu, rel=1e-12) and mu > 50.0
    run = simulate_block_numpy if backend == "numpy" else simulate_block_opencl
    sci = run(mu_frame, np.zeros(npix, bool), 0, 0, 9, p)[0].astype(float)
    for diff, k_mean, k_var in ((sci[1] - sci[0], 2.0, 1.5), (sci[5] - sci[0], 10.0, 9.5)):
        mean_exp, var_exp = k_mean * mu, k_var * mu
        var = diff.var(ddof=1)
        assert abs(diff.mean() - mean_exp) < 4 * math.sqrt(var_exp / npix)
        assert abs(var - var_exp) < 4 * var_exp * math.sqrt(2.0 / (npix - 1)) + 0.5    # + rounding


@pytest.mark.parametrize("nmd", [(2, 8, 0), (3, 4, 1)])
def test_ramp_slope_variance_matches_kubik16_for_few_groups(nmd):
    """For n ≤ 3 groups least squares is the maximum-likelihood slope: the empirical variance of
    simulated slopes × t_int equals Kubik16 (and Rauscher07) within 4 σ of its Monte Carlo error.
    Group means are rounded to ADU: σ_eff² = σ² + m/12 (gain 1)."""
    from slicersim.products.ramps import fit_slopes, simulate
    npix, rate, ron, tf = 40000, 2.0, 12.0, TFRAME
    sci = simulate(np.full((200, 200), rate), nmd, seed=17, ron=ron, dark=0.0, roic_glow=0.0,
                   backend="numpy")[0]
    n, m, d = nmd
    tint = (n - 1) * (m + d) * tf
    est = fit_slopes(sci.reshape(n, -1), nmd, tf) * tint
    var = est.var(ddof=1)
    ron_eff = math.sqrt(ron**2 + m / 12.0)
    kubik = float(variance_kubik16(rate, nmd, tf, ron_eff, 0.0))
    mc_err = kubik * math.sqrt(2.0 / (npix - 1))
    assert abs(var - kubik) < 4 * mc_err, (var, kubik, mc_err)
    assert kubik == pytest.approx(float(variance_rauscher07(rate, nmd, tf, ron_eff, 0.0)), rel=1e-3)


def test_rate_quantity_is_converted_or_refused_never_dropped():
    """A rate in e-/ms was taken as e-/s (1000× too low) and one in metres accepted: a Quantity is
    converted to e-/s or refused."""
    import astropy.units as u

    from slicersim.errors import ParameterError
    rate = np.full((8, 8), 2.0)
    plain = simulate(rate, nmd=(3, 1, 0), seed=1, progress=False)
    assert np.array_equal(simulate(rate * u.electron / u.s, nmd=(3, 1, 0), seed=1, progress=False), plain)
    assert np.array_equal(simulate(rate / 1000 * u.electron / u.ms, nmd=(3, 1, 0), seed=1, progress=False), plain)
    with pytest.raises(ParameterError, match="rate must be in units convertible to electron / s, got m"):
        simulate(rate * u.m, nmd=(3, 1, 0), seed=1)


def test_out_and_keywords_are_named():
    """out=5 gave a bare TypeError; a misspelt keyword listed only some keywords, without a did-you-mean."""
    from slicersim.errors import ParameterError
    rate = np.full((8, 8), 2.0)
    with pytest.raises(ParameterError, match="out must be a file path"):
        simulate(rate, nmd=(3, 1, 0), seed=1, out=5)
    with pytest.raises(ParameterError, match=r"'sead' \(did you mean 'seed'\?\).*'effects'"):
        simulate(rate, nmd=(3, 1, 0), sead=1)


def test_a_rate_beyond_the_samplers_range_is_refused_naming_it_and_the_bound():
    """A rate of 1e300 e-/s gave NumPy overflow RuntimeWarnings (and 1e9 e-/s an invalid cast): refused with
    the bound; a rate saturating a pixel many times within a frame but below the bound runs quietly."""
    import warnings

    from slicersim.errors import ParameterError
    for rate, dark, name in ((1e300, 0.0, "rate reaches 1e+300 e-/s"), (1e9, 0.0, "rate reaches 1e+09 e-/s"),
                             (1.0, np.full((8, 8), 1e300), "dark reaches 1e+300 e-/s")):
        with pytest.raises(ParameterError, match=re.escape(name) + r": .* e- per frame of 2.83 s, more than the 1e\+09 e- "
                                                 r"accepted \(1.57e\+04 full wells of 63535 e-"):
            simulate(np.full((8, 8), rate), (3, 1, 0), seed=1, progress=False, backend="numpy", dark=dark)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sci = simulate(np.full((8, 8), 3e8), (3, 1, 0), seed=1, progress=False, backend="numpy")
    assert sci.max() == 65535


@pytest.mark.parametrize("key, match", [("ron", r"ron \[electron\] must be in \[0, 10000\]"),
                                        ("gain", r"gain \[adu / electron\] must be in \(0, 1000\]")])
def test_ramp_read_noise_and_gain_beyond_their_range_are_refused(key, match):
    """simulate(ron=1e300) wrote ramps of nothing but 0 and 65535 without a word."""
    from slicersim.errors import ParameterError
    from slicersim.products.ramps import simulate
    with pytest.raises(ParameterError, match=match):
        simulate(np.ones((8, 8)), (4, 1, 0), seed=1, out=None, progress=False, **{key: 1e300})
    with pytest.raises(ParameterError, match=match):
        RampParameters(nmd=(4, 1, 0), **{key: 1e300})


@pytest.mark.parametrize("name, file_format, says", [("raw.h5", "jwst-uncal", "writes FITS: name it .fits"),
                                                     ("raw.fits", "hdf5", "writes HDF5: name it .h5")])
def test_a_format_the_output_name_contradicts_is_refused_before_writing(tmp_path, capsys, monkeypatch, name,
                                                                       file_format, says):
    """`--format jwst-uncal --out raw.h5` wrote FITS under an HDF5 name without a word."""
    from slicersim.errors import ParameterError
    out = tmp_path / name
    with pytest.raises(ParameterError, match=rf"^out: .*{name}: file_format '{file_format}' {says}"):
        simulate(np.ones((4, 4)), (3, 1, 0), seed=1, out=str(out), file_format=file_format)
    assert not out.exists()
    np.save(tmp_path / "rate.npy", np.ones((4, 4)))
    from slicersim.app.cli import main
    monkeypatch.chdir(tmp_path)
    assert main(["ramp", "--rate", "rate.npy", "--nmd", "3", "1", "0", "--format", file_format, "--out", name]) == 2
    assert f"--out: {name}: --format '{file_format}' {says}" in capsys.readouterr().err and not out.exists()
    for name in ("raw.fits", "raw.h5"):                   # the extension alone still decides
        simulate(np.ones((4, 4)), (3, 1, 0), seed=1, out=str(tmp_path / name))
        assert (tmp_path / name).exists()
