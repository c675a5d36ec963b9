"""Correlated read noise of an H4RG read through a SIDECAR-like ASIC (NGHXRG model).

After Rauscher (2015, PASP 127, 1144, "NGHXRG: a noise generator for Teledyne HxRG
detector arrays"; its public ``nghxrg.py`` was read to learn the clocking and the
components, no code was taken): the detector is read by ``n_outputs`` video outputs in
parallel, each a stripe of ``ncol = nx / n_outputs`` columns.  Even outputs scan their
columns left → right, odd outputs right → left (Teledyne's power-up default); rows are
read in order, bottom to top.  Each row costs ``nroh`` extra pixel times of row overhead
and each frame ``nfoh`` extra rows, so one output clocks

    row_len   = ncol + nroh                       pixel times per row
    frame_len = row_len · (ny + nfoh)             pixel times per frame
    dwell τ   = tframe / frame_len                [s] per pixel

For the Lazuli H4RG-10 (4096², 32 outputs, nroh = 12, nfoh = 1, tframe = 2.83 s):
row_len = 140, frame_len = 573 580, τ = 4.934 µs (a 202.7 kHz pixel clock), row time
690.8 µs.  The pixel (y, x) of frame f is read at t = τ·(f·frame_len + y·row_len + j(x)),
with j the position of x in its output's scan order (:meth:`ReadoutGeometry.scan_index`).

Components (all in e-, added to every read; white read noise is the ramp's ``ron``):

* correlated pink (``c_pink``): one 1/f time stream common to all outputs, each output
  seeing it in its own scan order;
* uncorrelated pink (``u_pink``): one independent 1/f stream per output;
* alternating column noise (``acn``): per output, independent 1/f streams on the even
  and on the odd pixel times (NGHXRG's ``a``/``b`` vectors at cadence 2τ, interleaved);
* picture frame (``picture_frame``): a static spatial template brighter toward the
  detector edges (:func:`picture_frame_template`, ours: NGHXRG's PCA-zero file is a
  NIRSpec measurement we do not ship) times a N(0, 1) amplitude per frame;
* pedestal drift (``pedestal``): a N(0, pedestal²) offset per output per frame.

Model PSD (one-sided, e-²/Hz, frequency f of the pixel-time stream of one output, Nyquist
f_N = 1/(2τ)).  A pink component of amplitude σ has

    S(f) = σ² / (f · ln(f_N · tframe))      for f_min ≤ f ≤ f_N,  0 otherwise,

so σ is its rms over the band [1/tframe, f_N] (the noise seen within one frame, as
NGHXRG normalises its streams per frame); the power below 1/tframe (down to f_min, the
longest time scale modelled) adds frame-to-frame drifts.  ACN's even/odd streams a, b
(cadence 2τ, Nyquist f_N/2) each have P_a(f) = σ_acn²/(f ln(f_N tframe/2)) on
[f_min, f_N/2]; their interleave is stationary with S_acn(f) = ½[P_a(f) + P_a(f_N − f)]
(the sum (a+b)/2 near 0 Hz, the alternating (a−b)/2·(−1)ⁿ near Nyquist).  One output's
stream therefore has S_out(f) = S_c(f) + S_u(f) + S_acn(f) (:func:`model_psd`).

Default amplitudes are NGHXRG's (``mknoise``: c_pink 3, u_pink 1, acn 0.5, pca0_amp 0.2,
pedestal 4 e-), which resemble JWST NIRSpec's H2RGs (Rauscher 2015, §4); no better-cited
per-component numbers for an H4RG-10 were found (Mosby et al. 2020, JATIS 6, 046001 give
totals only), so these are the defaults.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slicersim import validation
from slicersim.errors import EffectsError

__all__ = ["CorrelatedNoiseParameters", "ReadoutGeometry", "pink_psd", "acn_psd", "model_psd",
           "group_mean_variance", "group_combination_variance", "ols_slope_weights",
           "picture_frame_template", "crossover_low",
           "acn_half", "METHODS"]

#: generators of :class:`slicersim.backends.correlated_noise.CorrelatedNoise`
METHODS = ("exact", "multirate", "group", "white")


MAX_AMPLITUDE = 1e6            # e-: any larger noise amplitude is a typo, not a detector
MAX_COUNT = 1 << 16            # outputs, overhead pixels or rows


def _nonneg(name, value):
    """A number in [0, MAX_AMPLITUDE], else EffectsError naming ``correlated_noise.<name>``."""
    return validation.number(f"correlated_noise.{name}", value, low=0.0, high=MAX_AMPLITUDE, error=EffectsError)


def _posint(name, value, minimum=1):
    """An integer in [minimum, MAX_COUNT], else EffectsError naming ``correlated_noise.<name>``."""
    return validation.integer(f"correlated_noise.{name}", value, low=minimum, high=MAX_COUNT, error=EffectsError)


@validation.checked_fields(error=EffectsError)
@dataclass(kw_only=True)
class CorrelatedNoiseParameters:
    """Amplitudes [e-] and readout clocking of the correlated read noise (keyword-only).

    c_pink, u_pink, acn : rms [e-] of each pink component over [1/tframe, f_N] (see module doc);
    picture_frame : rms [e-] over the detector of the frame template per unit amplitude;
    pedestal : rms [e-] of the per-output, per-frame offset;
    f_min : Hz, lowest frequency of the 1/f spectra (default 1 mHz ≈ 1/(17 min));
    n_outputs : video outputs (32 for an H4RG-10); nroh : pixel times of row overhead;
    nfoh : rows of frame overhead.
    """

    c_pink: float = 3.0
    u_pink: float = 1.0
    acn: float = 0.5
    picture_frame: float = 0.2
    pedestal: float = 4.0
    f_min: float = 1e-3
    n_outputs: int = 32
    nroh: int = 12
    nfoh: int = 1

    def __post_init__(self):
        for name in ("c_pink", "u_pink", "acn", "picture_frame", "pedestal"):
            setattr(self, name, _nonneg(name, getattr(self, name)))
        self.f_min = _nonneg("f_min", self.f_min)
        if self.f_min <= 0:
            raise EffectsError(f"correlated noise: f_min must be > 0 Hz, got {self.f_min!r}")
        self.n_outputs = _posint("n_outputs", self.n_outputs)
        self.nroh = _posint("nroh", self.nroh, 0)
        self.nfoh = _posint("nfoh", self.nfoh, 0)


@dataclass(frozen=True)
class ReadoutGeometry:
    """Clocking of one frame: ``ny`` rows × ``nx`` columns over ``n_outputs`` outputs.

    ncol = nx / n_outputs columns per output; row_len = ncol + nroh and
    frame_len = row_len·(ny + nfoh) pixel times; dwell = tframe / frame_len [s].
    """

    ny: int
    nx: int
    n_outputs: int
    nroh: int
    nfoh: int
    tframe: float

    def __post_init__(self):
        for name in ("ny", "nx", "n_outputs"):
            _posint(name, getattr(self, name))
        if self.nx % self.n_outputs:
            raise EffectsError(f"correlated noise: nx = {self.nx} columns is not divisible by "
                               f"n_outputs = {self.n_outputs}")
        if (self.ncol + self.nroh) % 2:
            raise EffectsError(f"correlated noise: columns per output + nroh = {self.ncol} + {self.nroh} "
                               "must be even (alternating columns must keep their parity from row to row)")
        if not (math.isfinite(self.tframe) and self.tframe > 0):
            raise EffectsError(f"correlated noise: tframe must be > 0 s, got {self.tframe!r}")

    @classmethod
    def from_params(cls, params, shape, tframe):
        ny, nx = (int(v) for v in shape)
        return cls(ny, nx, params.n_outputs, params.nroh, params.nfoh, float(tframe))

    @property
    def ncol(self):
        """Columns per output."""
        return self.nx // self.n_outputs

    @property
    def row_len(self):
        """Pixel times per row (columns + row overhead)."""
        return self.ncol + self.nroh

    @property
    def frame_rows(self):
        """Row times per frame (rows + frame overhead)."""
        return self.ny + self.nfoh

    @property
    def frame_len(self):
        """Pixel times per frame and output."""
        return self.row_len * self.frame_rows

    @property
    def dwell(self):
        """Pixel dwell time τ = tframe / frame_len [s]."""
        return self.tframe / self.frame_len

    @property
    def f_nyquist(self):
        """Nyquist frequency of the pixel clock 1/(2τ) [Hz]."""
        return 0.5 / self.dwell

    @property
    def row_time(self):
        """Time of one row, row_len·τ [s]."""
        return self.row_len * self.dwell

    def scan_index(self, x):
        """Position j ∈ [0, ncol) of column(s) x in its output's scan (odd outputs reversed)."""
        x = np.asarray(x)
        out, xl = np.divmod(x, self.ncol)
        return np.where(out % 2 == 0, xl, self.ncol - 1 - xl)

    def sample_index(self, frame, y, x):
        """Pixel-time index n of pixel (y, x) in frame ``frame``: t = n·τ from the ramp's first read."""
        return (np.asarray(frame, np.int64) * self.frame_len + np.asarray(y, np.int64) * self.row_len
                + self.scan_index(x))


