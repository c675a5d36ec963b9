"""Detector effects of a raw ramp, assembled for the ramp driver (:func:`slicersim.products.ramps.simulate`).

:class:`EffectsPlan` turns a :class:`~slicersim.physics.effects.DetectorEffects` request into the
inputs of the effects stage of :mod:`slicersim.backends.ramp_effects`, in the order of the signal
chain of an H4RG pixel:

1. photo-response: bad pixels (low QE scales the photo-electron rate, hot/warm pixels add dark
   current, dead pixels and reference pixels collect nothing);
2. charge: Poisson electrons (the plain sampler's draws), cosmic-ray and persistence deposits at
   their frames, full-well clipping;
3. read value: per-pixel nonlinearity R(Q) of the accumulated charge, averaged over the m reads;
4. voltage: inter-pixel capacitance (3×3 kernel), white read noise, correlated read noise
   (NGHXRG) and telegraph offsets, bias (per-output and per-pixel with reference pixels);
5. digitisation: gain, rounding, uint16 clipping, saturation flags.

Each effect draws from its own Philox stream range, so switching one on or off leaves the others'
draws — and the plain ramp's — unchanged.  The truth of each effect is written beside the data
(``truth/<name>`` in the HDF5 file).
"""
from __future__ import annotations

import numpy as np

from slicersim import validation
from slicersim.errors import EffectsError

__all__ = ["EffectsPlan", "CR_DTYPE", "resolve_effects"]

#: one row per pixel crossed (or per persistence release): full-detector y, x; frame from the reset
CR_DTYPE = np.dtype([("ramp", "<u4"), ("frame", "<u4"), ("y", "<u2"), ("x", "<u2"), ("electrons", "<f4")])

#: JWST PIXELDQ bit of reference pixels
REFERENCE_PIXEL = 2**31


def resolve_effects(effects, has_previous_charge=False):
    """:class:`DetectorEffects` or None from None, a DetectorEffects, names ("ipc,cosmic_rays", "all",
    a list), a preset name ("lazuli") or a config dict.  With ``has_previous_charge`` "all" and the
    presets include persistence."""
    if effects is None or effects is False:
        return None
    from slicersim.physics.effects import DetectorEffects
    if isinstance(effects, DetectorEffects):
        return effects if effects.enabled else None
    from slicersim.physics.effects import PRESETS
    if isinstance(effects, dict):
        fx = DetectorEffects.from_config(effects, has_previous_charge)
    elif isinstance(effects, str) and effects.strip().lower() in PRESETS:
        fx = DetectorEffects.preset(effects.strip().lower(), has_previous_charge)
    elif isinstance(effects, (str, list, tuple)):
        fx = DetectorEffects.from_names(effects, has_previous_charge)
    else:
        raise EffectsError(f"effects must be None, names, a preset, a config dict or a DetectorEffects, "
                           f"got {type(effects).__name__}")
    return fx if fx.enabled else None


