"""Counter-based random numbers: Philox4x32-10 and the draws built on it (NumPy reference).

Every draw is a pure function of ``(seed, index, stream, draw)``: no state, so
any chunking, ordering or device gives the same numbers.  The OpenCL twin is
``kernels/philox.cl`` (+ ``kernels/noise.cl`` for Poisson); both use only
IEEE-754 +, −, ×, ÷, √, floor and exact bit manipulations (no libm log, exp
or cos, whose last bit differs between libraries), with no FMA contraction,
so the two implementations agree **bit for bit**.

Keying (Salmon et al. 2011, Random123):

* key     = (seed mod 2³², seed div 2³²)            — seed ∈ [0, 2⁶⁴)
* counter = (index mod 2³², index div 2³², stream, draw)
  — index: element (voxel, pixel) ∈ [0, 2⁶⁴); stream: e.g. a ramp or a
  purpose ∈ [0, 2³²); draw: successive attempts of a rejection sampler.

One Philox block (4 × 32 bits) gives two uniforms (words 0–1 and 2–3, 52
bits each, u = (2x + 1)·2⁻⁵³ ∈ (0, 1) exactly, never 0 or 1), and hence two
Box–Muller Gaussians.

This module sits low in the layers (below ``physics``): it imports only NumPy.  The grids of
draws that physics needs (:func:`uniform_normal_grid`, :func:`uniform_normal_draw`) are computed
here in NumPy unless a faster engine with the same keys is registered with
:func:`register_grid_engine`; :mod:`slicersim.backends.noise` registers its OpenCL kernel on
import (bit-identical, so the engine changes the speed, never the numbers).
"""
from __future__ import annotations

import numpy as np

from slicersim import validation
from slicersim.errors import ParameterError

__all__ = ["PHILOX_M0", "PHILOX_M1", "PHILOX_W0", "PHILOX_W1", "PTRS_MIN_MEAN",
           "philox4x32", "seed_to_key", "random_words", "words_to_uniform", "uniform", "normal",
           "poisson", "rng_log", "rng_exp", "sincos_2pi", "log_factorial", "check_stream", "check_grid", "grid_indices",
           "uniform_normal_grid", "uniform_normal_draw", "register_grid_engine"]

PHILOX_M0, PHILOX_M1 = 0xD2511F53, 0xCD9E8D57      # round multipliers
PHILOX_W0, PHILOX_W1 = 0x9E3779B9, 0xBB67AE85      # Weyl key increments
PTRS_MIN_MEAN = 10.0                               # Poisson: inversion below, PTRS at and above
PTRS_MAX_ATTEMPTS = 1000                           # never reached in practice (P ≈ 0.1^1000)
_MASK32 = np.uint64(0xFFFFFFFF)
_h = float.fromhex

# --- constants (same hex literals as kernels/philox.cl and kernels/noise.cl) ------------------
LN2_HI, LN2_LO = _h("0x1.62e42fee00000p-1"), _h("0x1.a39ef35793c76p-33")   # ln 2 = HI + LO
SQRT_HALF = _h("0x1.6a09e667f3bcdp-1")
TWO_PI = _h("0x1.921fb54442d18p+2")
INV_LN2 = _h("0x1.71547652b82fep+0")
HALF_LOG_2PI = _h("0x1.d67f1c864beb4p-1")
# 1/(2k+1), k = 11 … 1 (atanh series of log)
_LOG_C = [_h(x) for x in ("0x1.642c8590b2164p-5", "0x1.8618618618618p-5", "0x1.af286bca1af28p-5",
                          "0x1.e1e1e1e1e1e1ep-5", "0x1.1111111111111p-4", "0x1.3b13b13b13b14p-4",
                          "0x1.745d1745d1746p-4", "0x1.c71c71c71c71cp-4", "0x1.2492492492492p-3",
                          "0x1.999999999999ap-3", "0x1.5555555555555p-2")]
