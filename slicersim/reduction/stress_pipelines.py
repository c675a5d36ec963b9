"""The pipelines of the stress harness (:mod:`slicersim.reduction.stress`) and the exposure they read.

Each pipeline gets what a flight pipeline gets from a level-1b file: the raw groups (SCI [DN]) and
the pixel flags (PIXELDQ), **no** group flags (the simulator's SATURATED flags are truth, kept for
the scores); its calibration comes from the JWST reference files of the simulated detector
(:mod:`slicersim.products.reference`: the ``reference/`` folder a campaign with
``reference_files = true`` writes beside the ramps, else the same arrays computed from the ramp
file's keywords).  Each returns a :class:`PipelineOutput` in e-/s.

* ``stcal``: the JWST pipeline's library (``pip install 'slicersim[stcal]'``): dq_init (mask),
  saturation (per-pixel level, no growth), superbias, linearity, jump detection (two-point
  differences, 4σ, no neighbour flags, no snowballs), ramp fit (OLS_C, optimal weighting); DN/s ×
  gain [e-/DN].
* ``slicersim``: a saturation step with the reference saturation level (a raw group at or above
  it and every later group), then :func:`slicersim.reduction.ramp_fit.fit_ramps` (GLS, 4σ jumps)
  with the reference superbias and linearity coefficients, and the reference-pixel correction when
  the file has reference pixels.
* ``exec:COMMAND``: ``COMMAND INPUT.fits OUTPUT.fits`` (shlex-split, no shell), INPUT a level-1b
  file (SCI, PIXELDQ and the primary keywords; no GROUPDQ, no truth), OUTPUT a FITS file with a SCI
  extension: the rate, in DN/s (as JWST rate files) unless its BUNIT names electrons (e-/s,
  electron/s); optional ERR (same unit) and DQ (JWST pixel bits; DO_NOT_USE: no rate).
"""
from __future__ import annotations

import math
import os
import shlex
from dataclasses import dataclass, field

import numpy as np

from slicersim.errors import ParameterError, RampFileError

__all__ = ["BUILTIN", "DQFLAGS", "STCAL_INSTALL", "EXEC_TIMEOUT", "Exposure", "PipelineOutput", "parse_pipelines",
           "require_stcal", "load_exposure", "expected_rate", "run_pipeline"]

#: the built-in pipelines
BUILTIN = ("stcal", "slicersim")
#: JWST data-quality bits given to stcal
DQFLAGS = {"GOOD": 0, "DO_NOT_USE": 1, "SATURATED": 2, "JUMP_DET": 4, "DEAD": 1024, "HOT": 2048,
           "NO_GAIN_VALUE": 524288, "NO_LIN_CORR": 1048576, "NO_SAT_CHECK": 2097152,
           "UNRELIABLE_SLOPE": 16777216, "REFERENCE_PIXEL": 2**31, "CHARGELOSS": 128, "PERSISTENCE": 32,
           "AD_FLOOR": 64}
#: how to get stcal
STCAL_INSTALL = "pip install 'slicersim[stcal]'"
#: seconds an ``exec:`` pipeline may run on one exposure
EXEC_TIMEOUT = 3600.0
_TRUTH_NAMES = ("rate", "cosmic_rays", "bad_pixels/qe_factor", "bad_pixels/extra_dark", "ipc_kernel", "persistence")


def parse_pipelines(specs):
    """The pipelines asked for: names and commands, in order, repeats dropped.

    Parameters
    ----------
    specs : sequence of str
        ``"stcal"``, ``"slicersim"`` or ``"exec:COMMAND"``.

    Returns
    -------
    list of (str, list of str or None)
        (name, argv of the command or None for a built-in pipeline).

    Raises
    ------
    slicersim.errors.ParameterError
        An unknown name or an empty or unparsable command.
    """
    out, seen = [], set()
    if isinstance(specs, str):
        specs = [specs]
    for spec in specs:
        if not isinstance(spec, str):
            raise ParameterError(f"pipeline must be a string, got {type(spec).__name__}")
        spec = spec.strip()
        if spec in seen:
            continue
        seen.add(spec)
        if spec in BUILTIN:
            out.append((spec, None))
        elif spec.startswith("exec:"):
            try:
                argv = shlex.split(spec[5:])
            except ValueError as exc:
                raise ParameterError(f"pipeline {spec!r}: cannot split the command ({exc})") from None
            if not argv:
                raise ParameterError(f"pipeline {spec!r}: give a command after exec:, e.g. 'exec:mypipe --fast'")
            out.append((spec, argv))
        else:
            raise ParameterError(f"unknown pipeline {spec!r}: 'stcal', 'slicersim' or 'exec:COMMAND' "
                                 "(run as COMMAND INPUT.fits OUTPUT.fits)")
    if not out:
        raise ParameterError("give at least one pipeline ('stcal', 'slicersim' or 'exec:COMMAND')")
    return out


