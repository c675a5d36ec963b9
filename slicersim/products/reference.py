"""JWST calibration reference files of the simulated detector, matching its ramps exactly.

:func:`reference_arrays` draws the per-pixel maps the ramp driver draws for the same
(parameters, effects, seed, shape) — bad pixels, nonlinearity, reference-pixel bias — through
the same functions (:class:`~slicersim.products.effects.EffectsPlan`), and turns them into
the eight JWST reference arrays (:mod:`slicersim.physics.calibration` for the units);
:func:`write_reference_files` writes them (:mod:`slicersim.io.reference_files`), and
:func:`write_reference_files_for_ramps` does so for the parameters recorded in a ramp file.

The maps depend on the ramp's seed (a pixel's draws are keyed by (seed, pixel)): the reference
files of a ramp are those of its seed, so ramps of different seeds (a campaign's targets) each
need their own set.
"""
from __future__ import annotations

import json

import numpy as np

from slicersim import validation
from slicersim.errors import EffectsError, RampFileError
from slicersim.io import reference_files as _files
from slicersim.physics import calibration
from slicersim.physics.ramp import DEFAULT_BIAS, RampParameters

__all__ = ["DARK_FRAMES", "reference_arrays", "write_reference_files", "parameters_from_attrs",
           "write_reference_files_for_ramps", "available"]

#: True when the reference files can be written (stdatamodels installed: ``pip install slicersim[jwst]``)
available = _files.available

#: frames of the dark reference ramp (stcal's dark step extends it linearly to longer ramps)
DARK_FRAMES = 4
_ROWS = 256
#: the effects whose per-pixel maps or kernel enter the reference files
_STATIC = ("ipc", "nonlinearity", "reference_pixels", "bad_pixels")


def reference_arrays(p, effects, seed, shape, dark_frames=DARK_FRAMES):
    """The reference arrays of a ``shape`` detector read with ``p`` and ``effects`` (maps of ``seed``).

    Parameters
    ----------
    p : RampParameters
        The ramps' readout and detector parameters (gain [ADU/e-], ron [e-], bias [ADU], full well [e-], ...).
    effects : DetectorEffects or None
        The ramps' detector effects (bad pixels, nonlinearity, IPC and reference pixels enter the files).
    seed : int
        The ramps' seed.
    shape : (ny, nx)
        The ramps' image size [px].
    dark_frames : int
        Frames of the dark reference ramp.

    Returns
    -------
    dict
        The ``arrays`` of :func:`slicersim.io.reference_files.write_reference_files`: ``gain`` [e-/DN],
        ``readnoise`` [DN, CDS], ``saturation`` [DN], ``superbias`` [DN] float32 (ny, nx); ``linearity``
        float32 (k, ny, nx); ``dark`` float32 (dark_frames, ny, nx) [DN]; ``mask`` uint32 (ny, nx); ``ipc``
        (3, 3).
    """
    from slicersim.products.effects import EffectsPlan, resolve_effects
    seed = validation.seed(seed)
    ny, nx = validation.shape("shape", shape, error=EffectsError)
    dark_frames = validation.integer("dark_frames", dark_frames, low=2, high=1 << 16, error=EffectsError)
    fx = resolve_effects(effects)
    dark = np.asarray(p.dark, float)
    if dark.ndim and dark.shape != (ny, nx):
        raise EffectsError(f"the per-pixel dark is {dark.shape}, the detector {(ny, nx)}")
    plan = None
    if fx is not None:
        fx = fx.restricted_to([n for n in fx.enabled if n in _STATIC])   # the others draw no per-pixel map
        plan = EffectsPlan(fx, p, seed, (ny, nx)) if fx.enabled else None
    _, dark_rate, dead, flags = (plan.rate_and_dark(np.zeros((ny, nx)), dark) if plan is not None else
                                 (None, np.broadcast_to(dark, (ny, nx)), np.zeros((ny, nx), bool),
                                  np.zeros((ny, nx), np.uint32)))
    mu_dark = np.where(dead, 0.0, (dark_rate + p.thermal_dark) * p.tframe + p.roic_glow)
    superbias = np.full((ny, nx), p.bias, np.float32) if plan is None or plan.bias is None else plan.bias
    kernel = np.zeros((3, 3))
    kernel[1, 1] = 1.0
    if plan is not None and plan.ipc is not None:
        kernel = plan.ipc_kernel
    read_dn = calibration.frame_read_noise_dn(p.ron, p.gain)
    nonlinear = plan is not None and "nonlinearity" in plan.on
    degree = fx.params("nonlinearity").degree if nonlinear else 1
    linearity = np.zeros((degree + 1, ny, nx), np.float32)
    saturation = np.empty((ny, nx), np.float32)
    for y0 in range(0, ny, _ROWS):
        y1 = min(ny, y0 + _ROWS)
        a2 = a3 = None
        if nonlinear:
            from slicersim.physics.nonlinearity import inverse_coefficients
            a2, a3 = (a.reshape(y1 - y0, nx) for a in plan.nonlinearity_block(y0, y1))
            params = fx.params("nonlinearity")
            linearity[:, y0:y1] = inverse_coefficients(a2, a3, p.full_well, p.gain, degree=params.degree,
                                                       tolerance=params.tolerance)
        else:
            linearity[1, y0:y1] = 1.0
        saturation[y0:y1] = calibration.saturation_level(superbias[y0:y1], p.gain, p.full_well, a2, a3,
                                                         ipc_centre=float(kernel[1, 1]), read_noise_dn=read_dn)
    return {"gain": np.full((ny, nx), calibration.gain_e_per_dn(p.gain), np.float32),
            "readnoise": np.full((ny, nx), calibration.cds_read_noise(p.ron, p.gain), np.float32),
            "saturation": saturation, "superbias": np.asarray(superbias, np.float32), "linearity": linearity,
            "dark": calibration.dark_frames(mu_dark, p.gain, dark_frames), "mask": np.asarray(flags, np.uint32),
            "ipc": np.asarray(kernel, np.float32)}


