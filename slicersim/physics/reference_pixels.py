"""Reference pixels of an H4RG: a border with no photo-response that carries bias and read noise.

The H4RG-10 (like the H2RG) has a 4-pixel frame of reference pixels — rows 0–3 and
ny−4…ny−1, columns 0–3 and nx−4…nx−1 — connected to capacitors instead of photodiodes
(Loose et al. 2005; Rauscher et al. 2017, PASP 129, 105003).  They are read through the
same outputs at the same pixel clock, so they carry each output's bias drifts and the
correlated read noise (:mod:`slicersim.physics.correlated_noise`) but no photo-charge
(the ramp driver zeroes their charge: dark, light, cosmic rays).  A reference-pixel
correction (:mod:`slicersim.reduction.refpix`) uses them to remove those drifts.

The static bias [ADU], added to the ramp's scalar ``bias``, is a per-output offset plus
a per-pixel fixed pattern, both Gaussian (:func:`bias_map`); their sizes are free
parameters (NGHXRG's defaults are a 5000 e- offset and a 500 e- pattern amplitude,
scaled here to stay clear of 0 and 65535 ADU around the ramp's 2000 ADU pedestal).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slicersim import rng, validation
from slicersim.rng import uniform_normal_draw
from slicersim.errors import EffectsError
from slicersim.physics.effects import STREAMS

__all__ = ["ReferencePixelParameters", "reference_pixel_mask", "bias_map"]

_SUB_OUTPUT, _SUB_PIXEL = 0, 1


@validation.checked_fields(error=EffectsError)
@dataclass(kw_only=True)
class ReferencePixelParameters:
    """border : px width of the reference frame (4 for H2RG/H4RG); n_outputs : outputs;
    output_offset : rms [ADU] of the per-output bias offsets; pixel_offset : rms [ADU] of the
    per-pixel fixed bias pattern (both clipped at ±5 rms)."""

    border: int = 4
    n_outputs: int = 32
    output_offset: float = 100.0
    pixel_offset: float = 50.0

    def __post_init__(self):
        self.border = validation.integer("reference_pixels.border", self.border, low=0, high=1 << 16,
                                         error=EffectsError)
        self.n_outputs = validation.integer("reference_pixels.n_outputs", self.n_outputs, low=1, high=1 << 16,
                                            error=EffectsError)
        for name in ("output_offset", "pixel_offset"):
            setattr(self, name, validation.number(f"reference_pixels.{name} [ADU]", getattr(self, name), low=0.0,
                                                  error=EffectsError))


def _check_shape(shape, border):
    """(ny, nx) of a detector ``shape`` wide enough for a ``border``-pixel reference frame."""
    ny, nx = validation.shape("shape", shape, error=EffectsError)
    if ny <= 2 * border or nx <= 2 * border:
        raise EffectsError(f"reference pixels: detector {ny}×{nx} too small for a {border}-pixel border")
    return ny, nx


def reference_pixel_mask(shape, border=4):
    """bool (ny, nx): True on the reference pixels (the ``border``-pixel frame)."""
    ny, nx = _check_shape(shape, border)
    mask = np.zeros((ny, nx), bool)
    if border:
        mask[:border] = mask[-border:] = True
        mask[:, :border] = mask[:, -border:] = True
    return mask


def bias_map(seed, shape, params=None):
    """float32 (ny, nx) static bias [ADU] to add to the ramp's scalar bias: N(0, output_offset²)
    per output plus N(0, pixel_offset²) per pixel, each clipped at ±5 rms.

    Philox keyed under STREAMS["reference_pixels"]: sub-stream 0 index = output (outputs),
    sub-stream 1 index = pixel // 2 (both Box–Muller branches: pixel parity picks one)."""
    params = ReferencePixelParameters() if params is None else params
    ny, nx = _check_shape(shape, params.border)
    if nx % params.n_outputs:
        raise EffectsError(f"reference pixels: nx = {nx} is not divisible by n_outputs = {params.n_outputs}")
    base = STREAMS["reference_pixels"]
    z_out = rng.normal(seed, np.arange(params.n_outputs, dtype=np.uint64), base + _SUB_OUTPUT)[:, 0]
    out = np.repeat(params.output_offset * np.clip(z_out, -5, 5), nx // params.n_outputs)
    bias = np.empty((ny, nx), np.float32)
    rows = max(1, (1 << 22) // nx)
    for y0 in range(0, ny, rows):
        y1 = min(ny, y0 + rows)
        p0, p1 = y0 * nx, y1 * nx                       # pixel p uses branch p % 2 of block p // 2
        _, z = uniform_normal_draw((p1 + 1) // 2 - p0 // 2, seed, base + _SUB_PIXEL, first_index=p0 // 2)
        z = z.reshape(-1)[p0 % 2:p0 % 2 + p1 - p0]
        bias[y0:y1] = (out[None, :] + params.pixel_offset * np.clip(z, -5, 5).reshape(y1 - y0, nx))
    return bias
