"""Gaussian line-spread function along the wavelength axis (NumPy; the OpenCL path is
:func:`slicersim.backends.convolution.apply_lsf`).

σ is in bins.  A constant σ is a correlation with the normalised discrete
Gaussian exp(−k²/2σ²), |k| ≤ h = int(truncate σ + ½), with "reflect" edges
(… x1 x0 | x0 x1 …): scipy's ``gaussian_filter1d``.  A σ per bin is the
flux-conserving scatter form :func:`lsf_matrix` (each input bin spreads its own
content), which equals the constant form when σ is constant.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse
from scipy.ndimage import correlate1d

from slicersim import validation
from slicersim.errors import ParameterError

__all__ = ["lsf_weights", "lsf_index_weights", "reflect_index", "lsf_matrix", "apply_lsf",
           "check_sigma"]


def lsf_weights(sigma_bins, truncate=4.0):
    """(offsets, weights): normalised discrete Gaussian weights for offsets −h…h,
    h = int(truncate σ + ½); σ ≤ 0 gives ([0], [1])."""
    half = int(truncate * float(sigma_bins) + 0.5) if sigma_bins > 0 else 0
    if half == 0:                     # σ → 0 (σ² may underflow): the identity
        return np.array([0]), np.array([1.0])
    offsets = np.arange(-half, half + 1)
    w = np.exp(-0.5 * offsets**2 / float(sigma_bins) ** 2)
    return offsets, w / w.sum()


def reflect_index(t, n):
    """Fold unfolded positions t onto [0, n) with scipy's 'reflect' (… x1 x0 | x0 x1 …)."""
    m = np.mod(t, 2 * n)
    return np.where(m >= n, 2 * n - 1 - m, m)


def lsf_index_weights(nbins, sigma_bins, truncate=4.0):
    """(index, weight) arrays of shape (nbins, ntaps) for the LSF with reflect boundaries:
    out[i] = Σ_k weight[i, k] · in[index[i, k]]."""
    offsets, w = lsf_weights(sigma_bins, truncate)
    idx = reflect_index(np.arange(nbins)[:, None] + offsets[None, :], nbins)
    return idx, np.broadcast_to(w, idx.shape)


def check_sigma(sigma_bins, n, truncate):
    """σ [bins] per bin as a float64 array of length ``n`` (a scalar is broadcast), finite and
    ≥ 0, after checking ``truncate`` (finite, ≥ 0); else :class:`~slicersim.errors.ParameterError`."""
    validation.number("truncate", truncate, low=0.0)
    sig = validation.array("sigma_bins [bins]", sigma_bins, ndim=(0, 1), low=0.0)
    if sig.ndim == 0:
        return np.full(n, float(sig))
    if sig.shape != (n,):
        raise ParameterError(f"sigma_bins must be a float or an array of length {n} (the λ axis), "
                             f"got shape {sig.shape}")
    return sig


def lsf_matrix(sigma_bins, n, truncate=4.0):
    """Flux-conserving LSF matrix M (n × n, scipy.sparse CSR): out = M @ in along λ.

    Input bin j spreads its content over unfolded positions j + m, |m| ≤ r_j =
    int(truncate σ_j + 0.5), with weights exp(−m²/2σ_j²) normalised to 1; positions
    outside [0, n) are folded back with the 'reflect' rule (repeatedly when r_j > n),
    so every column of M sums to 1 and Σ_λ is conserved exactly.

    For a constant σ, M is symmetric (the reflect images of j are j + 2nt and
    −1 − j + 2nt, and the weights depend on |k − image|), so this scatter form equals
    scipy's gather form ``gaussian_filter1d(mode="reflect")`` everywhere, edges included.
    Cost and memory ∝ Σ_j (2 r_j + 1): σ of a few thousand bins is fine.
    """
    sig = check_sigma(sigma_bins, n, truncate)
    radius = np.floor(truncate * sig + 0.5).astype(np.int64)
    rmax = int(radius.max()) if n else 0
    m = np.arange(-rmax, rmax + 1, dtype=np.float64)
    rows, cols, vals = [], [], []
    step = max(1, int(4e6 // (2 * rmax + 1)))
    with np.errstate(divide="ignore", invalid="ignore"):
        for j0 in range(0, n, step):
            j = np.arange(j0, min(n, j0 + step))
            s = sig[j][:, None]
            w = np.where(m == 0, 1.0, np.exp(-0.5 * (m / s) ** 2))
            w[np.abs(m)[None, :] > radius[j][:, None]] = 0.0
            w /= w.sum(axis=1, keepdims=True)
            keep = w > 0
            t = (j[:, None] + m.astype(np.int64)[None, :])
            rows.append(reflect_index(t[keep], n))
            cols.append(np.broadcast_to(j[:, None], w.shape)[keep])
            vals.append(w[keep])
    if n == 0:
        return scipy.sparse.csr_matrix((0, 0))
    M = scipy.sparse.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                                shape=(n, n)).tocsr()
    M.sum_duplicates()
    M.sort_indices()
    return M


def apply_lsf(values, sigma_bins, axis=0, truncate=4.0):
    """Gaussian LSF along ``axis`` (σ in bins, a float or one per bin; see the module doc).

    The NumPy twin of :func:`slicersim.backends.convolution.apply_lsf`.  σ = 0
    returns a copy of the input."""
    values = np.asarray(values, dtype=float)
    if np.ndim(sigma_bins) == 0:
        if sigma_bins <= 0:
            return values.copy()
        return correlate1d(values, lsf_weights(sigma_bins, truncate)[1], axis=axis, mode="reflect")
    axis = int(axis) % values.ndim
    n = values.shape[axis]
    sig = check_sigma(sigma_bins, n, truncate)
    if not np.any(sig > 0):
        return values.copy()
    M = lsf_matrix(sig, n, truncate)
    moved = np.moveaxis(values, axis, 0)
    return np.moveaxis((M @ moved.reshape(n, -1)).reshape(moved.shape), 0, axis)
