"""Inter-pixel capacitance (IPC): a 3×3 kernel spreading each pixel's signal onto its neighbours.

The voltage read at a pixel is a weighted sum of the charge of the pixel and its neighbours,
through the capacitive coupling of adjacent nodes (Moore, Ninkov & Forrest 2004, Proc. SPIE 5167;
Moore et al. 2006, Opt. Eng. 45, 076402).  The kernel is

    [[α_d, α,             α_d],
     [α,   1 − 4α − 4α_d, α  ],
     [α_d, α,             α_d]],

with nearest-neighbour coupling α ≈ 1.6 % and diagonal α_d ≈ 0.2 % (HgCdTe H2RG/H4RG values:
Kannawadi et al. 2016, PASP 128, 095001, measured α ≈ 1.5–2 %; JWST NIRCam/NIRSpec IPC reference
files are of this order).  It is applied to the accumulated charge of every read; it conserves
charge away from the detector edges (Σ kernel = 1), and a user kernel may lose some (Σ ≤ 1).

Measurement (the validation of the simulation): the signal of a flat field is white Poisson
noise, so after IPC its pixel autocorrelation equals the kernel's own autocorrelation
normalised by Σ K² (Moore et al. 2004; Kannawadi et al. 2016, eq. 5 and following);
:func:`ipc_alpha_from_autocorrelation` solves for (α, α_d) from the lag-(1,0) and lag-(1,1)
correlations.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slicersim import validation
from slicersim.errors import EffectsError
from slicersim.physics.effects import check_number

__all__ = ["IPCParameters", "ipc_kernel", "apply_ipc", "ipc_alpha_from_autocorrelation",
           "kernel_autocorrelation"]


@validation.checked_fields(error=EffectsError)
@dataclass(kw_only=True)
class IPCParameters:
    """alpha, alpha_diag : nearest and diagonal coupling (fractions);  kernel : optional 3×3 user
    kernel (nested lists; replaces alpha and alpha_diag)."""

    alpha: float = 0.016
    alpha_diag: float = 0.002
    kernel: list | None = None

    def __post_init__(self):
        k = ipc_kernel(self.alpha, self.alpha_diag, self.kernel)      # validates
        self.alpha, self.alpha_diag = float(self.alpha), float(self.alpha_diag)
        self.kernel = None if self.kernel is None else k.tolist()

    def to_dict(self):
        return {"alpha": self.alpha, "alpha_diag": self.alpha_diag, "kernel": self.kernel}

    def matrix(self):
        """The 3×3 float64 kernel."""
        return ipc_kernel(self.alpha, self.alpha_diag, self.kernel)


def ipc_kernel(alpha=0.016, alpha_diag=0.002, kernel=None):
    """3×3 float64 IPC kernel (centre 1 − 4α − 4α_d), or the validated user ``kernel``.

    EffectsError when the kernel is not 3×3, has a negative or non-finite entry, or sums to
    more than 1 (+1e-12).
    """
    if kernel is None:
        alpha = check_number("ipc.alpha", alpha, 0.0, 0.25)
        alpha_diag = check_number("ipc.alpha_diag", alpha_diag, 0.0, 0.25)
        centre = 1.0 - 4.0 * alpha - 4.0 * alpha_diag
        if centre < 0.0:
            raise EffectsError(f"ipc.alpha + ipc.alpha_diag must be ≤ 0.25 (centre 1 − 4α − 4α_d ≥ 0), "
                               f"got α = {alpha}, α_d = {alpha_diag}")
        return np.array([[alpha_diag, alpha, alpha_diag], [alpha, centre, alpha], [alpha_diag, alpha, alpha_diag]])
    k = validation.array("ipc.kernel", kernel, ndim=2, low=0.0, error=EffectsError)
    if k.shape != (3, 3):
        raise EffectsError(f"ipc.kernel must be 3×3, got shape {k.shape}")
    if k.sum() > 1.0 + 1e-12:
        raise EffectsError(f"ipc.kernel must sum to ≤ 1 (charge cannot be created), got {k.sum():.15g}")
    return k


def apply_ipc(image, kernel):
    """NumPy reference of the IPC stencil: out[y, x] = Σ_{dy,dx} K[1+dy, 1+dx] · in[y−dy, x−dx]
    (the charge of a pixel puts K[1+dy, 1+dx] of itself at offset (dy, dx)); zero outside the
    image.  ``image`` (..., ny, nx); float64 out."""
    k = ipc_kernel(kernel=kernel)
    img = np.asarray(image, dtype=np.float64)
    if img.ndim < 2:
        raise EffectsError(f"apply_ipc needs an image (..., ny, nx), got shape {img.shape}")
    ny, nx = img.shape[-2:]
    out = np.zeros_like(img)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            w = k[1 + dy, 1 + dx]
            if w == 0.0:
                continue
            dst_y, src_y = slice(max(dy, 0), ny + min(dy, 0)), slice(max(-dy, 0), ny - max(dy, 0))
            dst_x, src_x = slice(max(dx, 0), nx + min(dx, 0)), slice(max(-dx, 0), nx - max(dx, 0))
            out[..., dst_y, dst_x] += w * img[..., src_y, src_x]
    return out


def kernel_autocorrelation(kernel):
    """(r_near, r_diag): the lag-(0,1)/(1,0) mean and lag-(1,±1) mean autocorrelation of white
    noise after the kernel, normalised by the zero lag."""
    k = np.asarray(kernel, float)
    pad = np.pad(k, 1)

    def lag(dy, dx):
        return float(np.sum(pad[1:4, 1:4] * pad[1 + dy:4 + dy, 1 + dx:4 + dx]))
    zero = lag(0, 0)
    near = (lag(0, 1) + lag(1, 0) + lag(0, -1) + lag(-1, 0)) / 4.0
    diag = (lag(1, 1) + lag(1, -1) + lag(-1, 1) + lag(-1, -1)) / 4.0
    return near / zero, diag / zero


def _lag_correlation(img, dy, dx):
    """Mean product of the pixel pairs (y, x), (y + dy, x + dx) of every image (dy ≥ 0)."""
    ny, nx = img.shape[-2:]
    x0, x1 = max(0, -dx), nx - max(dx, 0)
    return float(np.mean(img[..., :ny - dy, x0:x1] * img[..., dy:, x0 + dx:x1 + dx]))


def ipc_alpha_from_autocorrelation(flat, noise_variance=0.0, border=1, iterations=50):
    """Estimate (α, α_d) from the pixel autocorrelation of a flat field (Moore et al. 2004).

    ``flat`` (ny, nx) or a stack (nimg, ny, nx) of flat-field signal images (e.g. a slope or a
    difference of two reads of a uniform illumination; each image's mean is removed).
    ``noise_variance``: variance [same units²] of noise added after IPC (read noise), removed from
    the zero lag.  ``border`` pixels are dropped on every side (IPC with zero outside the image
    darkens the edge, a structure that would bias the lags).  The normalised lag-1 correlations
    (averaged over the four directions of each kind) are matched to :func:`kernel_autocorrelation` of the symmetric kernel by Newton steps.
    """
    img = validation.array("flat", flat, finite=False, error=EffectsError)
    if img.ndim == 2:
        img = img[None]
    border = validation.integer("border", border, low=0, error=EffectsError)
    if img.ndim != 3 or min(img.shape[-2:]) < 3 + 2 * border or border < 0:
        raise EffectsError(f"flat must be (ny, nx) or (nimg, ny, nx) with ny, nx ≥ 3 + 2·border "
                           f"(border = {border} ≥ 0), got {np.shape(flat)}")
    if border:
        img = img[..., border:-border, border:-border]
    img = img - img.mean(axis=(-2, -1), keepdims=True)
    zero = float(np.mean(img * img)) - float(noise_variance)
    if not zero > 0:
        raise EffectsError("flat has no variance left after removing noise_variance")
    r_near = (_lag_correlation(img, 0, 1) + _lag_correlation(img, 1, 0)) / 2.0 / zero
    r_diag = (_lag_correlation(img, 1, 1) + _lag_correlation(img, 1, -1)) / 2.0 / zero
    target = np.array([r_near, r_diag])
    x = np.array([max(r_near / 2.0, 0.0), max(r_diag / 2.0, 0.0)])
    h = 1e-7
    for _ in range(iterations):
        f = np.array(kernel_autocorrelation(ipc_kernel(*x))) - target
        jac = np.empty((2, 2))
        for i in range(2):
            step = x.copy()
            step[i] += h
            jac[:, i] = (np.array(kernel_autocorrelation(ipc_kernel(*step))) - target - f) / h
        dx = np.linalg.solve(jac, -f)
        x = np.clip(x + dx, 0.0, 0.124)
        if np.max(np.abs(dx)) < 1e-12:
            break
    return float(x[0]), float(x[1])
