"""The effects stage of the ramp sampler (kernels/ramp.cl -DRAMP_EFFECTS, kernels/ramp_readout.cl)
against its NumPy twin, and against the plain sampler.

Tolerance: none — both implementations use the same IEEE operations in the same order (no FMA
contraction, Philox integers), so every comparison is bit for bit.
"""
import numpy as np
import pytest

from slicersim.backends import ramp_effects as rfx
from slicersim.backends.ramp import simulate_block_numpy, simulate_block_opencl
from slicersim.physics.ramp import RampParameters, frame_mean_charge

NY, NX = 24, 40
IPC = np.array([[0.002, 0.016, 0.002], [0.016, 0.928, 0.016], [0.002, 0.016, 0.002]])


def _scene(seed=1):
    r = np.random.default_rng(seed)
    rate = np.where(r.random((NY, NX)) < 0.3, r.uniform(0, 300, (NY, NX)), r.uniform(0, 0.2, (NY, NX)))
    rate[5, 5] = 5000.0                         # reaches the full well
    p = RampParameters(nmd=(6, 4, 2), ron=10.0, ktc_noise=20.0, full_well=30000.0)
    mu = frame_mean_charge(rate, 0.01, 0.0, 0.003, p.tframe).ravel()
    dead = np.zeros(mu.size, bool)
    dead[7] = True
    k = 1500                                    # deposits, some in dropped frames and past the ramp
    dep = rfx.deposits_csr(mu.size, r.integers(0, mu.size, k), r.integers(0, p.nframes + 2, k),
                           r.uniform(10, 3000, k))
    a2, a3 = r.normal(-2e-6, 2e-7, mu.size), r.normal(1e-12, 1e-13, mu.size)
    return p, mu, dead, dep, a2, a3


def _no_effects(npix):
    return rfx.ChargeEffects(np.zeros(npix + 1, np.uint32), np.zeros(0, np.int32), np.zeros(0))


@pytest.mark.slow
@pytest.mark.parametrize("use_nl", [False, True])
def test_charge_stage_twins_bit_identical(use_nl):
    p, mu, dead, dep, a2, a3 = _scene()
    fx = rfx.ChargeEffects(*dep, a2 if use_nl else None, a3 if use_nl else None)
    ref = rfx.charge_block_numpy(mu, dead, 100, 1, 42, p, fx)
    for vw in (1, 4, 16):                       # lanes never change a pixel's numbers
        got = rfx.charge_block_opencl(mu, dead, 100, 1, 42, p, fx, vector_width=vw, workspace={})
        assert np.array_equal(ref[0], got[0]) and np.array_equal(ref[1], got[1])