def require_stcal():
    """Raise a one-line ParameterError with the install command when stcal cannot be imported.

    Returns
    -------
    str
        The stcal version.
    """
    try:
        import stcal
        from stcal.jump.jump import detect_jumps_data  # noqa: F401
        from stcal.ramp_fitting import ramp_fit  # noqa: F401
    except ImportError:
        raise ParameterError(f"the stcal pipeline needs stcal, which is not installed: {STCAL_INSTALL} "
                             "(or leave it out: --pipeline slicersim)") from None
    return getattr(stcal, "__version__", "?")


@dataclass
class Exposure:
    """One raw ramp file read whole with the truth the scores use.

    Parameters
    ----------
    path : str
        The ramp file.
    sci : numpy.ndarray of shape (nints, ngroups, ny, nx)
        Raw groups [DN], uint16.
    pixeldq : numpy.ndarray of shape (ny, nx)
        Pixel flags (zeros when the file has none).
    attrs : dict
        Root attributes (GAIN [ADU/e-], READNOISE [e-/frame], NFRAMES, TFRAME, ...).
    saturated : numpy.ndarray of shape (nints, ngroups, ny, nx), bool, or None
        The simulator's saturated groups (truth), None when the file holds none.
    truth : dict
        ``rate`` [e-/s], ``cosmic_rays``, bad-pixel maps, ``ipc_kernel``, ... as stored.
    notes : list of str
        What truth is missing.
    """

    path: str
    sci: np.ndarray
    pixeldq: np.ndarray
    attrs: dict
    saturated: np.ndarray | None
    truth: dict
    notes: list = field(default_factory=list)

    @property
    def nmd(self):
        """(groups, frames per group, dropped frames)."""
        a = self.attrs
        return int(self.sci.shape[1]), int(a["NFRAMES"]), int(a.get("GROUPGAP", 0))


@dataclass
class PipelineOutput:
    """What a pipeline returns, in slicersim's units.

    Parameters
    ----------
    rate, err : numpy.ndarray of shape (ny, nx)
        Rate and its error [e-/s] (NaN: no rate; err None when not given).
    dq : numpy.ndarray of shape (ny, nx) or None
        JWST pixel bits.
    groupdq : numpy.ndarray of shape (nints, ngroups, ny, nx) or None
        JWST group bits (jump and saturation flags), None when the pipeline gives none.
    notes : list of str
    """

    rate: np.ndarray
    err: np.ndarray | None
    dq: np.ndarray | None
    groupdq: np.ndarray | None
    notes: list = field(default_factory=list)


def _decoded(attrs):
    return {k: (v.decode() if isinstance(v, bytes) else v) for k, v in attrs.items()}


def load_exposure(path):
    """Read a ramp file (slicersim HDF5 or level-1b FITS) and its truth.

    Parameters
    ----------
    path : str or path-like
        The ramp file.

    Returns
    -------
    Exposure
    """
    path = os.fspath(path)
    from slicersim.reduction.ramp_sources import ramp_file_kind
    kind = ramp_file_kind(path)
    notes = []
    if kind == "hdf5":
        import h5py

        from slicersim.reduction.checks import register_hdf5_filters
        register_hdf5_filters()                        # campaigns' lz4/zstd ramps

        from slicersim.io.rampfile import read_dataset, read_ramps
        sci, gdq, pdq, attrs = read_ramps(path)
        truth = {}
        with h5py.File(path, "r") as fh:
            for name in _TRUTH_NAMES:
                if f"truth/{name}" in fh:
                    truth[name] = read_dataset(fh[f"truth/{name}"], path)
        saturated = (gdq & DQFLAGS["SATURATED"]) != 0
    elif kind == "fits":
        from slicersim.io.uncal_read import read_uncal, read_uncal_truth
        sci, _, pdq, head = read_uncal(path)
        attrs = {k[len("SLICERSIM "):]: v for k, v in head.items() if k.startswith("SLICERSIM ")}
        truth = {k[len("truth/"):]: v for k, v in read_uncal_truth(path).items() if k[len("truth/"):] in _TRUTH_NAMES}
        saturated = None
        notes.append("no saturation truth: a level-1b file carries no simulator flags (score from an HDF5 ramp)")
    else:
        raise RampFileError(f"{path}: neither an HDF5 ramp file nor a JWST level-1b FITS file")
    attrs = _decoded(attrs)
    missing = [k for k in ("NFRAMES", "TFRAME", "GAIN", "READNOISE") if k not in attrs]
    if missing:
        raise RampFileError(f"{path}: not a slicersim ramp file (no {', '.join(missing)} keyword)")
    pdq = np.zeros(sci.shape[2:], np.uint32) if pdq is None else np.asarray(pdq, np.uint32)
    return Exposure(path, np.asarray(sci), pdq, attrs, saturated, truth, notes)


