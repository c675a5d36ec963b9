"""Inter-pixel capacitance correction of a rate image.

IPC couples each pixel's charge to its neighbours by a 3×3 kernel K (:mod:`slicersim.physics.ipc`),
linear and the same in every frame, so the fitted rates are K ⊛ r.  The correction deconvolves them,

    r̂ = F⁻¹[ F(d) / F(K) ],

with F the 2-D discrete Fourier transform (K̂ ≥ 1 − 8α − 8α_d > 0 for a physical kernel, so the
inverse is bounded: for Lazuli's α = 0.016, α_d = 0.002, K̂ ≥ 0.872).  Unusable pixels enter as the
median of their usable 3×3 neighbours.  The noise of r̂ is K⁻¹ applied to the rates' noise: its
variance grows by Σ (K⁻¹)² − 1 ≈ 8α² (2e-3 for Lazuli) and neighbours become correlated by ≈ −α
(−1.6 %); both are left out of the pixel variances.  Left in, IPC biased a point source's flux by
−0.9 % (narrow field) and −1.2 % (wide) on the Lazuli detector (noiseless, forward extraction):
IPC moves light from the core to pixels the model gives less weight.
"""
from __future__ import annotations

import json

import numpy as np

from slicersim import validation
from slicersim.errors import ParameterError, RampFileError

__all__ = ["ipc_kernel_of", "deconvolve_ipc"]


def ipc_kernel_of(attrs):
    """The 3×3 IPC kernel a ramp file records (its EFFECTS keyword, when ``ipc`` is enabled), or None."""
    from slicersim.physics.ipc import ipc_kernel
    text = (attrs or {}).get("EFFECTS")
    if text is None:
        return None
    try:
        effects = json.loads(text.decode() if isinstance(text, bytes) else text).get("effects", {})
    except (ValueError, AttributeError):
        raise RampFileError("the file's EFFECTS keyword is not valid JSON: cannot tell whether IPC needs "
                            "correcting (give ipc=False to reduce without the correction)") from None
    if "ipc" not in effects.get("enabled", []):
        return None
    p = effects.get("ipc", {}) or {}
    return ipc_kernel(p.get("alpha", 0.016), p.get("alpha_diag", 0.002), p.get("kernel"))


def _median3_at(img, where):
    """``scipy.ndimage.median_filter(img, size=3, mode="nearest")`` at the pixels ``where`` only (the 5th of
    the 9 values of each 3×3 neighbourhood, edges repeated): the same values, without filtering the whole
    image for the few unusable pixels."""
    ys, xs = np.nonzero(where)
    padded = np.pad(img, 1, mode="edge")
    near = np.stack([padded[ys + 1 + dy, xs + 1 + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
    return np.partition(near, 4, axis=0)[4]


def deconvolve_ipc(rate, usable, kernel):
    """r̂ = K⁻¹ ⊛ rate (module docstring) on an (H, W) image; ``usable`` (H, W) bool: pixels whose rate
    is valid (the others are filled from their neighbours before, and set to 0 after).  Returns float64."""
    from scipy import fft
    k = validation.array("kernel", kernel)
    if k.shape != (3, 3) or not np.isclose(k.sum(), 1.0, atol=1e-9):
        raise ParameterError(f"kernel (the IPC kernel) must be a 3×3 array summing to 1, got "
                             f"{validation.short_repr(k) if k.shape != (3, 3) else k.tolist()}")
    img = np.where(usable, np.asarray(rate, float), 0.0)
    if not usable.all():
        img[~usable] = _median3_at(img, ~usable)
    H, W = img.shape
    pad = np.zeros((H, W))
    for dy in (-1, 0, 1):                     # kernel centred on pixel (0, 0), wrapped (images of 1 or 2 rows too:
        for dx in (-1, 0, 1):                 # a row range of a ramp of some rows)
            pad[dy % H, dx % W] += k[1 + dy, 1 + dx]
    khat = fft.rfft2(pad, workers=-1)
    out = fft.irfft2(fft.rfft2(img, workers=-1) / khat, s=(H, W), workers=-1)
    return np.where(usable, out, 0.0)
