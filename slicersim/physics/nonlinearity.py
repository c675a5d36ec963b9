"""Classical nonlinearity of an H4RG pixel: the measured charge M(Q) falls below the accumulated
charge Q as the integrating node fills, and the pipeline's polynomial correction of it.

Model, per pixel (Q, M in e-):

    M(Q) = Q + a₂ Q² + a₃ Q³,

the leading quadratic term from the junction capacitance growing as the diode debiases, a
smaller cubic term for the shape near saturation.  The default deficit at the full well,
δ = 1 − M(Q_fw)/Q_fw = 5 %, with a 10 % (relative) pixel-to-pixel scatter, is typical of HgCdTe
H2RG/H4RG arrays (JWST User Documentation, NIRCam and NIRSpec detector linearity: a few % to
≈ 10 % near saturation; the JWST linearity reference files fit a polynomial of this kind).  With
a share s of the deficit in the cubic term (default 25 %, scatter 0.05):

    a₂ = −δ (1 − s) / Q_fw,      a₃ = −δ s / Q_fw².

M is invertible on [0, Q_fw] iff dM/dQ = 1 + 2a₂Q + 3a₃Q² > 0 there (:func:`check_invertible`).

Correction coefficients follow the JWST linearity reference-file convention consumed by
``stcal.linearity.linearity.linearity_correction``: with DN = gain · M (bias removed),

    corrected DN = Σ_k c_k DN^k  (= gain · Q),   c_0 = 0,

fitted per pixel on Chebyshev nodes of [0, gain · M(Q_fw)] (:func:`inverse_coefficients`).

Randomness: the per-pixel deficit and cubic share use the two Box–Muller normals of the
Philox block at index ``y << 16 | x`` (full-detector pixel), stream ``STREAMS["nonlinearity"]``,
so a window of the detector gets the same coefficients as the full detector.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from slicersim import rng, validation
from slicersim.rng import uniform_normal_grid
from slicersim.errors import EffectsError
from slicersim.physics.effects import STREAMS, check_number, check_shape_rows

__all__ = ["NonlinearityParameters", "nonlinearity_coefficients", "measured_charge", "linear_charge",
           "inverse_coefficients", "check_invertible", "apply_correction", "pixel_index"]

Z_MAX = 8.6                    # largest |z| of a Box–Muller pair from 53-bit uniforms: √(2·53·ln 2) = 8.57
ROWS_PER_CHUNK = 256           # rows per block of the per-pixel draws (device Philox grid)
EXACT_MAX_PIXELS = 1 << 14     # above: fits interpolated in (A₂, A₃) (inverse_coefficients)
GRID_NODES = 6                 # Chebyshev nodes per parameter axis of that interpolation
PIXELS_PER_CHUNK = 1 << 16     # pixels per cache-sized block of the per-pixel arithmetic
CHECK_MAX_PIXELS = 1 << 13     # check_invertible: above, a strided subset plus the extreme pixels


@validation.checked_fields(error=EffectsError)
@dataclass(kw_only=True)
class NonlinearityParameters:
    """deficit : 1 − M(Q_fw)/Q_fw (mean);  deficit_scatter : relative rms of the per-pixel deficit;
    cubic_share : share of the deficit in the cubic term;  cubic_share_scatter : its rms;
    degree : degree of the correction polynomial;  tolerance : largest relative error of the
    correction over [0, full well]."""

    deficit: float = 0.05
    deficit_scatter: float = 0.10
    cubic_share: float = 0.25
    cubic_share_scatter: float = 0.05
    degree: int = 5
    tolerance: float = 1e-4

    def __post_init__(self):
        self.deficit = check_number("nonlinearity.deficit", self.deficit, 0.0, 0.3)
        self.deficit_scatter = check_number("nonlinearity.deficit_scatter", self.deficit_scatter, 0.0, 1.0)
        self.cubic_share = check_number("nonlinearity.cubic_share", self.cubic_share, 0.0, 1.0)
        self.cubic_share_scatter = check_number("nonlinearity.cubic_share_scatter", self.cubic_share_scatter,
                                                0.0, 1.0)
        self.degree = validation.integer("nonlinearity.degree", self.degree, low=2, high=12, error=EffectsError)
        self.tolerance = check_number("nonlinearity.tolerance", self.tolerance, 0.0, 0.1, low_open=True)
        self._check_invertible()

    def _check_invertible(self):
        """No pixel may get a non-monotonic M(Q) on [0, Q_fw]: with δ the pixel's deficit and s its
        cubic share, dM/dQ = 1 − 2δ(1 − s)Q/Q_fw − 3δs(Q/Q_fw)² is smallest at Q_fw: 1 − 2δ − δs.  The largest
        Gaussian the Box–Muller draws can give is Z_MAX, so δ ≤ deficit·(1 + deficit_scatter·Z_MAX)
        and s ≤ min(1, cubic_share + cubic_share_scatter·Z_MAX) bound every pixel."""
        d_max = self.deficit * (1.0 + self.deficit_scatter * Z_MAX)
        s_max = min(1.0, self.cubic_share + self.cubic_share_scatter * Z_MAX)
        slope = 1.0 - 2.0 * d_max - d_max * s_max
        if slope <= 0.05:
            raise EffectsError(f"nonlinearity is not invertible: deficit {self.deficit} with scatter "
                               f"{self.deficit_scatter} (cubic share ≤ {s_max:.2f}) lets a pixel's deficit reach "
                               f"{d_max:.2f}, where M(Q) stops increasing before the full well (dM/dQ = {slope:.2f}); "
                               "lower deficit or deficit_scatter")

    def to_dict(self):
        return asdict(self)


def pixel_index(rows, nx):
    """Philox index ``y << 16 | x`` of the full-detector pixels of ``rows`` (uint64, (len(rows), nx))."""
    y = np.asarray(rows, np.uint64)[:, None]
    return (y << np.uint64(16)) | np.arange(nx, dtype=np.uint64)[None, :]


def nonlinearity_coefficients(seed, shape, params, full_well, rows=None):
    """Per-pixel (a₂ [e-⁻¹], a₃ [e-⁻²]) of M(Q) = Q + a₂Q² + a₃Q³: float64 (2, ny, nx), or
    (2, r1 − r0, nx) for ``rows`` = (r0, r1) (the same values as those rows of the full map)."""
    (ny, nx), (r0, r1) = check_shape_rows(shape, rows)
    full_well = check_number("full_well [e-]", full_well, 0.0, low_open=True)
    rng.seed_to_key(seed)
    out = np.empty((2, r1 - r0, nx))
    for c0 in range(r0, r1, ROWS_PER_CHUNK):
        c1 = min(c0 + ROWS_PER_CHUNK, r1)
        _, z = uniform_normal_grid(c1 - c0, nx, seed, STREAMS["nonlinearity"], 0, first_index=c0 << 16,
                                   row_stride=1 << 16)                   # index y << 16 | x
        deficit = params.deficit * np.maximum(1.0 + params.deficit_scatter * z[..., 0], 0.0)
        share = np.clip(params.cubic_share + params.cubic_share_scatter * z[..., 1], 0.0, 1.0)
        out[0, c0 - r0:c1 - r0] = -deficit * (1.0 - share) / full_well
        out[1, c0 - r0:c1 - r0] = -deficit * share / full_well ** 2
    return out


def measured_charge(charge, a2, a3):
    """M(Q) = Q + a₂Q² + a₃Q³ [e-] (broadcast)."""
    q = np.asarray(charge, dtype=np.float64)
    return q + q * q * (a2 + a3 * q)


def linear_charge(measured, a2, a3, iterations=4):
    """Q with M(Q) = ``measured`` [e-]: third-order series reversion Q₀ = M − a₂M² + (2a₂² − a₃)M³
    (error ≈ 5δ⁴·Q for a deficit δ) refined by ``iterations`` Newton steps (each squares the
    relative error: 4 reach machine precision for δ ≤ 0.3)."""
    m = np.asarray(measured, dtype=np.float64)
    q = m * (1.0 - m * (a2 - m * (2.0 * a2 * a2 - a3)))
    for _ in range(iterations):
        q = q - (measured_charge(q, a2, a3) - m) / (1.0 + q * (2.0 * a2 + 3.0 * a3 * q))
    return q


def _min_slope(a2, a3, full_well):
    """min over Q ∈ [0, Q_fw] of dM/dQ = 1 + 2a₂Q + 3a₃Q² (endpoints and the vertex)."""
    slope_fw = 1.0 + 2.0 * a2 * full_well + 3.0 * a3 * full_well ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        vertex = np.where(a3 > 0, -a2 / (3.0 * a3), -1.0)
    inside = (vertex > 0) & (vertex < full_well)
    slope_v = np.where(inside, 1.0 + 2.0 * a2 * vertex + 3.0 * a3 * vertex ** 2, np.inf)
    return np.minimum(np.minimum(1.0, slope_fw), slope_v)


def apply_correction(dn, coeffs, out=None):
    """Σ_k c_k DN^k (Horner, as stcal's apply_polynomial) in float64; ``out``: a float64 array of the
    broadcast shape, sharing no memory with ``dn``, to write the result into."""
    c = np.asarray(coeffs, np.float64)
    x = np.asarray(dn, np.float64)
    shape = np.broadcast_shapes(c.shape[1:], x.shape)
    if out is not None and (not isinstance(out, np.ndarray) or out.dtype != np.float64 or out.shape != shape
                            or not out.flags.writeable or np.may_share_memory(out, x) or np.may_share_memory(out, c)):
        raise ValueError(f"out must be a writeable float64 array of shape {shape} sharing no memory with dn or "
                         "coeffs (Horner reads dn after each step)")
    acc = np.multiply(c[-1], x, out=np.empty(shape) if out is None else out)
    for k in range(c.shape[0] - 2, 0, -1):          # in place: no temporary of the block per term
        acc += c[k]
        acc *= x
    acc += c[0]
    return acc


def _chebyshev_nodes(count):
    """Chebyshev–Lobatto nodes of [0, 1] (both ends included)."""
    return 0.5 - 0.5 * np.cos(np.pi * np.arange(count) / (count - 1))


def _ratio_fit(A2, A3, degree):
    """Exact per-pixel fit: b (degree, n) with Q/M ≈ Σ_k b_k t^k, t = M/M_fw, in normalised units
    (q = Q/Q_fw, m(q) = q + A₂q² + A₃q³), least squares on 4·degree Chebyshev nodes of t."""
    t = _chebyshev_nodes(4 * degree)
    pinv = np.linalg.pinv(t[:, None] ** np.arange(degree)[None, :])
    m_fw = 1.0 + A2 + A3
    m = t[:, None] * m_fw[None, :]
    q = linear_charge(m, A2[None, :], A3[None, :])
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(m > 0, q / m, 1.0)                        # Q/M → 1 at 0
    return pinv @ ratio


def _axis_nodes(values, count):
    """(nodes, lo, half-width) of a Chebyshev grid over the range of ``values`` (1 node if flat)."""
    lo, hi = float(values.min()), float(values.max())
    if hi - lo <= 1e-12 * max(abs(lo), abs(hi), 1e-300):
        return np.array([lo]), lo, 0.0
    x = np.cos(np.pi * (np.arange(count) + 0.5) / count)             # Chebyshev points of [−1, 1]
    return lo + (x + 1.0) * 0.5 * (hi - lo), lo, 0.5 * (hi - lo)


class _InterpolatedFit:
    """b(A₂, A₃) by tensor Chebyshev interpolation of exact fits at GRID_NODES² points of the
    parameter box [A₂ range] × [A₃ range] (b is analytic in A₂, A₃: for the default scatter the
    interpolation error is at the float32 rounding of the coefficients, far below the fit's)."""

    def __init__(self, A2, A3, degree, count=GRID_NODES):
        self.axes = [_axis_nodes(v, count) for v in (A2, A3)]
        g2, g3 = np.meshgrid(self.axes[0][0], self.axes[1][0], indexing="ij")
        n2, n3 = g2.shape
        values = _ratio_fit(g2.ravel(), g3.ravel(), degree).reshape(degree, n2, n3)
        inv = [np.ones((1, 1)) if half == 0.0 else
               np.linalg.inv(np.polynomial.chebyshev.chebvander((nodes - lo) / half - 1.0, nodes.size - 1))
               for nodes, lo, half in self.axes]
        cheb = np.einsum("ai,kij,bj->kab", inv[0], values, inv[1])     # Chebyshev coefficients
        self.degree, self.n2, self.n3 = degree, n2, n3
        self.matrix = np.ascontiguousarray(cheb.transpose(1, 0, 2).reshape(n2, degree * n3))

    def _basis(self, v, axis):
        nodes, lo, half = self.axes[axis]
        if half == 0.0:
            return np.ones((v.size, 1))
        return np.polynomial.chebyshev.chebvander((v - lo) / half - 1.0, nodes.size - 1)

    def __call__(self, A2, A3):
        w = np.einsum("pi,ij->pj", self._basis(A2, 0), self.matrix).reshape(-1, self.degree, self.n3)
        return np.einsum("pkj,pj->kp", w, self._basis(A3, 1))


def inverse_coefficients(a2, a3, full_well, gain, degree=5, tolerance=1e-4):
    """Correction coefficients (JWST linearity reference convention), float32 (degree + 1, ...):
    corrected DN = Σ c_k DN^k with DN = gain · M(Q) (bias removed) gives gain · Q, c₀ = 0.

    Per pixel the ratio Q/M is fitted as a polynomial of degree − 1 in t = DN/DN_fw by least
    squares on 4·degree Chebyshev nodes of [0, 1]; then c_{k+1} = b_k / DN_fw^k.  Above
    EXACT_MAX_PIXELS pixels the fits b(A₂, A₃) (A₂ = a₂Q_fw, A₃ = a₃Q_fw²) are interpolated from
    exact ones on a GRID_NODES² Chebyshev grid of the parameter box.  The result is checked
    (:func:`check_invertible`): relative error < ``tolerance`` on [0, full well].
    """
    a2, a3 = np.asarray(a2, np.float64), np.asarray(a3, np.float64)
    full_well = check_number("full_well [e-]", full_well, 0.0, low_open=True)
    gain = check_number("gain [ADU/e-]", gain, 0.0, low_open=True)
    degree = validation.integer("nonlinearity.degree", degree, low=2, high=12, error=EffectsError)
    if a2.shape != a3.shape:
        raise EffectsError(f"a2 and a3 must have the same shape, got {a2.shape} and {a3.shape}")
    check_invertible(a2, a3, full_well)
    A2, A3 = a2.reshape(-1) * full_well, a3.reshape(-1) * full_well ** 2
    fit = (lambda x, y: _ratio_fit(x, y, degree)) if A2.size <= EXACT_MAX_PIXELS else _InterpolatedFit(A2, A3, degree)
    out = np.empty((degree + 1, A2.size), np.float32)
    out[0] = 0.0
    for p0 in range(0, A2.size, PIXELS_PER_CHUNK):                  # cache-sized blocks
        sl = slice(p0, p0 + PIXELS_PER_CHUNK)
        b = fit(A2[sl], A3[sl])
        dn_fw = gain * full_well * (1.0 + A2[sl] + A3[sl])
        inv_dn = 1.0 / dn_fw
        scale = np.ones_like(dn_fw)
        for k in range(degree):                                      # gain·Q = DN · Σ b_k (DN/DN_fw)^k
            out[k + 1, sl] = b[k] * scale
            scale *= inv_dn
    coeffs = out.reshape((degree + 1,) + a2.shape)
    check_invertible(a2, a3, full_well, coeffs=coeffs, gain=gain, tolerance=tolerance)
    return coeffs


def check_invertible(a2, a3, full_well, coeffs=None, gain=1.0, tolerance=1e-4, samples=33):
    """EffectsError unless dM/dQ > 0 on [0, full well] for every pixel and, if ``coeffs`` is given,
    the correction of gain · M(Q) is within ``tolerance`` (relative) of gain · Q on ``samples``
    points of [0, full well] (float32 coefficients evaluated in float64).  Above CHECK_MAX_PIXELS
    pixels the accuracy is checked on a strided subset of that many plus the pixels of extreme
    a₂ and a₃ (the error is a smooth function of (a₂, a₃)).  Returns the largest relative error
    (0 without coeffs)."""
    a2, a3 = np.asarray(a2, np.float64), np.asarray(a3, np.float64)
    if not (np.all(np.isfinite(a2)) and np.all(np.isfinite(a3))):
        raise EffectsError("nonlinearity coefficients must be finite")
    flat2, flat3 = a2.reshape(-1), a3.reshape(-1)
    bad = np.concatenate([np.flatnonzero(_min_slope(flat2[p0:p0 + PIXELS_PER_CHUNK], flat3[p0:p0 + PIXELS_PER_CHUNK],
                                                    full_well) <= 0.0) + p0
                          for p0 in range(0, flat2.size, PIXELS_PER_CHUNK)] + [np.zeros(0, np.int64)])
    if bad.size:
        raise EffectsError(f"nonlinearity is not invertible: dM/dQ ≤ 0 within [0, {full_well:g}] e- for "
                           f"{bad.size} pixel(s) (first: flat index {bad[0]}, a2 = {flat2[bad[0]]:.4g}, "
                           f"a3 = {flat3[bad[0]]:.4g}); lower the deficit")
    if coeffs is None:
        return 0.0
    c = np.asarray(coeffs).reshape(np.shape(coeffs)[0], -1)
    if c.shape[1] != flat2.size:
        raise EffectsError(f"coeffs must have one column per pixel ({flat2.size}), got shape {np.shape(coeffs)}")
    pixels = np.arange(flat2.size)
    if flat2.size > CHECK_MAX_PIXELS:                                # strided subset + extreme pixels
        extremes = [np.argmin(flat2), np.argmax(flat2), np.argmin(flat3), np.argmax(flat3)]
        pixels = np.unique(np.concatenate([pixels[::-(-flat2.size // CHECK_MAX_PIXELS)], extremes]))
    q = np.linspace(0.0, full_well, samples)[1:, None]
    b2, b3 = flat2[None, pixels], flat3[None, pixels]
    dn = gain * measured_charge(q, b2, b3)
    corrected = apply_correction(dn, c[:, None, pixels].astype(np.float64))
    worst = float(np.max(np.abs(corrected / (gain * q) - 1.0)))
    if not worst < tolerance:
        raise EffectsError(f"nonlinearity correction misses its tolerance: relative error {worst:.3g} ≥ "
                           f"{tolerance:g} on [0, {full_well:g}] e- (raise nonlinearity.degree or lower the deficit)")
    return worst