def expected_rate(exposure):
    """The rate [e-/s] a perfect pipeline measures in each pixel, and the pixels scored.

    The input rate (``truth/rate``) times the pixel's QE factor, plus the dark (DARK + THERMAL_DARK
    + ROIC_GLOW / TFRAME and the hot pixels' extra dark), through the IPC kernel when the file has
    one; scored: the pixels without any PIXELDQ flag.

    Parameters
    ----------
    exposure : Exposure

    Returns
    -------
    expected : numpy.ndarray of shape (ny, nx) or None
        [e-/s]; None without ``truth/rate``.
    good : numpy.ndarray of shape (ny, nx), bool
    notes : list of str
    """
    t, a = exposure.truth, exposure.attrs
    good = exposure.pixeldq == 0
    notes = []
    if "rate" not in t:
        return None, good, ["no truth/rate in the ramp file: slope scores are NaN"]
    rate = np.asarray(t["rate"], np.float64)
    if "bad_pixels/qe_factor" in t:
        rate = rate * t["bad_pixels/qe_factor"]
    dark = sum(float(a.get(k, 0.0)) for k in ("DARK", "THERMAL_DARK")) + float(a.get("ROIC_GLOW", 0.0)) / float(a["TFRAME"])
    if not all(k in a for k in ("DARK", "THERMAL_DARK", "ROIC_GLOW")):
        notes.append("DARK/THERMAL_DARK/ROIC_GLOW keywords missing: taken as 0 in the expected rate")
    total = rate + dark
    if "bad_pixels/extra_dark" in t:
        total = total + t["bad_pixels/extra_dark"]
    if "ipc_kernel" in t:
        from scipy.ndimage import convolve
        total = convolve(total, np.asarray(t["ipc_kernel"], np.float64), mode="constant")
    if "persistence" in t and len(t["persistence"]):
        notes.append("persistence charge is not in the expected rate")
    return total, good, notes


# ----------------------------------------------------------------------------- calibration
def _reference(exposure):
    """The reference arrays of the exposure's detector (reference/ beside it, else computed)."""
    from slicersim.products.reference import parameters_from_attrs, reference_arrays
    refdir = os.path.join(os.path.dirname(os.path.abspath(exposure.path)), "reference")
    if os.path.isdir(refdir):
        from slicersim.io.reference_files import read_reference_files
        ref = read_reference_files(refdir)
        return ref, f"reference files {refdir}"
    p, fx, seed = parameters_from_attrs(exposure.attrs)
    ref = reference_arrays(p, fx, seed, exposure.sci.shape[2:])
    return ref, "reference arrays from the ramp keywords (slicersim.products.reference)"