# (−1)ⁿ/(2n)!, n = 9 … 1 and (−1)ⁿ/(2n+1)!, n = 9 … 1
_COS_C = [_h(x) for x in ("-0x1.6827863b97d97p-53", "0x1.ae7f3e733b81fp-45", "-0x1.93974a8c07c9dp-37",
                          "0x1.1eed8eff8d898p-29", "-0x1.27e4fb7789f5cp-22", "0x1.a01a01a01a01ap-16",
                          "-0x1.6c16c16c16c17p-10", "0x1.5555555555555p-5", "-0x1.0000000000000p-1")]
_SIN_C = [_h(x) for x in ("-0x1.2f49b46814157p-57", "0x1.952c77030ad4ap-49", "-0x1.ae7f3e733b81fp-41",
                          "0x1.6124613a86d09p-33", "-0x1.ae64567f544e4p-26", "0x1.71de3a556c734p-19",
                          "-0x1.a01a01a01a01ap-13", "0x1.1111111111111p-7", "-0x1.5555555555555p-3")]
# 1/n!, n = 13 … 2 (Taylor series of exp)
_EXP_C = [_h(x) for x in ("0x1.6124613a86d09p-33", "0x1.1eed8eff8d898p-29", "0x1.ae64567f544e4p-26",
                          "0x1.27e4fb7789f5cp-22", "0x1.71de3a556c734p-19", "0x1.a01a01a01a01ap-16",
                          "0x1.a01a01a01a01ap-13", "0x1.6c16c16c16c17p-10", "0x1.1111111111111p-7",
                          "0x1.5555555555555p-5", "0x1.5555555555555p-3", "0x1.0000000000000p-1")]
# Stirling series of ln Γ(x): coefficients of x⁻¹³ … x⁻¹ (Horner in 1/x²)
_STIRLING_C = [_h(x) for x in ("0x1.a41a41a41a41ap-8", "-0x1.f6ab0d9993c7dp-10", "0x1.b951e2b18ff23p-11",
                               "-0x1.3813813813814p-11", "0x1.a01a01a01a01ap-11", "-0x1.6c16c16c16c17p-9",
                               "0x1.5555555555555p-4")]
# ln k! for k = 0 … 9
_LOG_FACTORIAL = np.array([_h(x) for x in (
    "0x0.0p+0", "0x0.0p+0", "0x1.62e42fefa39ecp-1", "0x1.cab0bfa2a2004p+0", "0x1.96ca77c922cf7p+1",
    "0x1.326643c4479cap+2", "0x1.a51273acf01cbp+2", "0x1.10ce1f32dcc30p+3", "0x1.5358e82fcb70cp+3",
    "0x1.99a8921a7f7cep+3")])


# --------------------------------------------------------------------------- Philox
def philox4x32(counter, key, rounds=10):
    """Philox4x32 block function (Salmon et al. 2011).

    counter : (..., 4) uint32;  key : (..., 2) uint32 (broadcast against counter)
    Returns (..., 4) uint32.
    """
    ctr = np.asarray(counter, dtype=np.uint32).astype(np.uint64)
    k = np.broadcast_to(np.asarray(key, dtype=np.uint32), ctr.shape[:-1] + (2,)).astype(np.uint64)
    c0, c1, c2, c3 = (ctr[..., i] for i in range(4))
    k0, k1 = k[..., 0].copy(), k[..., 1].copy()
    m0, m1 = np.uint64(PHILOX_M0), np.uint64(PHILOX_M1)
    w0, w1 = np.uint64(PHILOX_W0), np.uint64(PHILOX_W1)
    s32 = np.uint64(32)
    for r in range(rounds):
        if r:
            k0 = (k0 + w0) & _MASK32
            k1 = (k1 + w1) & _MASK32
        p0 = m0 * c0                                  # exact 64-bit products
        p1 = m1 * c2
        c0, c1, c2, c3 = ((p1 >> s32) ^ c1 ^ k0, p1 & _MASK32, (p0 >> s32) ^ c3 ^ k1, p0 & _MASK32)
    return np.stack([c0, c1, c2, c3], axis=-1).astype(np.uint32)