class EffectsPlan:
    """Host-side inputs of the effects stage for one exposure (all ramps) of a ``shape`` detector.

    effects : DetectorEffects;  p : RampParameters;  seed : int;  shape : (ny, nx)
    previous_charge : (ny, nx) [e-] charge of the previous exposure (persistence), or None
    noise_cache_bytes : bytes the correlated noise may keep between row blocks (None: its default)
    """

    def __init__(self, effects, p, seed, shape, previous_charge=None, noise_cache_bytes=None):
        self.effects, self.p, self.seed, self.shape = effects, p, int(seed), tuple(shape)
        self.on = set(effects.enabled)
        ny, nx = self.shape
        if "persistence" in self.on and previous_charge is None:
            raise EffectsError("persistence needs previous_charge: the (ny, nx) charge image [e-] of the "
                               "previous exposure")
        if "persistence" in self.on and not (p.nramps <= 2**12 and p.nframes <= 2**20):
            raise EffectsError(f"persistence supports up to 4096 ramps of up to 2**20 frames, got {p.nramps} "
                               f"ramps of {p.nframes} frames")
        if previous_charge is not None:
            previous_charge = np.asarray(previous_charge, float)
            if previous_charge.shape != self.shape or not np.all(np.isfinite(previous_charge)) \
                    or np.any(previous_charge < 0):
                raise EffectsError(f"{validation.shown('previous_charge')} must be a finite, non-negative {self.shape} "
                                   f"image [e-], got shape {previous_charge.shape}")
        self.previous_charge = previous_charge
        self.halo = 1 if "ipc" in self.on else 0
        self.ipc = None
        if "ipc" in self.on:
            # K[1+dy, 1+dx]: fraction of a pixel's signal that appears at offset (dy, dx) (the
            # convention of apply_ipc and of the truth); the readout gathers v(y, x) =
            # Σ W[1+dy, 1+dx]·s(y+dy, x+dx), so it takes W = K flipped
            self.ipc_kernel = effects.params("ipc").matrix()
            self.ipc = np.ascontiguousarray(self.ipc_kernel[::-1, ::-1])
        self.reference = None
        if "reference_pixels" in self.on:
            from slicersim.physics.reference_pixels import reference_pixel_mask
            self.reference = reference_pixel_mask(self.shape, effects.params("reference_pixels").border)
        self.bad = None
        if "bad_pixels" in self.on:
            from slicersim.physics.bad_pixels import bad_pixel_maps
            self.bad = bad_pixel_maps(self.seed, self.shape, effects.params("bad_pixels"))
        self.bias = None
        if "reference_pixels" in self.on:
            from slicersim.physics.reference_pixels import bias_map
            self.bias = np.asarray(p.bias + bias_map(self.seed, self.shape, effects.params("reference_pixels")),
                                   np.float32)
            lowest = float(self.bias.min())
            if lowest < 0.0:                  # the ADC would clip these pixels at 0 ADU in every read
                raise EffectsError(f"bias {p.bias:g} ADU is too low for the reference-pixel offsets: the bias map "
                                   f"reaches {lowest:.1f} ADU; raise the bias or lower output_offset/pixel_offset")
        self.noise = None
        if "correlated_noise" in self.on:
            from slicersim.backends.correlated_noise import CorrelatedNoise
            cache = {} if noise_cache_bytes is None else {"cache_bytes": int(noise_cache_bytes)}
            self.noise = CorrelatedNoise(effects.params("correlated_noise"), self.shape, p.nmd, p.tframe, self.seed,
                                         **cache)
        self._deposits = {}
        self._telegraph = {}
        self.nx = nx

    @staticmethod
    def truth_nbytes(effects, p, shape):
        """Upper estimate [bytes] of the effects' truth datasets (for the disk-space check before a run)."""
        ny, nx = shape
        on = set(effects.enabled)
        nbytes = 0
        if "nonlinearity" in on:              # a2, a3 float64 + inverse coefficients float32
            nbytes += ny * nx * (16 + 4 * (effects.params("nonlinearity").degree + 1))
        if "bad_pixels" in on:                # extra dark, QE factor (float32)
            nbytes += ny * nx * 8
        if "reference_pixels" in on:          # bias map (float32)
            nbytes += ny * nx * 4
        if "cosmic_rays" in on:               # CR_DTYPE rows: hits × pixels crossed (≤ 64 on average)
            params = effects.params("cosmic_rays")
            area_cm2 = ny * nx * (params.pixel_pitch * 1e-4) ** 2
            hits = params.rate * area_cm2 * p.nframes * p.tframe * p.nramps
            nbytes += int(hits * 64 * CR_DTYPE.itemsize)
        return nbytes

    # ------------------------------------------------------------------ photo-response
    def rate_and_dark(self, rate, dark, user_dead=None):
        """(photo rate [e-/s], dark [e-/s], mask of pixels collecting no charge, PIXELDQ flags) after bad
        and reference pixels.  Reference pixels get only the REFERENCE_PIXEL flag (no photodiode: no
        DEAD, HOT, WARM or LOW_QE)."""
        self.user_dead = None if user_dead is None else np.asarray(user_dead, bool)
        rate = np.asarray(rate, float)
        dark = np.broadcast_to(np.asarray(dark, float), self.shape)
        dead = np.zeros(self.shape, bool)
        flags = np.zeros(self.shape, np.uint32)
        if self.bad is not None:
            rate = rate * self.bad["qe_factor"]
            dark = dark + self.bad["extra_dark"]
            dead |= self.bad["dead"]
            flags |= self.bad["pixeldq"]
        if self.reference is not None:
            dead |= self.reference                      # no photodiode: no charge at all
            flags[self.reference] = np.uint32(REFERENCE_PIXEL)
        return rate, dark, dead, flags

    def drop_photo_maps(self):
        """Free the extra-dark and QE maps and the bad pixels' PIXELDQ (3 × 4 B per pixel) once the
        rates, the flags and the truth have them."""
        if self.bad is not None:
            self.bad.pop("extra_dark", None)
            self.bad.pop("qe_factor", None)
            self.bad.pop("pixeldq", None)

    # ------------------------------------------------------------------ charge deposits
    def deposits(self, ramp):
        """All charge deposits of ``ramp`` (CR_DTYPE rows, sorted by y, x, frame), cosmic rays first."""
        if ramp in self._deposits:
            return self._deposits[ramp]
        parts = [self._cosmic_rays(ramp), self._persistence(ramp)]
        rows = np.concatenate(parts)
        rows = rows[np.lexsort((rows["frame"], rows["x"], rows["y"]))]
        self._deposits = {ramp: rows}                    # one ramp at a time in memory
        return rows

    def _collected(self, rows):
        """The deposits on pixels that collect charge (not on dead or reference pixels)."""
        user_dead = getattr(self, "user_dead", None)
        if self.reference is None and self.bad is None and user_dead is None:
            return rows
        dead = np.zeros(self.shape, bool) if self.reference is None else self.reference.copy()
        if self.bad is not None:
            dead |= self.bad["dead"]
        if user_dead is not None:
            dead |= user_dead
        return rows[~dead[rows["y"], rows["x"]]]

    def _cosmic_rays(self, ramp):
        """Cosmic-ray truth of ``ramp`` (pixels that collect charge), CR_DTYPE sorted by y, x, frame."""
        if "cosmic_rays" not in self.on:
            return np.zeros(0, CR_DTYPE)
        from slicersim.physics.cosmic_rays import cosmic_ray_deposits
        rows = cosmic_ray_deposits(self.seed, ramp, self.p.nframes, self.p.tframe, self.shape,
                                   self.effects.params("cosmic_rays"))
        return self._collected(np.asarray(rows).astype(CR_DTYPE))

    def _persistence(self, ramp):
        if "persistence" not in self.on:
            return np.zeros(0, CR_DTYPE)
        from slicersim.physics.persistence import persistence_deposits
        rows = persistence_deposits(self.seed, ramp, self.p.nframes, self.p.tframe, self.previous_charge,
                                    self.effects.params("persistence"))
        return self._collected(np.asarray(rows).astype(CR_DTYPE))

    def block_deposits(self, ramp, y0, y1):
        """CSR deposits (start, frame, electrons) of rows [y0, y1) (block-local pixel numbers)."""
        from slicersim.backends.ramp_effects import deposits_csr
        rows = self.deposits(ramp)
        lo, hi = np.searchsorted(rows["y"], [y0, y1])
        sel = rows[lo:hi]
        local = (sel["y"].astype(np.int64) - y0) * self.nx + sel["x"]
        return deposits_csr((y1 - y0) * self.nx, local, sel["frame"], sel["electrons"].astype(np.float64))

    # ------------------------------------------------------------------ voltage domain
    def read_noise_block(self, ramp, y0, y1):
        """Group-averaged read-domain noise [e-] (n, y1−y0, nx) float32 (correlated + telegraph), or None."""
        out = None
        if self.noise is not None:
            out = np.asarray(self.noise.block(ramp, y0, y1), np.float32)
        if self.bad is not None and len(self.bad.get("telegraph", ())):
            offsets, ys, xs = self._telegraph_offsets(ramp)
            sel = (ys >= y0) & (ys < y1)
            if sel.any():
                if out is None:
                    out = np.zeros((self.p.nmd[0], y1 - y0, self.nx), np.float32)
                out[:, ys[sel] - y0, xs[sel]] += offsets[:, sel]
        return out

    def _telegraph_offsets(self, ramp):
        if ramp not in self._telegraph:
            from slicersim.physics.bad_pixels import telegraph_offsets
            pixels = self.bad["telegraph"]                # structured: y, x, amplitude, dwell times
            offsets = np.asarray(telegraph_offsets(self.seed, ramp, self.p.nmd, self.p.tframe, pixels,
                                                   self.effects.params("bad_pixels")), np.float32)
            ys, xs = pixels["y"].astype(np.int64), pixels["x"].astype(np.int64)
            self._telegraph = {ramp: (offsets, ys, xs)}
        return self._telegraph[ramp]

    def nonlinearity_block(self, y0, y1):
        """(a2 [e-⁻¹], a3 [e-⁻²]) of rows [y0, y1) raveled, or (None, None) (drawn per pixel: the same
        values whatever the blocks)."""
        if "nonlinearity" not in self.on:
            return None, None
        from slicersim.physics.nonlinearity import nonlinearity_coefficients
        a = nonlinearity_coefficients(self.seed, self.shape, self.effects.params("nonlinearity"), self.p.full_well,
                                      rows=(y0, y1))
        return np.ascontiguousarray(a[0]).ravel(), np.ascontiguousarray(a[1]).ravel()

    def bias_block(self, y0, y1):
        return None if self.bias is None else self.bias[y0:y1]

    def plateau_block(self, y0, y1):
        """(y1 − y0, nx) DN where a full pixel of rows [y0, y1) reads, noise aside: bias (map) +
        gain·R(full well), R the nonlinear read value when ``nonlinearity`` is on [DN]."""
        from slicersim.backends.ramp_effects import nl_read
        nx = self.shape[1]
        a2, a3 = self.nonlinearity_block(y0, y1)
        full = np.full((y1 - y0) * nx, float(self.p.full_well))
        read = full if a2 is None else nl_read(full, a2, a3)
        bias = self.p.bias if self.bias is None else np.asarray(self.bias[y0:y1], np.float64)
        return bias + self.p.gain * read.reshape(y1 - y0, nx)

    # ------------------------------------------------------------------ truth
    def write_truth(self, writer, nramps, part="all"):
        """Truth of every effect into ``writer`` (RampWriter or UncalWriter: ``write_dataset``).

        part: "all"; "maps" (the bad-pixel maps only, so that :meth:`drop_photo_maps` can free them
        before the rest is written) or "rest" (everything but those)."""
        attrs = {"EFFECTS": self.effects.to_config()}

        def maps():
            if self.bad is not None:
                writer.write_dataset("bad_pixels/extra_dark", self.bad["extra_dark"], {"UNITS": "e-/s"})
                writer.write_dataset("bad_pixels/qe_factor", self.bad["qe_factor"], {"UNITS": "dimensionless"})
                writer.write_dataset("bad_pixels/telegraph", self.bad["telegraph"],
                                     {"UNITS": "amplitude e- (read offset), dwell times s"})
        if part == "maps":
            maps()
            return attrs
        if "cosmic_rays" in self.on:
            rows = np.concatenate([self._cosmic_rays(r) for r in range(nramps)])
            writer.write_dataset("cosmic_rays", rows, {"UNITS": "electrons", "FRAME": "from the reset, "
                                                       "dropped frames included", "Y_X": "full-detector pixel"})
        if self.ipc is not None:
            writer.write_dataset("ipc_kernel", self.ipc_kernel,
                                 {"CONVENTION": "K[1+dy, 1+dx]: fraction of a pixel's signal seen at offset (dy, dx)"})
        if "nonlinearity" in self.on:
            writer.write_dataset("nonlinearity/coefficients", _RowBlocks(self, "forward"),
                                 {"MODEL": "R(Q) = Q + a2 Q^2 + a3 Q^3 [e-] (a2, a3)"})
            writer.write_dataset("nonlinearity/inverse_coefficients", _RowBlocks(self, "inverse"),
                                 {"CONVENTION": "JWST linearity: corrected DN = sum_k c_k DN^k (bias removed)"})
        if "persistence" in self.on:
            writer.write_dataset("persistence", np.concatenate([self._persistence(r) for r in range(nramps)]))
        if part == "all":
            maps()
        if self.bias is not None:
            writer.write_dataset("bias", self.bias, {"UNITS": "ADU"})
        return attrs