def _stcal(exposure):
    from stcal.jump.jump import detect_jumps_data
    from stcal.jump.jump_class import JumpData
    from stcal.linearity.linearity import linearity_correction
    from stcal.ramp_fitting import ramp_fit as stcal_fit
    from stcal.ramp_fitting.ramp_fit_class import RampData
    from stcal.saturation.saturation import flag_saturated_pixels
    ref, source = _reference(exposure)
    a = exposure.attrs
    _, m, d = exposure.nmd
    data = exposure.sci.astype(np.float32)
    gdq = np.zeros(data.shape, np.uint8)
    pdq = exposure.pixeldq | np.asarray(ref["mask"], np.uint32)                     # dq_init
    shape = pdq.shape
    sat_dq = np.asarray(ref.get("saturation_dq", np.zeros(shape, np.uint32)), np.uint32)
    gdq, pdq, _ = flag_saturated_pixels(data, gdq, pdq, np.asarray(ref["saturation"], np.float32), sat_dq, 65535,
                                        DQFLAGS, n_pix_grow_sat=0)
    data -= np.asarray(ref["superbias"], np.float32)
    lin_dq = np.asarray(ref.get("linearity_dq", np.zeros(shape, np.uint32)), np.uint32)
    data, pdq, _ = linearity_correction(data, gdq, pdq, np.asarray(ref["linearity"], np.float32), lin_dq, DQFLAGS)
    gain = np.asarray(ref["gain"], np.float32)                 # e-/DN
    readnoise = np.asarray(ref["readnoise"], np.float32)       # CDS DN (rounding included)
    jd = JumpData(gain2d=gain, rnoise2d=readnoise, dqflags=DQFLAGS)
    jd.init_arrays_from_arrays(data, gdq, pdq)
    jd.nframes = m
    jd.dt_group = np.ones(1)
    jd.n_reads_groupdiff = np.ones(1) * 2 * m
    jd.flag_4_neighbors = False
    jd.max_cores = "none"
    gdq, pdq, *_ = detect_jumps_data(jd)
    ramp = RampData()
    ramp.set_arrays(data.astype(np.float32), gdq.copy(), pdq, np.zeros(shape, np.float32))
    ramp.set_meta(name="NIRSPEC", frame_time=float(a["TFRAME"]), group_time=float(a.get("TGROUP", (m + d) * float(a["TFRAME"]))),
                  groupgap=d, nframes=m, drop_frames1=None)
    ramp.set_dqflags(DQFLAGS)
    ramp.start_row, ramp.num_rows = 0, shape[0]
    ramp.suppress_one_group_ramps = False
    image, _, _ = stcal_fit.ramp_fit_data(ramp, False, readnoise, gain, "OLS_C", "optimal", "none")
    if isinstance(image, dict):
        slope, err, dq = image["slope"], image["err"], image["dq"]
    else:
        slope, dq, _, _, err = image
    rate = np.asarray(slope, np.float64) * gain
    err = np.asarray(err, np.float64) * gain
    return PipelineOutput(rate, err, np.asarray(dq, np.uint32), gdq, [f"stcal with {source}"])


def _slicersim(exposure):
    from slicersim.reduction.ramp_fit import fit_ramps
    ref, source = _reference(exposure)
    lin = np.asarray(ref["linearity"], np.float64)
    nonlinear = lin.shape[0] > 2 or not (np.all(lin[0] == 0) and np.all(lin[1] == 1))
    # the saturation step (JWST order): a raw group at or above the reference level, and every later group
    level = np.asarray(ref["saturation"], np.float64)
    gdq = np.where(np.maximum.accumulate(exposure.sci >= level, axis=1), np.uint8(DQFLAGS["SATURATED"]), np.uint8(0))
    res = fit_ramps((exposure.sci, gdq, exposure.pixeldq, exposure.attrs), superbias=np.asarray(ref["superbias"], np.float64),
                    linearity=lin if nonlinear else False, return_groupdq=True, progress=False)
    return PipelineOutput(res.rate, res.err, res.dq, res.groupdq, [f"fit_ramps with {source}"])


def _write_level1b(exposure, path):
    """The exposure as a flight-like level-1b file: SCI, PIXELDQ and keywords; no GROUPDQ, no truth."""
    from slicersim.io.uncal import UncalWriter
    nints, n, ny, nx = exposure.sci.shape
    attrs = {k: v for k, v in exposure.attrs.items() if k != "COMPLETE"}
    with UncalWriter(path, nints, n, (ny, nx), attrs=attrs, truth_rate=False, pixeldq=True, groupdq=False) as w:
        w.write_pixeldq(exposure.pixeldq)
        for i in range(nints):
            w.write_block(i, 0, exposure.sci[i])
    return path