def seed_to_key(seed):
    """(key0, key1) uint32 of an integer seed in [0, 2⁶⁴) (ParameterError naming ``seed`` otherwise)."""
    if isinstance(seed, np.random.Generator):
        raise ParameterError("seed must be an integer in [0, 2**64) here, got a numpy Generator")
    seed = validation.seed(seed, allow_none=False)
    return np.array([seed & 0xFFFFFFFF, seed >> 32], dtype=np.uint32)


def _check_word(value, name):
    """An integer in [0, 2³²) (a Philox stream or draw number)."""
    return validation.integer(name, value, low=0, high=2**32 - 1)


def random_words(seed, index, stream=0, draw=0):
    """Philox block for counter (index lo, index hi, stream, draw): (..., 4) uint32."""
    key = seed_to_key(seed)
    index = np.asarray(index, dtype=np.uint64)
    ctr = np.empty(index.shape + (4,), np.uint64)
    ctr[..., 0] = index & _MASK32
    ctr[..., 1] = index >> np.uint64(32)
    ctr[..., 2] = _check_word(stream, "stream")
    ctr[..., 3] = draw if np.ndim(draw) else _check_word(draw, "draw")
    return philox4x32(ctr, key)


def words_to_uniform(hi, lo):
    """52-bit uniform u = (2x + 1)·2⁻⁵³ ∈ (0, 1), x = hi·2²⁰ + lo div 2¹² (exact)."""
    x = (np.asarray(hi, np.uint64) << np.uint64(20)) | (np.asarray(lo, np.uint64) >> np.uint64(12))
    return (x * np.uint64(2) + np.uint64(1)).astype(np.float64) * 2.0**-53


def uniform(seed, index, stream=0, draw=0):
    """Two independent uniforms in (0, 1) per index: (..., 2) float64."""
    w = random_words(seed, index, stream, draw)
    return np.stack([words_to_uniform(w[..., 0], w[..., 1]), words_to_uniform(w[..., 2], w[..., 3])], -1)


def normal(seed, index, stream=0, draw=0):
    """Two independent N(0, 1) draws per index (Box–Muller cos and sin branches): (..., 2)."""
    u = uniform(seed, index, stream, draw)
    return _box_muller(u[..., 0], u[..., 1])


def _box_muller(u1, u2):
    radius = np.sqrt(-2.0 * rng_log(u1))
    c, s = sincos_2pi(u2)
    return np.stack([radius * c, radius * s], -1)


# --------------------------------------------------------------------------- elementary functions
def _horner(coeffs, x):
    acc = np.full_like(x, coeffs[0])
    for c in coeffs[1:]:
        acc = acc * x + c
    return acc


def rng_log(u):
    """Natural log of positive normal doubles, ≤ 2 ulp; bit-identical to ``rng_log`` in philox.cl.

    u = m·2ᵉ with m ∈ [√½, √2); log m = 2 atanh s, s = (m − 1)/(m + 1), series to s²³.
    """
    u = np.asarray(u, dtype=np.float64)
    bits = u.view(np.int64)
    e = ((bits >> 52) & 0x7FF) - 1022
    m = ((bits & 0x000FFFFFFFFFFFFF) | 0x3FE0000000000000).view(np.float64)   # [0.5, 1)
    low = m < SQRT_HALF
    m = np.where(low, m + m, m)
    e = (e - low).astype(np.float64)
    s = (m - 1.0) / (m + 1.0)
    s2 = s * s
    logm = 2.0 * s + (2.0 * s) * (s2 * _horner(_LOG_C, s2))
    return e * LN2_HI + (e * LN2_LO + logm)


def rng_exp(x):
    """exp(x) for |x| < 700, ≤ 2 ulp; bit-identical to ``rng_exp`` in noise.cl."""
    x = np.asarray(x, dtype=np.float64)
    n = np.floor(x * INV_LN2 + 0.5)
    r = (x - n * LN2_HI) - n * LN2_LO
    p = 1.0 + r * (1.0 + r * _horner(_EXP_C, r))
    return np.ldexp(p, n.astype(np.int32))