class _RowBlocks:
    """Lazy (k, ny, nx) truth array of nonlinearity coefficients, computed by row blocks when sliced
    (``forward``: a2, a3 float64; ``inverse``: JWST correction coefficients float32)."""

    ROWS = 256

    def __init__(self, plan, kind):
        self.plan, self.kind = plan, kind
        ny, nx = plan.shape
        ncoef = 2 if kind == "forward" else plan.effects.params("nonlinearity").degree + 1
        self.shape = (ncoef, ny, nx)
        self.dtype = np.dtype(np.float64 if kind == "forward" else np.float32)
        self.ndim = 3
        self._full = None

    def rows(self, y0, y1):
        a2, a3 = self.plan.nonlinearity_block(y0, y1)
        nx = self.shape[2]
        if self.kind == "forward":
            return np.stack([a2, a3]).reshape(2, y1 - y0, nx)
        from slicersim.physics.nonlinearity import inverse_coefficients
        p = self.plan.p
        params = self.plan.effects.params("nonlinearity")
        return np.asarray(inverse_coefficients(a2.reshape(y1 - y0, nx), a3.reshape(y1 - y0, nx), p.full_well, p.gain,
                                               degree=params.degree, tolerance=params.tolerance), self.dtype)

    def __getitem__(self, key):
        """``[:, y0:y1]`` row slices (HDF5 writer), first-axis slices ``[i:j]`` (FITS writer: the
        whole array is computed once and kept) and ``[...]``."""
        if key is Ellipsis or isinstance(key, slice):
            if self._full is None:
                self._full = np.concatenate([self.rows(y0, min(self.shape[1], y0 + self.ROWS))
                                             for y0 in range(0, self.shape[1], self.ROWS)], axis=1)
            return self._full if key is Ellipsis else self._full[key]
        rows = key[1] if isinstance(key, tuple) and len(key) >= 2 else slice(None)
        y0, y1, _ = rows.indices(self.shape[1])
        return self.rows(y0, y1)