# --------------------------------------------------------------------------- PSD model
def pink_psd(f, sigma, geometry, f_min):
    """One-sided 1/f PSD [e-²/Hz] with rms ``sigma`` [e-] over [1/tframe, f_N], cut outside [f_min, f_N]."""
    f = np.asarray(f, dtype=float)
    norm = sigma**2 / math.log(geometry.f_nyquist * geometry.tframe)
    inside = (f >= f_min) & (f <= geometry.f_nyquist)
    return np.where(inside, norm / np.where(f > 0, f, 1.0), 0.0)


def acn_half(f, sigma, geometry, f_min):
    """P_a(f)/2: half the PSD of one of ACN's even/odd streams (cadence 2τ) [e-²/Hz]."""
    f = np.asarray(f, dtype=float)
    fa = 0.5 * geometry.f_nyquist
    norm = sigma**2 / math.log(fa * geometry.tframe)
    inside = (f >= f_min) & (f <= fa)
    return np.where(inside, 0.5 * norm / np.where(f > 0, f, 1.0), 0.0)


def acn_psd(f, sigma, geometry, f_min):
    """Stationary PSD of alternating column noise in the pixel-time stream [e-²/Hz]:
    ½[P_a(f) + P_a(f_N − f)] (the sum of the even/odd streams near 0, their difference near f_N)."""
    f = np.asarray(f, dtype=float)
    return acn_half(f, sigma, geometry, f_min) + acn_half(geometry.f_nyquist - f, sigma, geometry, f_min)