def sincos_2pi(u):
    """(cos 2πu, sin 2πu) with exact quarter-turn reduction; bit-identical to philox.cl."""
    u = np.asarray(u, dtype=np.float64)
    q = np.floor(4.0 * u + 0.5)
    t = (u - 0.25 * q) * TWO_PI                                  # |t| ≤ π/4
    t2 = t * t
    c = 1.0 + t2 * _horner(_COS_C, t2)
    s = t + t * (t2 * _horner(_SIN_C, t2))
    k = np.mod(q, 4.0)
    cos = np.where(k == 0, c, np.where(k == 1, -s, np.where(k == 2, -c, s)))
    sin = np.where(k == 0, s, np.where(k == 1, c, np.where(k == 2, -s, -c)))
    return cos, sin


def log_factorial(k):
    """ln k! for integer-valued doubles k ≥ 0: table below 10, Stirling series (error < 1e-17) above."""
    k = np.asarray(k, dtype=np.float64)
    small = k < 10.0
    x = np.where(small, 11.0, k + 1.0)
    r = 1.0 / x
    series = r * _horner(_STIRLING_C, r * r)
    big = ((x - 0.5) * rng_log(x) - x) + (HALF_LOG_2PI + series)
    return np.where(small, _LOG_FACTORIAL[np.where(small, k, 0.0).astype(np.int64)], big)


# --------------------------------------------------------------------------- Poisson
def poisson(mean, seed, index=None, stream=0):
    """Poisson draws with expectation ``mean`` (≥ 0), as float64 (exact integers; NaN for NaN/inf mean).

    mean < 10: inversion (sequential search of the CDF, one uniform, draw 0);
    mean ≥ 10: PTRS transformed rejection (Hörmann 1993), attempt a uses draw a.
    ``index`` (default ``arange(mean.size)`` in C order) keys each element.
    """
    mean = validation.array("Poisson mean", mean, finite=False)
    if np.any(mean < 0):
        raise ParameterError(f"Poisson mean must be ≥ 0 ({np.count_nonzero(mean < 0)} negative value(s))")
    flat = mean.ravel()
    index = np.arange(flat.size, dtype=np.uint64) if index is None else \
        np.broadcast_to(np.asarray(index, np.uint64), mean.shape).ravel()
    out = np.full(flat.shape, np.nan)
    small = np.nonzero(flat < PTRS_MIN_MEAN)[0]
    large = np.nonzero((flat >= PTRS_MIN_MEAN) & np.isfinite(flat))[0]
    if small.size:
        out[small] = _poisson_inversion(flat[small], seed, index[small], stream)
    if large.size:
        out[large] = _poisson_ptrs(flat[large], seed, index[large], stream)
    return out.reshape(mean.shape)


def _poisson_inversion(mu, seed, index, stream):
    u = uniform(seed, index, stream, 0)[..., 0]
    return inversion_search(mu, rng_exp(-mu), u)


def inversion_search(mu, p0, u):
    """Poisson(mu) by sequential search of the CDF from P(0) = p0 = e^−mu, one uniform u each
    (vectorised twin of the OpenCL loops; the same operations in the same order)."""
    p = np.array(p0, dtype=np.float64, copy=True)
    cdf = p.copy()
    k = np.zeros_like(mu)
    todo = np.nonzero((u > cdf) & (p > 0.0))[0]
    while todo.size:
        k[todo] += 1.0
        p[todo] = p[todo] * mu[todo] / k[todo]
        cdf[todo] = cdf[todo] + p[todo]
        todo = todo[(u[todo] > cdf[todo]) & (p[todo] > 0.0)]
    return k


