"""The sparse ramp sampler's draws (issue 30): one Philox block per two group windows, 32-bit count
words refined to full 52-bit uniforms where a CDF value needs it, 32-bit event-0 frames."""
import math

import numpy as np
import pytest
from scipy import stats

from slicersim import rng
from slicersim.backends import opencl
from slicersim.backends.ramp import sparse_count
from slicersim.products.ramps import simulate


@pytest.mark.parametrize("lam", [0.02, 0.4, 3.0, 9.5])
def test_sparse_count_is_the_count_of_the_full_52_bit_uniform(lam):
    """For top words at (and next to) every CDF value and any low word, the refined count equals
    the inversion of the 52-bit uniform built from both words; the low word is asked for only where
    the top word leaves the count open."""
    p0 = rng.rng_exp(-np.array([lam]))[0]
    p, cdf, edges = p0, p0, []
    for k in range(1, 40):                       # the CDF values of the inversion, in its own arithmetic
        edges.append(cdf)
        p = p * lam / k
        cdf = cdf + p
    top = np.floor(np.array(edges) * 2.0**32).astype(np.int64)
    hi = np.unique(np.clip(np.concatenate([top - 1, top, top + 1]), 0, 2**32 - 1)).astype(np.uint32)
    lows = np.array([0, 1, 2**11 - 1, 2**11, 2**31, 2**32 - 2**11, 2**32 - 1], np.uint32)
    gen = np.random.default_rng(5)
    lows = np.concatenate([lows, gen.integers(0, 2**32, 9, dtype=np.uint32)])
    H, L = (a.ravel() for a in np.meshgrid(hi, lows, indexing="ij"))
    lam_v, p_v = np.full(H.size, lam), np.full(H.size, p0)
    asked = []

    def low_words(sel):
        asked.append(sel.size)
        return L[sel]
    K = sparse_count(lam_v, p_v, H, low_words)
    exact = rng.inversion_search(lam_v, p_v, rng.words_to_uniform(H, L))
    assert np.array_equal(K, exact)
    assert 0 < sum(asked) < H.size                 # refinement exercised, and only where needed
    rand = gen.integers(0, 2**32, 4000, dtype=np.uint32)
    rl = gen.integers(0, 2**32, 4000, dtype=np.uint32)
    asked.clear()
    K = sparse_count(np.full(4000, lam), np.full(4000, p0), rand, lambda sel: rl[sel])
    assert np.array_equal(K, rng.inversion_search(np.full(4000, lam), np.full(4000, p0),
                                                  rng.words_to_uniform(rand, rl)))
    assert sum(asked) == 0                         # random top words: ambiguity has probability ~1e-9


def _pooled_chi2(counts, pmf, nobs):
    """Chi-square p-value of observed counts against a pmf (tail pooled into bins of ≥ 10 expected)."""
    exp = pmf * nobs
    obs = counts[:exp.size].astype(float)
    keep = exp >= 10
    o = np.append(obs[keep], nobs - obs[keep].sum())
    e = np.append(exp[keep], nobs - exp[keep].sum())
    return stats.chisquare(o, e, ddof=0).pvalue


def test_sparse_windows_even_and_odd_follow_the_poisson_process():
    """MACC(4, 1, 3), no read noise, ADU = charge: group 0 sees the events of frame 0 (Poisson(μ));
    each later group adds those of the 3 dropped frames before it and of its own read frame
    (Poisson(4μ)), across even and odd windows (the two halves of a block).  MACC(2, 4, 0): group 0
    sums the 4 reads, Σ over its events of (4 − frame), a compound Poisson law; chi-square p > 1e-4."""
    mu, tf = 0.2, 2.83
    rate = np.full((160, 160), mu / tf)
    kw = dict(ron=0.0, bias=0.0, dark=0.0, roic_glow=0.0, sparse_max_group=64.0, backend="numpy", progress=False)
    sci = simulate(rate, (4, 1, 3), seed=11, gain=1.0, **kw)[0].reshape(4, -1).astype(int)
    npix = sci.shape[1]
    incs = [sci[0]] + [sci[g] - sci[g - 1] for g in range(1, 4)]
    for g, inc in enumerate(incs):
        lam = mu if g == 0 else 4 * mu
        pmf = stats.poisson.pmf(np.arange(30), lam)
        assert inc.min() >= 0
        assert _pooled_chi2(np.bincount(inc, minlength=30), pmf, npix) > 1e-4, g
    s0 = simulate(rate, (2, 4, 0), seed=12, gain=4.0, **kw)[0].reshape(2, -1)[0].astype(int)
    lam, kmax = 4 * mu, 25
    one = np.array([0, 0.25, 0.25, 0.25, 0.25])                  # an event at frame j is seen by 4 − j reads
    pmf, conv = np.zeros(4 * kmax + 1), np.array([1.0])
    for k in range(kmax):
        pmf[:conv.size] += stats.poisson.pmf(k, lam) * conv
        conv = np.convolve(conv, one)
    assert _pooled_chi2(np.bincount(s0, minlength=pmf.size), pmf, npix) > 1e-4
    assert abs(s0.mean() - lam * 2.5) < 4 * math.sqrt(lam * 7.5 / npix)   # E = λ E[4−j], Var = λ E[(4−j)²]