def model_psd(f, params, geometry, component="output"):
    """Model PSD [e-²/Hz, one-sided] of one output's pixel-time stream.

    component: "c_pink", "u_pink", "acn", "own" (u_pink + acn: independent per output) or
    "output" (all three; picture frame and pedestal are per-frame, not stationary streams).
    """
    fm = params.f_min
    parts = {"c_pink": lambda: pink_psd(f, params.c_pink, geometry, fm),
             "u_pink": lambda: pink_psd(f, params.u_pink, geometry, fm),
             "acn": lambda: acn_psd(f, params.acn, geometry, fm)}
    if component in parts:
        return parts[component]()
    if component == "own":
        return parts["u_pink"]() + parts["acn"]()
    if component == "output":
        return parts["c_pink"]() + parts["u_pink"]() + parts["acn"]()
    raise EffectsError(f"correlated noise: unknown PSD component {component!r}")


def crossover_low(f, nu_c):
    """Power fraction W_L²(f) given to the low-frequency generator: 1 below ν_c/2, 0 above 2ν_c,
    cos² in log f between (W_L² + W_H² = 1 with W_H² = 1 − W_L²)."""
    f = np.asarray(f, dtype=float)
    u = np.clip((np.log2(np.maximum(f, 1e-300) / nu_c) + 1.0) / 2.0, 0.0, 1.0)
    return np.cos(0.5 * np.pi * u) ** 2


def _integral(func, lo, hi, n, log):
    """Midpoint-rule ∫ func over [lo, hi] on n cells (log or linear spacing)."""
    if hi <= lo:
        return 0.0
    edges = np.geomspace(lo, hi, n + 1) if log else np.linspace(lo, hi, n + 1)
    mid = np.sqrt(edges[:-1] * edges[1:]) if log else 0.5 * (edges[:-1] + edges[1:])
    return float(np.sum(func(mid) * np.diff(edges)))


def _fejer(f, m, tframe):
    """|mean of m reads tframe apart|² transfer F_m(f) = sin²(π f m t)/(m² sin²(π f t))."""
    x = np.pi * f * tframe
    den = np.sin(x)
    small = np.abs(den) < 1e-12
    return np.where(small, 1.0, np.sin(m * x) ** 2 / (m**2 * np.where(small, 1.0, den) ** 2))


def group_mean_variance(m, params, geometry, component="output", include_frame_terms=True):
    """Variance [e-²] of the mean of m consecutive reads of one pixel (reads tframe apart).

    ∫ S_slow(f) F_m(f) df with F_m the Fejér transfer of the m-read mean.  ACN's alternating
    half aliases onto 0 Hz at the frame cadence (frame_len even: a pixel keeps its parity), so
    S_slow = S_c + S_u + P_a (its two halves).  Cells resolve F_m below 64/tframe; above,
    F_m is replaced by its period mean 1/m (S varies < 2 % over a period there).  Adds
    (pedestal² + picture_frame²)/m when include_frame_terms (independent draws per frame; the
    picture-frame template has unit rms)."""
    m = _posint("m", m)
    fm, t = params.f_min, geometry.tframe
    fn = geometry.f_nyquist
    if component == "output":
        def slow(f):
            return (pink_psd(f, params.c_pink, geometry, fm) + pink_psd(f, params.u_pink, geometry, fm)
                    + 2.0 * acn_half(f, params.acn, geometry, fm))
    else:
        def slow(f):
            psd = model_psd(f, params, geometry, component)
            if component in ("acn", "own"):
                psd = psd - acn_half(fn - f, params.acn, geometry, fm) + acn_half(f, params.acn, geometry, fm)
            return psd
    f1 = min(0.05 / (m * t), fn)
    f2 = min(64.0 / t, fn)
    var = _integral(lambda f: slow(f) * _fejer(f, m, t), fm, f1, 2000, True)
    var += _integral(lambda f: slow(f) * _fejer(f, m, t), max(fm, f1), f2, int(64 * m * 64), False)
    var += _integral(slow, max(fm, f2), fn, 4000, True) / m
    if include_frame_terms and component == "output":
        var += (params.pedestal**2 + params.picture_frame**2) / m
    return var