@pytest.mark.parametrize("near_full_well", [False, True])
def test_charge_stage_twins_dark_windows_with_nonlinearity(near_full_well):
    """Dark pixels (most windows: no deposit, at most one event per lane, the kernel's two-level
    shortcut of the read-by-read sum) mixed with a few brighter ones and deposits: bit for bit.
    near_full_well: the two levels straddle the full well (clipping inside the shortcut)."""
    r = np.random.default_rng(7)
    p = RampParameters(nmd=(8, 8, 0), ron=10.0, full_well=30000.0)
    npix = 4096
    mu = r.uniform(0.0, 0.03, npix)
    mu[r.integers(0, npix, 40)] = r.uniform(0.1, 0.6, 40)          # a few windows with K ≥ 2
    if near_full_well:
        mu[:] = 0.0
        mu[::3] = 0.05
    dead = np.zeros(npix, bool)
    k = 30
    dep = rfx.deposits_csr(npix, r.integers(0, npix, k), r.integers(0, p.nframes, k), r.uniform(10, 3000, k))
    if near_full_well:
        dep = rfx.deposits_csr(npix, np.arange(0, npix, 5), np.zeros(npix // 5 + 1, int),
                               np.full(npix // 5 + 1, 29999.5))
    a2, a3 = r.normal(-2e-6, 2e-7, npix), r.normal(1e-12, 1e-13, npix)
    fx = rfx.ChargeEffects(*dep, a2, a3)
    ref = rfx.charge_block_numpy(mu, dead, 100, 1, 42, p, fx)
    for vw in (1, 16):
        got = rfx.charge_block_opencl(mu, dead, 100, 1, 42, p, fx, vector_width=vw, workspace={})
        assert np.array_equal(ref[0], got[0]) and np.array_equal(ref[1], got[1])


def test_neutral_effects_equal_the_plain_ramp():
    """No deposits, no nonlinearity, identity readout: the plain ramp bit for bit (same draws)."""
    p, mu, dead, *_ = _scene()
    gmean, qsat = rfx.charge_block_opencl(mu, dead, 0, 1, 42, p, _no_effects(mu.size), workspace={})
    plain = simulate_block_opencl(mu, dead, 0, 1, 42, p)
    assert np.array_equal(plain[0], simulate_block_numpy(mu, dead, 0, 1, 42, p)[0])
    for readout in (rfx.readout_numpy, rfx.readout_opencl):
        sci, gdq = readout(gmean.reshape(-1, NY, NX), qsat.reshape(-1, NY, NX), NY, 0, 0, NY, 1, 42, p)
        assert np.array_equal(sci.reshape(plain[0].shape), plain[0])
        assert np.array_equal(gdq.reshape(plain[1].shape), plain[1])


def test_deposits_add_exactly_their_charge_to_later_reads():
    """Without noise or clipping, a deposit of E e- at frame f adds E·(reads after f)/m to its group
    and E to every later group, and nothing to any other pixel."""
    p = RampParameters(nmd=(5, 3, 2), ron=0.0, full_well=1e9)
    mu = np.full(NY * NX, 0.4)
    dead = np.zeros(mu.size, bool)
    base, _ = rfx.charge_block_numpy(mu, dead, 0, 0, 7, p, _no_effects(mu.size))
    frames = [0, 2, 3, 4, 12]                   # read, read, dropped, dropped, last group's first read
    dep = rfx.deposits_csr(mu.size, [11, 11, 30, 31, 32], frames[1:] + [0], [100.0, 50.0, 7.0, 9.0, 3.0])
    got, _ = rfx.charge_block_numpy(mu, dead, 0, 0, 7, p, rfx.ChargeEffects(*dep))
    diff = got - base
    touched = {11, 30, 31, 32}
    others = [i for i in range(mu.size) if i not in touched]
    assert np.all(diff[:, others] == 0)
    # pixel 32: 3 e- at frame 0 (read 0 of group 0): all 3 reads of group 0 see it
    np.testing.assert_allclose(diff[:, 32], 3.0, rtol=0, atol=1e-9)
    # pixel 11: 100 e- at frame 2 (read 2 of group 0: 1 of 3 reads), 50 e- at frame 3 (dropped)
    np.testing.assert_allclose(diff[:, 11], [100 / 3, 150, 150, 150, 150], atol=1e-9)
    # pixel 31: 9 e- at frame 12 = group 2's... frames 0-4 g0, 5-9 g1, 10-14 g2: read 2 of group 2
    np.testing.assert_allclose(diff[:, 31], [0, 0, 3, 9, 9], atol=1e-9)


@pytest.mark.parametrize("sparse_max_group", [None, 0.0])          # sparse path, dense path
def test_nonlinearity_is_applied_to_every_read(sparse_max_group):
    """No Poisson charge (μ = 0), known deposits: group mean = (1/m) Σ_j R(Q_j) exactly."""
    p = RampParameters(nmd=(4, 3, 2), ron=0.0, full_well=1e9, sparse_max_group=sparse_max_group)
    npix = 3
    mu, dead = np.zeros(npix), np.zeros(npix, bool)
    frames = np.array([0, 1, 4, 6, 12])
    charge = np.array([1000.0, 2500.0, 4000.0, 800.0, 20000.0])
    dep = rfx.deposits_csr(npix, [1] * 5, frames, charge)
    a2, a3 = np.full(npix, -3e-6), np.full(npix, 2e-12)
    got, _ = rfx.charge_block_numpy(mu, dead, 0, 0, 3, p, rfx.ChargeEffects(*dep, a2, a3))
    ocl, _ = rfx.charge_block_opencl(mu, dead, 0, 0, 3, p, rfx.ChargeEffects(*dep, a2, a3), workspace={})
    assert np.array_equal(got, ocl)
    read_frames = [g * 5 + j for g in range(4) for j in range(3)]           # m + d = 5
    q = np.array([charge[frames <= f].sum() for f in read_frames]).reshape(4, 3)
    expected = (q + q * q * (-3e-6 + 2e-12 * q)).mean(axis=1)
    np.testing.assert_allclose(got[:, 1], expected, rtol=1e-13)
    assert np.all(got[:, [0, 2]] == 0)


def test_readout_twins_with_ipc_noise_and_bias_map():
    p, mu, dead, *_ = _scene(2)
    gmean, qsat = rfx.charge_block_numpy(mu, dead, 0, 1, 42, p, _no_effects(mu.size))
    r = np.random.default_rng(5)
    extra = r.normal(0, 3, (6, 10, NX)).astype(np.float32)
    bias = r.normal(2000, 30, (10, NX)).astype(np.float32)
    g = gmean.reshape(-1, NY, NX)[:, 9:21]
    q = qsat.reshape(-1, NY, NX)[:, 9:21]
    a = rfx.readout_numpy(g, q, 10, 1, 10, NY, 1, 42, p, ipc=IPC, extra=extra, bias_map=bias)
    b = rfx.readout_opencl(g, q, 10, 1, 10, NY, 1, 42, p, ipc=IPC, extra=extra, bias_map=bias, workspace={})
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


def test_readout_rounding_and_clipping_match_rint():
    """ramp_readout rounds as (x + 2^52) - 2^52 (PoCL's rint is scalar): ties to even, negative
    values, the uint16 ends and values past 2^52 give numpy's clipped rint bit for bit."""
    p = RampParameters(nmd=(2, 1, 0), ron=0.0, bias=0.0, gain=1.0, full_well=1e300)
    vals = np.array([0.5, 1.5, 2.5, 2.4999999999999996, 2.5000000000000004, -0.4, -0.5, -0.6, -1.5, -3e9,
                     65534.5, 65535.5, 65535.49999999999, 65536.0, 1e6, 2.0**52 - 0.5, 2.0**52 + 1, 2.0**53 + 2,
                     1e300, 0.0, 12345.5, 12346.5, 7.49999999999999, 99.5])
    nx = vals.size
    gmean = np.stack([vals, vals[::-1]])[:, None, :].copy()
    q = np.zeros(gmean.shape, np.uint8)
    a = rfx.readout_numpy(gmean, q, 1, 0, 0, 1, 0, 1, p)
    b = rfx.readout_opencl(gmean, q, 1, 0, 0, 1, 0, 1, p, workspace={})
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert np.array_equal(a[0][0, 0], np.clip(np.rint(vals), 0, 65535).astype(np.uint16))
    assert nx == a[0].shape[2]


def test_ipc_conserves_flux_away_from_edges():
    p = RampParameters(nmd=(2, 1, 0), ron=0.0, bias=0.0, gain=1.0)
    gmean = np.zeros((2, 9, 9))
    gmean[:, 4, 4] = 10000.0
    sci, _ = rfx.readout_numpy(gmean, np.zeros(gmean.shape, np.uint8), 9, 0, 0, 9, 0, 1, p, ipc=IPC)
    assert sci[0].sum() == pytest.approx(10000.0, abs=4.5)          # 9 roundings of ±0.5
    assert sci[0, 4, 5] == 160 and sci[0, 5, 5] == 20 and sci[0, 4, 4] == 9280