@pytest.mark.slow
@pytest.mark.needs_opencl
def test_kernel_refinement_path_gives_the_same_counts(monkeypatch):
    """A build whose every sparse lane draws the low bits of its count gives the ramps of the default
    build (bit for bit, plain and with effects): refinement reproduces the 52-bit count, and the
    default build asks for it exactly where the twin does."""
    rate = np.random.default_rng(3).uniform(0.0, 0.3, (48, 40))
    kw = dict(seed=9, nramps=2, return_dq=True, progress=False, ktc_noise=2.0, backend="opencl")
    ref = {eff: simulate(rate, (6, 3, 2), effects=eff, **kw) for eff in (None, "cosmic_rays,ipc")}
    base = opencl.precision_options
    monkeypatch.setattr(opencl, "precision_options", lambda precision: base(precision) + ("-DRAMP_REFINE_ALWAYS",))
    for eff, want in ref.items():
        got = simulate(rate, (6, 3, 2), effects=eff, **kw)
        assert all(np.array_equal(a, b) for a, b in zip(got, want)), eff
    twin = simulate(rate, (6, 3, 2), **{**kw, "backend": "numpy"})
    assert all(np.array_equal(a, b) for a, b in zip(twin, ref[None]))


def test_inversion_range_up_to_30_e_per_frame_is_poisson():
    """The dense sampler inverts the CDF up to a mean of RAMP_PTRS_MIN_MEAN = 30 e-/frame (PTRS above):
    MACC(3, 1, 0) differences of a μ = 25 pixel are single-frame increments, Poisson(25) (chi-square
    p > 1e-4, mean and variance within 4σ)."""
    from slicersim.physics.ramp import RAMP_PTRS_MIN_MEAN
    assert RAMP_PTRS_MIN_MEAN == 30.0
    mu, tf = 25.0, 2.83
    sci = simulate(np.full((100, 100), mu / tf), (3, 1, 0), seed=21, ron=0.0, bias=0.0, gain=1.0, dark=0.0,
                   roic_glow=0.0, backend="numpy", progress=False)[0].reshape(3, -1).astype(int)
    inc = np.concatenate([sci[1] - sci[0], sci[2] - sci[1]])
    pmf = stats.poisson.pmf(np.arange(80), mu)
    assert _pooled_chi2(np.bincount(inc, minlength=80), pmf, inc.size) > 1e-4
    assert abs(inc.mean() - mu) < 4 * math.sqrt(mu / inc.size)
    assert abs(inc.var() - mu) < 4 * mu * math.sqrt(2.0 / inc.size)


@pytest.mark.slow
@pytest.mark.needs_opencl
def test_kernel_equals_twin_across_the_inversion_ptrs_boundary():
    """Pixels from 5 to 60 e-/frame (inversion below 30, PTRS above), plain and with effects: the
    OpenCL kernels and the NumPy twin agree bit for bit."""
    rate = np.geomspace(5.0, 60.0, 12 * 16).reshape(12, 16) / 2.83
    rate[::5, ::3] = 0.02
    kw = dict(seed=2, return_dq=True, progress=False, ktc_noise=1.0)
    for eff in (None, "cosmic_rays,ipc"):
        a = simulate(rate, (4, 3, 1), backend="numpy", effects=eff, **kw)
        b = simulate(rate, (4, 3, 1), backend="opencl", effects=eff, **kw)
        assert all(np.array_equal(x, y) for x, y in zip(a, b)), eff
