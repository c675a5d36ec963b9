"""MACC up-the-ramp readout physics: times, variance models, saturation.

A MACC(n, m, d) ramp has n groups of m averaged frames with d dropped frames
between groups; ``nramps`` ramps are summed.  Times (frame time t_f):

* frames per ramp  N_f   = n (m + d) − d
* exposure / ramp  t_exp = N_f t_f
* integration      t_int = (n − 1)(m + d) t_f     (first to last group)
* group time       t_g   = (m + d) t_f
"""
from __future__ import annotations

import numpy as np

from slicersim import validation
from slicersim.errors import ReadoutError
from slicersim.physics.conventions import DEFAULT_CONVENTIONS, check_conventions, variance_gain_factor

__all__ = ["check_readout", "readout_times", "rauscher07_coefficients", "variance_rauscher07",
           "variance_kubik16", "VARIANCE_MODELS", "cell_variance_coefficients"]


def check_readout(nmd, nramps=1, min_group=2, max_group=None):
    """Validate a MACC readout (n, m, d) and a number of ramps; return ((n, m, d), nramps) as ints
    (:func:`slicersim.validation.readout` and :func:`~slicersim.validation.nramps`: ReadoutError)."""
    n, m, d = validation.readout(nmd, min_group=min_group)
    if max_group is not None and n > max_group:
        raise ReadoutError(f"readout mode nmd = ({n}, {m}, {d}): n = {n} exceeds max_group = {max_group} "
                           "(the detector's largest number of groups)")
    return (n, m, d), validation.nramps(nramps)


def readout_times(nmd, tframe):
    """Times of ONE ramp of MACC (n, m, d): ``nframes``, ``exposure_time_per_ramp``,
    ``integration_time_per_ramp`` and ``group_time`` [s].

    Vocabulary used everywhere in slicersim: ``exposure_time`` / ``integration_time``
    without a suffix are totals over all ramps; ``*_per_ramp`` are one ramp's."""
    n, m, d = nmd
    nframes = n * (m + d) - d
    return {"nframes": nframes, "exposure_time_per_ramp": nframes * tframe,
            "integration_time_per_ramp": (n - 1) * (m + d) * tframe, "group_time": (m + d) * tframe}


# --------------------------------------------------------------------------- #
#  variance models (per pixel, e- rate in, ADU² out, reference gain convention) #
# --------------------------------------------------------------------------- #
def rauscher07_coefficients(nmd, tframe):
    """(a, b) with V_R = a σ_r² + b S  [e-²] for a rate S [e-/s] (Rauscher et al. 2007, corrected).

    a = 12 (n−1) / (m n (n+1))
    b = 6 (n²+1) (n−1) t_g / (5 n (n+1)) − 2 (m²−1)(n−1) t_f / (m n (n+1))
    """
    n, m, d = (np.asarray(v, dtype=float) for v in nmd)
    tgroup = (m + d) * tframe
    a = 12.0 * (n - 1) / (m * n * (n + 1))
    b = 6.0 * (n**2 + 1) / (5.0 * n * (n + 1)) * (n - 1) * tgroup \
        - 2.0 * (m**2 - 1) * (n - 1) / (m * n * (n + 1)) * tframe
    return a, b


def variance_rauscher07(flux, nmd, tframe, ron, dark, gain=1.0, conventions=DEFAULT_CONVENTIONS):
    """Variance [ADU²] of the integrated signal over t_int for a pixel receiving ``flux`` [e-/s]
    plus ``dark`` [e-/s] (Rauscher et al. 2007 as corrected in 2010): a σ_r² + b S [e-²]
    times g² (``conventions="slicersim-1.0"``: divided by g²)."""
    a, b = rauscher07_coefficients(nmd, tframe)
    return (a * ron**2 + b * (np.asarray(flux, dtype=float) + dark)) * variance_gain_factor(gain, conventions)


def variance_kubik16(flux, nmd, tframe, ron, dark, gain=1.0, conventions=DEFAULT_CONVENTIONS):
    """Variance [ADU²] of the Kubik et al. (2016) maximum-likelihood signal estimator.

    With S_A = (flux + dark) g t_int [ADU], ĝ = S_A/(n−1), α = (1−m²)/(3m(m+d)),
    γ = 2 g² σ_r²/m, β = γ/(1+α), s_β = ĝ + β/g:
    V = [((n−1)+α) ĝ + γ/g] g · 4 s_β² / [(1+α)² g² + 4 s_β²].
    It equals Rauscher07 for n ≤ 3 in the read-noise limit and within ~4 % for
    bright pixels with few groups; for many groups the read-noise term stays at
    2σ²/m (two-point limit) where Rauscher's least-squares term falls as 12σ²/(m n).

    Physical convention: the estimator's variance in e-² (the formula with g = 1) times g²;
    ``conventions="slicersim-1.0"`` evaluates the formula with the gain as written.
    """
    if check_conventions(conventions) == "physical" and gain != 1.0:
        return variance_kubik16(flux, nmd, tframe, ron, dark, 1.0, conventions) * gain**2
    n, m, d = nmd
    tint = (n - 1) * (m + d) * tframe
    signal = (np.asarray(flux, dtype=float) + dark) * gain * tint
    gghat = signal / (n - 1)
    alpha = (1.0 - m**2) / (3.0 * m * (m + d))
    gamma = 2.0 * gain**2 * ron**2 / m
    beta = gamma / (1.0 + alpha)
    s_beta = gghat + beta / gain
    var = (((n - 1) + alpha) * gghat + gamma / gain) * gain * 4 * s_beta**2
    return var / ((1 + alpha) ** 2 * gain**2 + 4 * s_beta**2)


VARIANCE_MODELS = {"rauscher07": variance_rauscher07, "rauscher10": variance_rauscher07,
                   "kubik16": variance_kubik16}


def cell_variance_coefficients(nmd, tframe, ron, dark, gain, saturation, pixels_per_cell,
                               conventions=DEFAULT_CONVENTIONS):
    """Rauscher07 variance of one cell as V = A + B·Q [ADU²] for a cell electron rate Q [e-/s],
    and the saturation limit Qsat [e-/s/cell] (cells with Q > Qsat saturate).

    ``nmd`` may hold arrays (one entry per candidate readout).  With a, b from
    :func:`rauscher07_coefficients` and p pixels per cell:
    A = p (a σ² + b D_eff) G,  B = b G,  Qsat = p (sat / (t_int g) − D_eff), with
    G = :func:`~slicersim.physics.conventions.variance_gain_factor` (g², or 1/g² for slicersim 1.0).
    """
    n, m, d = nmd
    a, b = rauscher07_coefficients((n, m, d), tframe)
    factor = variance_gain_factor(gain, conventions)
    var_a = pixels_per_cell * (a * ron**2 + b * dark) * factor
    var_b = b * factor
    tint = (n - 1) * (m + d) * tframe
    qsat = pixels_per_cell * (saturation / (tint * gain) - dark)
    return var_a, var_b, qsat