def ols_slope_weights(nmd, tframe):
    """w_g [1/s] of the least-squares slope Σ w_g ḡ_g of the n group means of MACC(n, m, d)
    against their mean read times t_g = (g(m + d) + (m − 1)/2)·tframe."""
    n, m, d = (int(v) for v in nmd)
    t = (np.arange(n) * (m + d) + 0.5 * (m - 1)) * float(tframe)
    dt = t - t.mean()
    return dt / np.sum(dt**2) if n > 1 else np.zeros(1)


def group_combination_variance(weights, nmd, params, geometry, picture_frame_ms=1.0, cells=32):
    """Variance of Σ_g w_g·(group mean g) of one pixel for MACC(n, m, d), e.g. the slope of
    :func:`ols_slope_weights` [e-²·w²].

    ∫ S_slow(f) F_m(f) |Σ_g w_g e^{2πi f g (m+d) tframe}|² df (S_slow, F_m as in
    :func:`group_mean_variance`): log cells below 1/(n(m+d)tframe), linear cells of 1/``cells``
    of that width up to 64/tframe, above it the transfer's period mean Σ w_g²/m; frame terms
    (pedestal² + picture_frame²·``picture_frame_ms``)·Σ w_g²/m, with ``picture_frame_ms`` the
    template's mean square over the pixels considered (1 over the whole detector).  With w = (1,)
    this is the group-mean variance (finer cells than :func:`group_mean_variance`: 5.7012 vs
    5.6979 e-² at m = 8, NGHXRG amplitudes, 4096²)."""
    n, m, d = (int(v) for v in nmd)
    w = np.asarray(weights, dtype=float)
    if w.shape != (n,):
        raise EffectsError(f"correlated noise: {w.size} weights for {n} groups")
    fm, t, fn = params.f_min, geometry.tframe, geometry.f_nyquist
    period = (m + d) * t

    def slow(f):
        return (pink_psd(f, params.c_pink, geometry, fm) + pink_psd(f, params.u_pink, geometry, fm)
                + 2.0 * acn_half(f, params.acn, geometry, fm))

    def transfer(f):
        out = np.empty(f.size)
        for i in range(0, f.size, 8192):
            fi = f[i:i + 8192]
            out[i:i + 8192] = np.abs(np.exp(2j * np.pi * np.outer(fi, np.arange(n) * period)) @ w) ** 2
        return out * _fejer(f, m, t)

    f1 = min(1.0 / (n * period), fn)
    f2 = min(64.0 / t, fn)
    var = _integral(lambda f: slow(f) * transfer(f), fm, f1, 4000, True)
    var += _integral(lambda f: slow(f) * transfer(f), max(fm, f1), f2,
                     max(1, int(math.ceil((f2 - max(fm, f1)) * n * period * cells))), False)
    white = float(np.sum(w**2)) / m
    var += _integral(slow, max(fm, f2), fn, 4000, True) * white
    var += (params.pedestal**2 + params.picture_frame**2 * picture_frame_ms) * white
    return var


def picture_frame_template(shape, width=0.04):
    """Static picture-frame pattern, unit rms over the detector, brighter toward the edges:
    exp(−d_y/w) + exp(−d_x/w) minus its mean, with d the distance to the nearest edge as a
    fraction of the detector size and w = ``width`` (our own template; NGHXRG uses a
    measured NIRSpec PCA-zero image)."""
    ny, nx = shape
    dy = np.minimum(np.arange(ny) + 0.5, ny - 0.5 - np.arange(ny)) / ny
    dx = np.minimum(np.arange(nx) + 0.5, nx - 0.5 - np.arange(nx)) / nx
    ey, ex = np.exp(-dy / width), np.exp(-dx / width)
    ey, ex = ey - ey.mean(), ex - ex.mean()
    rms = math.sqrt(float(np.mean(ey**2) + np.mean(ex**2)))
    return (ey / rms).astype(np.float32), (ex / rms).astype(np.float32)