def _read_rate_file(path, shape, gain):
    """(rate, err or None, dq or None, unit note) of an exec pipeline's output [e-/s]."""
    from astropy.io import fits
    try:
        with fits.open(path, memmap=False) as hdul:
            names = [h.name for h in hdul]
            if "SCI" not in names:
                raise RampFileError(f"the output {os.path.basename(path)} has no SCI extension")
            sci = np.asarray(hdul["SCI"].data, np.float64)
            bunit = str(hdul["SCI"].header.get("BUNIT", "DN/s"))
            err = np.asarray(hdul["ERR"].data, np.float64) if "ERR" in names else None
            dq = np.asarray(hdul["DQ"].data) if "DQ" in names else None
    except OSError as exc:
        raise RampFileError(f"the output is not a FITS file ({' '.join(str(exc).split())})") from None
    except (TypeError, ValueError) as exc:         # a table or text where an image is expected
        raise RampFileError(f"the output's SCI, ERR or DQ is not a numeric image ({' '.join(str(exc).split())})") from None
    for ext, arr in (("SCI", sci), ("ERR", err), ("DQ", dq)):
        if arr is not None and arr.shape != tuple(shape):
            raise RampFileError(f"the output {ext} is {arr.shape}, the detector {tuple(shape)}")
    if dq is not None:
        if dq.dtype.kind not in "iub" or (dq.dtype.kind == "i" and dq.size and dq.min() < 0):
            raise RampFileError(f"the output DQ must hold JWST bits (integers ≥ 0), got {dq.dtype} "
                                f"{'with negative values' if dq.dtype.kind == 'i' else 'values'}")
        dq = dq.astype(np.uint32)
    electrons = any(w in bunit.lower() for w in ("electron", "e-"))
    scale = 1.0 if electrons else 1.0 / gain                     # DN/s → e-/s: gain [ADU/e-]
    return sci * scale, None if err is None else err * scale, dq, f"rate unit {bunit}"


def _exec(exposure, argv, workdir, timeout=EXEC_TIMEOUT):
    import subprocess
    import tempfile
    with tempfile.TemporaryDirectory(prefix="stress-", dir=workdir) as tmp:
        inp, out = os.path.join(tmp, "input_uncal.fits"), os.path.join(tmp, "output_rate.fits")
        _write_level1b(exposure, inp)
        try:      # its own session: a timeout kills what it started too (a child holding the pipes: no hang)
            proc = subprocess.Popen([*argv, inp, out], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                    stdin=subprocess.DEVNULL, text=True, errors="replace", start_new_session=True)
        except FileNotFoundError:
            raise RampFileError(f"command not found: {argv[0]}") from None
        except PermissionError:
            raise RampFileError(f"command not executable: {argv[0]}") from None
        try:
            _, stderr = proc.communicate(timeout=timeout)
        except BaseException as exc:        # timeout, or the harness interrupted: leave no process behind
            import signal
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except OSError:
                pass
            proc.kill()
            proc.communicate()
            if isinstance(exc, subprocess.TimeoutExpired):
                raise RampFileError(f"timed out after {timeout:g} s (killed)") from None
            raise
        if proc.returncode != 0:
            lines = [ln for ln in (stderr or "").splitlines() if ln.strip()]
            raise RampFileError(f"exit status {proc.returncode}: {lines[-1].strip() if lines else '(no stderr)'}")
        if not os.path.isfile(out):
            raise RampFileError("exit status 0 but no output file")
        rate, err, dq, unit = _read_rate_file(out, exposure.sci.shape[2:], float(exposure.attrs["GAIN"]))
    notes = [unit] + ([] if err is not None else ["no ERR extension: pulls are NaN"])
    notes.append("no group flags from an exec pipeline: jump and saturation scores are NaN")
    return PipelineOutput(rate, err, dq, None, notes)


def run_pipeline(name, argv, exposure, workdir=None, exec_timeout=EXEC_TIMEOUT):
    """Run one pipeline on one exposure.

    Parameters
    ----------
    name : str
        "stcal", "slicersim" or "exec:..." (:func:`parse_pipelines`).
    argv : list of str or None
        The command of an exec pipeline.
    exposure : Exposure
    workdir : str, optional
        Folder of the exec pipeline's temporary files (default: the system's).
    exec_timeout : float
        Seconds an exec pipeline may run on the exposure; then it and what it started are killed
        and the exposure fails.

    Returns
    -------
    PipelineOutput
    """
    if name == "stcal":
        require_stcal()
        return _stcal(exposure)
    if name == "slicersim":
        return _slicersim(exposure)
    return _exec(exposure, argv, workdir, exec_timeout)


def finite_or_nan(value):
    """``value`` as a float, NaN when it is not a finite number."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return math.nan
    return v if math.isfinite(v) else math.nan