def _describe(effects, seed):
    names = "none" if effects is None or not effects.enabled else ",".join(effects.enabled)
    return f"seed {int(seed)}; effects {names}"


def write_reference_files(directory, p, effects, seed, shape, detector="lazuli", overwrite=False,
                          dark_frames=DARK_FRAMES):
    """Write the eight reference files (:func:`reference_arrays`) into ``directory``.

    Parameters
    ----------
    directory : path
        Made if missing (its parent must exist).
    p, effects, seed, shape, dark_frames :
        As :func:`reference_arrays`.
    detector : str
        Label in the file names (``slicersim_<detector>_<type>.fits``).
    overwrite : bool
        Replace existing files (default: refuse before computing anything).

    Returns
    -------
    dict
        {type: path}.
    """
    import os
    from slicersim.products.effects import resolve_effects
    names = _files.reference_file_names(detector)
    if not overwrite:
        for name in names.values():
            path = os.path.join(os.fspath(directory), name)
            if os.path.lexists(path):
                raise RampFileError(f"output file exists: {os.path.abspath(path)} (pass overwrite=True / "
                                    "--overwrite to replace the reference files)")
    fx = resolve_effects(effects)
    arrays = reference_arrays(p, fx, seed, shape, dark_frames)
    return _files.write_reference_files(directory, arrays, detector=detector, description=_describe(fx, seed),
                                        overwrite=overwrite)


def parameters_from_attrs(attrs):
    """(RampParameters, DetectorEffects or None, seed) recorded in a ramp file's root attributes
    (NGROUPS, NFRAMES, GROUPGAP, NINTS, TFRAME, READNOISE, GAIN, BIAS, SATURATION, FULLWELL, DARK,
    THERMAL_DARK, ROIC_GLOW, KTC_NOISE, SEED, EFFECTS).  A per-pixel dark map is recorded as its mean."""
    from slicersim.physics.effects import DetectorEffects
    need = ("NGROUPS", "NFRAMES", "GROUPGAP", "TFRAME", "READNOISE", "GAIN", "SEED")
    missing = [k for k in need if k not in attrs]
    if missing:
        raise RampFileError(f"not a slicersim ramp file: keyword(s) {', '.join(missing)} missing")
    p = RampParameters(nmd=(int(attrs["NGROUPS"]), int(attrs["NFRAMES"]), int(attrs["GROUPGAP"])),
                       nramps=int(attrs.get("NINTS", 1)), tframe=float(attrs["TFRAME"]), ron=float(attrs["READNOISE"]),
                       gain=float(attrs["GAIN"]), dark=float(attrs.get("DARK", 0.0)),
                       thermal_dark=float(attrs.get("THERMAL_DARK", 0.0)), roic_glow=float(attrs.get("ROIC_GLOW", 0.0)),
                       bias=float(attrs.get("BIAS", DEFAULT_BIAS)),
                       saturation=float(attrs.get("SATURATION", 65535.0)),
                       ktc_noise=float(attrs.get("KTC_NOISE", 0.0)),
                       full_well=None if "FULLWELL" not in attrs else float(attrs["FULLWELL"]))
    effects = attrs.get("EFFECTS")
    if isinstance(effects, str):
        effects = json.loads(effects) if effects.strip() else None
    fx = DetectorEffects.from_config(effects, has_previous_charge=True) if effects else None
    return p, fx, int(attrs["SEED"])


def write_reference_files_for_ramps(ramp_path, directory, detector="lazuli", overwrite=False,
                                    dark_frames=DARK_FRAMES):
    """Write the reference files of the ramps in ``ramp_path`` (HDF5 or level-1b FITS): the parameters,
    effects, seed and size its keywords record (:func:`parameters_from_attrs`).  Returns {type: path}."""
    attrs, shape = _files.ramp_file_keywords(ramp_path)
    p, fx, seed = parameters_from_attrs(attrs)
    return write_reference_files(directory, p, fx, seed, shape, detector=detector, overwrite=overwrite,
                                 dark_frames=dark_frames)