def _poisson_ptrs(mu, seed, index, stream):
    out = np.full_like(mu, np.nan)
    smu = np.sqrt(mu)
    log_mu = rng_log(mu)
    b = 0.931 + 2.53 * smu
    a = -0.059 + 0.02483 * b
    log_inv_alpha = rng_log(1.1239 + 1.1328 / (b - 3.4))
    vr = 0.9277 - 3.6224 / (b - 2.0)
    todo = np.arange(mu.size)
    for attempt in range(PTRS_MAX_ATTEMPTS):
        if not todo.size:
            break
        uv = uniform(seed, index[todo], stream, attempt)
        U, V = uv[:, 0] - 0.5, uv[:, 1]
        us = 0.5 - np.abs(U)
        ai, bi, mi = a[todo], b[todo], mu[todo]
        k = np.floor((2.0 * ai / us + bi) * U + mi + 0.43)
        quick = (us >= 0.07) & (V <= vr[todo])
        reject = (k < 0.0) | ((us < 0.013) & (V > us))
        lhs = (rng_log(V) + log_inv_alpha[todo]) - rng_log(ai / (us * us) + bi)
        rhs = (k * log_mu[todo] - mi) - log_factorial(np.maximum(k, 0.0))
        accept = quick | (~reject & (lhs <= rhs))
        out[todo[accept]] = k[accept]
        todo = todo[~accept]
    return out


# --------------------------------------------------------------------------- grids of draws
#: engine(rows, ncols, seed, stream, draw, first_index, row_stride) -> (uniforms, normals), or None
_grid_engine = None


def register_grid_engine(engine):
    """Compute :func:`uniform_normal_grid` with ``engine`` (None: NumPy here) and return the previous
    engine.  ``engine(rows, ncols, seed, stream, draw, first_index, row_stride)`` must return the
    same (uniforms, normals) arrays as the NumPy path, bit for bit: it is called with checked
    arguments.  :mod:`slicersim.backends.noise` registers its device kernel on import."""
    global _grid_engine
    previous, _grid_engine = _grid_engine, engine
    return previous


def check_stream(stream):
    """``stream`` as an int in [0, 2³²)."""
    return _check_word(stream, "stream")


def check_grid(rows, ncols, first_index=0, row_stride=None):
    """(rows, ncols, first_index, row_stride) as ints (row_stride default ncols) whose Philox
    indices ``first_index + r·row_stride + c`` stay in [0, 2⁶⁴)."""
    rows, ncols = validation.integer("rows", rows, low=0), validation.integer("ncols", ncols, low=0)
    first_index = validation.integer("first_index", first_index, low=0)
    row_stride = ncols if row_stride is None else validation.integer("row_stride", row_stride, low=0)
    if first_index + max(rows - 1, 0) * row_stride + ncols > 2**64:
        raise ParameterError(f"uniform_normal_grid: rows = {rows}, ncols = {ncols}, row_stride = {row_stride} "
                             f"and first_index = {first_index} reach Philox indices beyond 2**64")
    return rows, ncols, first_index, row_stride


def grid_indices(rows, ncols, first_index, row_stride):
    """(rows, ncols) uint64 Philox indices ``first_index + r·row_stride + c`` (checked arguments)."""
    return (np.uint64(first_index) + np.arange(rows, dtype=np.uint64)[:, None] * np.uint64(row_stride)
            + np.arange(ncols, dtype=np.uint64)[None, :])


def uniform_normal_grid(rows, ncols, seed, stream=0, draw=0, *, first_index=0, row_stride=None):
    """(uniforms, normals), each (rows, ncols, 2) float64: element (r, c) keyed by Philox index
    ``first_index + r·row_stride + c`` (row_stride default ncols), e.g. a block of detector rows
    keyed ``y << 16 | x`` with first_index = y0 << 16 and row_stride = 2¹⁶.  Equal to
    :func:`uniform` / :func:`normal` of those indices (on the registered engine when there is one)."""
    seed_to_key(seed)
    stream = check_stream(stream)
    rows, ncols, first_index, row_stride = check_grid(rows, ncols, first_index, row_stride)
    if _grid_engine is not None and rows * ncols > 0:
        return _grid_engine(rows, ncols, int(seed), stream, draw, first_index, row_stride)
    index = grid_indices(rows, ncols, first_index, row_stride)
    return uniform(seed, index, stream, draw), normal(seed, index, stream, draw)


def uniform_normal_draw(n, seed, stream=0, draw=0, *, first_index=0):
    """(uniforms, normals), each (n, 2) float64, for indices first_index … first_index + n − 1."""
    u, z = uniform_normal_grid(1, n, seed, stream, draw, first_index=first_index)
    return u[0], z[0]
