"""Raw up-the-ramp H4RG reads: exact sampling of MACC(n, m, d) ramps.

Readout physics in small documented steps (cf. romanisim ``l1``):

1. :func:`frame_mean_charge` — mean charge collected per frame μ = (rate + dark
   + thermal dark)·t_f + ROIC glow  [e-/frame];
2. charge accumulation, a Poisson process sampled exactly by one of two paths
   chosen from μ only: *dense* — a Poisson increment in every frame; *sparse*
   (μ·(m+d) < ``sparse_max_group``, default ≈ μ < 0.75 e-/frame) — per group window
   (m reads + d dropped frames) a Poisson count and a uniform frame for each
   event, so a dark pixel costs one uniform and one Gaussian per group;
3. full-well clipping; group averaging of the m reads with read noise
   σ_r/√m per group; kTC reset noise once per ramp;
4. :func:`to_adu` — bias pedestal + gain, rounding and uint16 saturation;
   GROUPDQ flags (JWST SATURATED = 2).

Randomness is Philox4x32-10 keyed by (seed, ramp, pixel, frame or group): the
output is identical for any chunking, work-group size, vector width or device
count.  The OpenCL kernels are in ``kernels/ramp.cl``;
:func:`simulate_block_numpy` is their bit-exact NumPy twin.
"""
from __future__ import annotations

import math
import os

import numpy as np

from slicersim import rng
from slicersim.backends.ramp import simulate_block_numpy, simulate_block_opencl
from slicersim.io.rampfile import DQ, RampWriter
from slicersim.physics.ramp import (DEFAULT_BIAS, RampParameters, frame_mean_charge,  # noqa: F401
                                    macc_frame_schedule, readpatt)
from slicersim.physics.readout import readout_times

__all__ = ["simulate", "RampParameters", "frame_mean_charge", "macc_frame_schedule", "readpatt",
           "fit_slopes", "DEFAULT_BIAS"]


def simulate(rate, nmd=(16, 8, 0), nramps=1, seed=0, out=None, tframe=2.83, ron=12.0, dark=2.8e-3,
             thermal_dark=0.0, roic_glow=3e-3, gain=1.0, saturation=65535, bias=DEFAULT_BIAS,
             ktc_noise=0.0, full_well=None, dead_pixels=None, pixeldq=None, sparse_max_group=None,
             gauss_min_mean=np.inf, compression=None, memory_budget=2**29, truth=True,
             config=None, backend="auto", progress=None, work_group=None, return_dq=False, overwrite=False,
             effects=None, previous_charge=None, file_format=None, precision="auto"):
    """Simulate raw MACC ramps of a rate image.

    Parameters
    ----------
    rate : (ny, nx) photo-electron rate [e-/s] (detector terms are added here)
    nmd : (n, m, d) readout;  nramps : ramps between resets;  seed : int in [0, 2⁶⁴)
    out : HDF5 path (group-level file, see :mod:`slicersim.io.rampfile`) or None
    tframe [s], ron [e-/read], dark [e-/s, scalar or image], thermal_dark [e-/s],
    roic_glow [e-/frame], gain [ADU/e-], saturation [ADU], bias [ADU], ktc_noise [e-],
    full_well [e-] (default (saturation − bias)/gain)
    dead_pixels : bool (ny, nx) pixels collecting no charge;  pixeldq : uint32 (ny, nx) flags
    sparse_max_group : expected e- per group below which the sparse sampler is used (None:
        0.9·(m+d) − 1, see :func:`sparse_threshold`; capped at 64).  Both samplers are exact:
        this only trades speed.
    gauss_min_mean : Poisson mean above which a rounded Gaussian replaces the exact draw
    memory_budget : bytes of host memory for the row blocks and, with correlated noise, a third of it
        for its cached segments (default 512 MiB: a full-detector ramp
        peaks below 1.5 GB; larger blocks are not faster)
    work_group : OpenCL local size (None: 64 on CPUs, the runtime's on GPUs); never changes the result
    overwrite : replace an existing ``out`` (default: refuse with :class:`~slicersim.errors.RampFileError`)
    effects : detector systematics (off by default): names (``"cosmic_rays,ipc"``, ``"all"``), a preset
        (``"lazuli"``), a config dict or a :class:`~slicersim.physics.effects.DetectorEffects`; see
        :mod:`slicersim.products.effects`.  Their truth is written to ``truth/<name>``
        of ``out`` (with ``out=None`` only SCI is returned: write a file to keep the truth).
    previous_charge : (ny, nx) charge [e-] of the previous exposure, for ``persistence``
    file_format : ``"hdf5"`` (group-level file, :mod:`slicersim.io.rampfile`) or ``"jwst-uncal"`` (JWST
        level-1b FITS, :mod:`slicersim.io.uncal`); None: ``jwst-uncal`` for a ``.fits`` name, else hdf5.
        The same seed gives the same SCI in both formats.
    precision : ``"auto"`` (default), ``"double"`` or ``"single"`` floating type of the samplers
        (:mod:`slicersim.backends.precision`).  Single draws from the same Philox words: its SCI equal
        double's except where a float rounding moves a decision (measured: ~1e-3 of the values, mostly
        by 1 ADU; not bit-identical), with the same statistics; with ``effects`` the charge sampler and
        the readout (IPC, noise, digitisation) run in float too (the effects' maps and draws stay float64).

    The output size is checked against the free disk space (``out``) or memory (``out`` None)
    before anything is allocated.

    Returns
    -------
    SCI (nramps, ngroups, ny, nx) uint16 when ``out`` is None (and GROUPDQ with
    ``return_dq``), else the path written.
    """
    rate = np.asarray(rate, dtype=float)
    if rate.ndim != 2 or rate.size == 0:
        raise ValueError(f"rate must be a non-empty 2-D image (ny, nx), got shape {rate.shape}")
    if not np.all(np.isfinite(rate)):
        raise ValueError(f"rate contains {np.count_nonzero(~np.isfinite(rate))} NaN/inf pixel(s)")
    if np.any(rate < 0):
        raise ValueError(f"rate contains {np.count_nonzero(rate < 0)} negative pixel(s) [e-/s]")
    dark_arr = np.asarray(dark, dtype=float)
    if np.any(~np.isfinite(dark_arr)) or np.any(dark_arr < 0):
        raise ValueError("dark must be finite and ≥ 0")
    seed = int(rng.seed_to_key(seed).astype(np.uint64)[0] | (rng.seed_to_key(seed).astype(np.uint64)[1] << np.uint64(32)))
    p = RampParameters(nmd=nmd, nramps=nramps, tframe=tframe, ron=ron, dark=0.0, thermal_dark=thermal_dark,
                       roic_glow=roic_glow, gain=gain, saturation=saturation, bias=bias, ktc_noise=ktc_noise,
                       full_well=full_well, sparse_max_group=sparse_max_group, gauss_min_mean=gauss_min_mean)
    from slicersim.products.effects import EffectsPlan, resolve_effects
    fx = resolve_effects(effects, has_previous_charge=previous_charge is not None)
    if previous_charge is not None and (fx is None or "persistence" not in fx.enabled):
        from slicersim.errors import EffectsError
        raise EffectsError("previous_charge is given but the persistence effect is not enabled "
                           "(add 'persistence' to effects)")
    from slicersim.backends.precision import resolve_precision
    backend, precision = resolve_precision(precision, backend, "ramp")
    ny, nx = rate.shape
    if ny * nx >= 2**32:
        raise ValueError("image too large: pixel indices must fit in 32 bits")
    n = p.nmd[0]
    dead = None if dead_pixels is None else np.asarray(dead_pixels, bool)
    if dead is not None and dead.shape != rate.shape:
        raise ValueError("dead_pixels must have the shape of rate")
    # bytes per pixel in flight: mu + dead + index list + SCI + GDQ (host and device copies); with
    # effects also the group means (8 B), flags, read-domain noise (4 B) and deposits
    per_row = nx * (8 + 1 + 4 + 3 * n) * 2 if fx is None else nx * (8 + 1 + 4 + 16 + 16 * n) * 2
    # a third of the budget (with correlated noise) keeps the noise segments that span row blocks
    noise_cache = memory_budget // 3 if fx is not None and "correlated_noise" in fx.enabled else 0
    rows = int(max(1, min(ny, (memory_budget - noise_cache) // per_row)))
    if memory_budget - noise_cache < per_row:
        raise MemoryError(f"memory budget {memory_budget} B is smaller than one detector row "
                          f"({per_row} B for {n} groups{' plus the noise cache' if noise_cache else ''})")
    # sizes first: nothing below is allocated before the output is known to fit
    writer = None
    if out is not None:
        writer_class = _writer_class(out, file_format)
        truth_bytes = EffectsPlan.truth_nbytes(fx, p, (ny, nx)) if (fx is not None and truth) else 0
        writer = writer_class(out, p.nramps, n, (ny, nx), row_block=min(rows, 256), compression=compression,
                              truth_rate=truth, overwrite=overwrite, extra_bytes=truth_bytes).check()
    else:
        full_bytes = p.nramps * n * ny * nx * (3 if return_dq else 2)
        if full_bytes > 16 * memory_budget:
            raise MemoryError(f"returning SCI in memory needs {full_bytes / 2**30:.1f} GiB: pass out=<file.h5>")
        avail = _available_memory()
        if avail is not None and full_bytes > avail:
            raise MemoryError(f"returning SCI in memory needs {full_bytes / 2**30:.1f} GiB, "
                              f"{avail / 2**30:.1f} GiB available: pass out=<file.h5>")
    if dead is None:
        dead = np.zeros(rate.shape, bool)
    plan, rate_in = None, rate
    dq_dead = dead                                   # pixels flagged DEAD in PIXELDQ
    dark_mean = float(np.mean(dark_arr))             # the detector's dark: hot/warm pixels' extra dark is truth
    if fx is not None:
        plan = EffectsPlan(fx, p, seed, rate.shape, previous_charge, noise_cache_bytes=noise_cache)
        rate, dark_arr, no_charge, flags = plan.rate_and_dark(rate, dark_arr, dead)
        flags[dead] |= np.uint32(DQ["DEAD"] | DQ["DO_NOT_USE"])              # the user's dead pixels
        pixeldq = flags if pixeldq is None else (np.asarray(pixeldq, np.uint32) | flags)
        dead, flags, no_charge = dead | no_charge, None, None
    mu = frame_mean_charge(rate, dark_arr, thermal_dark, roic_glow, tframe)
    if precision == "single":
        mu = _single_frame_means(mu, p)
    rate = dark_arr = None                           # the effects' copies: not needed past mu
    block = simulate_block_opencl if backend == "opencl" else simulate_block_numpy
    kwargs = {}
    if backend == "opencl":
        kwargs = {"work_group": work_group, "want_dq": out is not None or return_dq, "workspace": {},
                  "precision": precision}
    nsteps = p.nramps * -(-ny // rows)
    steps = ((r, y0) for r in range(p.nramps) for y0 in range(0, ny, rows))     # lazy: nramps may be huge
    if progress is None:
        progress = nsteps > 4
    iterator = steps
    if progress:
        from tqdm.auto import tqdm
        iterator = tqdm(steps, desc="ramps", unit="block", total=nsteps)
    attrs = p.attrs(seed)
    attrs.update({"SOFTWARE": "slicersim", "VERSION": _version(), "BACKEND": backend, "PRECISION": precision,
                  "CONFIG": config if config is not None else {}, "DARK": dark_mean,
                  "THERMAL_DARK": thermal_dark, "ROIC_GLOW": roic_glow, "KTC_NOISE": ktc_noise})
    result = None if out is not None else np.empty((p.nramps, n, ny, nx), np.uint16)
    result_dq = np.empty((p.nramps, n, ny, nx), np.uint8) if (out is None and return_dq) else None
    if writer is not None:
        writer.attrs = attrs

    if plan is not None:
        attrs["EFFECTS"] = fx.to_config()

    buffers = []

    def block_buffers(size):
        if not buffers:
            buffers.extend([np.empty(size, np.uint16), np.empty(size, np.uint8)])
        return buffers

    def run(w):
        nonlocal pixeldq
        if w is not None:
            w.write_pixeldq(_pixeldq(pixeldq, dq_dead, rate_in.shape))
            if truth:
                w.write_truth(rate_in)
        pixeldq = None                                   # written: 4 B per pixel less in the blocks
        # effects into an HDF5 file: their truth (mostly single-threaded NumPy) and the HDF5 writes of
        # the blocks run in two background threads while this one computes the next blocks
        background = _Background() if (plan is not None and isinstance(w, RampWriter)) else None
        try:
            run_blocks(w, background)
        except BaseException:
            if background is not None:
                background.finish(raise_error=False)         # the file is aborted after the lanes stop
            raise
        if background is not None:
            background.finish()

    def run_blocks(w, background):
        if plan is not None and background is not None:
            # the bad-pixel maps first, here, then freed (3 × 4 B per pixel less while the blocks run);
            # the rest of the truth in the background
            if truth:
                plan.write_truth(w, p.nramps, part="maps")
            plan.drop_photo_maps()
            if truth:
                background.submit("truth", plan.write_truth, w, p.nramps, "rest")
        elif plan is not None:
            if w is not None and truth:
                plan.write_truth(w, p.nramps)
            plan.drop_photo_maps()                   # used by rate_and_dark and the truth only
        for ramp, y0 in iterator:
            y1 = min(ny, y0 + rows)
            if plan is not None:
                sci, gdq = _effects_block(plan, mu, dead, ramp, y0, y1, seed, p, backend, kwargs)
                if background is not None:               # fresh arrays each block: handed over
                    background.submit("write", w.write_block, ramp, y0, sci, gdq)
                elif w is not None:
                    w.write_block(ramp, y0, sci, gdq)
                else:
                    result[ramp, :, y0:y1] = sci
                    if result_dq is not None:
                        result_dq[ramp, :, y0:y1] = gdq
                continue
            direct = {}
            if w is None and backend == "opencl" and y0 == 0 and y1 == ny:     # whole ramp: no copy
                direct = {"sci_out": result[ramp].reshape(n, -1)}
                if result_dq is not None:
                    direct["gdq_out"] = result_dq[ramp].reshape(n, -1)
            elif w is not None and backend == "opencl":      # one pair of host buffers for every block
                npix = (y1 - y0) * nx
                sci_buf, gdq_buf = block_buffers(n * rows * nx)
                reused = {"sci_out": sci_buf[:n * npix].reshape(n, npix),
                          "gdq_out": gdq_buf[:n * npix].reshape(n, npix)}
                sci, gdq = block(mu[y0:y1].ravel(), dead[y0:y1].ravel(), y0 * nx, ramp, seed, p, **kwargs, **reused)
                w.write_block(ramp, y0, sci.reshape(n, y1 - y0, nx), gdq.reshape(n, y1 - y0, nx))
                continue
            sci, gdq = block(mu[y0:y1].ravel(), dead[y0:y1].ravel(), y0 * nx, ramp, seed, p, **kwargs, **direct)
            if direct:
                continue
            sci = sci.reshape(n, y1 - y0, nx)
            if w is not None:
                w.write_block(ramp, y0, sci, gdq.reshape(n, y1 - y0, nx))
            else:
                result[ramp, :, y0:y1] = sci
                if result_dq is not None:
                    result_dq[ramp, :, y0:y1] = gdq.reshape(n, y1 - y0, nx)
    if writer is None:
        run(None)
        return (result, result_dq) if return_dq else result
    with writer as w:
        run(w)
    return os.path.abspath(out)


class _Background:
    """Named single-thread lanes for the effects path of :func:`simulate` ("truth", "write"): each
    lane runs its jobs in order, at most one queued behind the running one (a block's SCI waits for
    the previous block's write, bounding memory to two blocks); the first error is raised by
    :meth:`submit` or :meth:`finish`, which waits for every lane.  h5py serialises the lanes' HDF5
    calls; NumPy, pocketfft, OpenCL waits and the file writes release the GIL meanwhile."""

    def __init__(self):
        from concurrent.futures import ThreadPoolExecutor
        self._pools = {name: ThreadPoolExecutor(1, thread_name_prefix=f"slicersim-{name}")
                       for name in ("truth", "write")}
        self._pending = {name: None for name in self._pools}

    def submit(self, lane, func, *args):
        self.raise_failed()
        previous = self._pending[lane]
        if previous is not None:
            previous.result()
        self._pending[lane] = self._pools[lane].submit(func, *args)

    def raise_failed(self):
        """Raise the error of any lane's job that has already failed (the truth lane's one job is
        otherwise looked at only in :meth:`finish`, after every block; a SIGINT held back while
        that lane was inside HDF5 is raised there as KeyboardInterrupt)."""
        for future in self._pending.values():
            if future is not None and future.done() and future.exception() is not None:
                raise future.exception()

    def finish(self, raise_error=True):
        error = None
        for lane, pool in self._pools.items():
            future, self._pending[lane] = self._pending[lane], None
            try:
                if future is not None:
                    future.result()
            except BaseException as exc:             # noqa: BLE001 - first error re-raised below
                error = error or exc
            finally:
                pool.shutdown(wait=True)
        if error is not None and raise_error:
            raise error


def _effects_block(plan, mu, dead, ramp, y0, y1, seed, p, backend, kwargs):
    """SCI, GROUPDQ (n, y1 − y0, nx) of rows [y0, y1) with detector effects (charge on the rows ± the
    IPC halo, then the readout)."""
    from slicersim.backends import ramp_effects as rfx
    ny, nx = mu.shape
    n = p.nmd[0]
    yi0, yi1 = max(0, y0 - plan.halo), min(ny, y1 + plan.halo)
    start, frame, electrons = plan.block_deposits(ramp, yi0, yi1)
    a2, a3 = plan.nonlinearity_block(yi0, yi1)
    charge_fx = rfx.ChargeEffects(start, frame, electrons, a2, a3)
    args = (mu[yi0:yi1].ravel(), dead[yi0:yi1].ravel(), yi0 * nx, ramp, seed, p, charge_fx)
    shape_in = (n, yi1 - yi0, nx)
    noise = plan.read_noise_block(ramp, y0, y1)
    common = dict(ipc=plan.ipc, extra=noise, bias_map=plan.bias_block(y0, y1))
    if backend == "opencl":               # group means stay on the device between the two kernels
        d_gmean, d_flags = rfx.charge_block_opencl(*args, work_group=kwargs.get("work_group"),
                                                   workspace=kwargs.get("workspace"), to_host=False,
                                                   precision=kwargs["precision"])
        return rfx.readout_opencl(d_gmean, d_flags, y1 - y0, y0 - yi0, y0, ny, ramp, seed, p,
                                  workspace=kwargs.get("workspace"), shape_in=shape_in,
                                  precision=kwargs["precision"], **common)
    gmean, qsat = rfx.charge_block_numpy(*args)
    return rfx.readout_numpy(gmean.reshape(shape_in), qsat.reshape(shape_in), y1 - y0, y0 - yi0, y0, ny, ramp,
                             seed, p, **common)


#: largest mean charge per frame [e-] the float samplers draw (float32 Poisson counts, as noise.cl)
SINGLE_MAX_FRAME_MEAN = float(2**22)


def _single_frame_means(mu, p):
    """μ [e-/frame] for the float samplers: a pixel whose μ exceeds the full well by 64 σ fills it in its
    first frame whatever μ (otherwise with probability < e⁻²⁰⁰⁰), so μ is capped there — float32
    would turn 1e39 into inf, and lose the draw's accuracy far below that.  Means above
    :data:`SINGLE_MAX_FRAME_MEAN` that the cap leaves (a full well above it) are refused."""
    cap = p.full_well + 64.0 * math.sqrt(p.full_well) + 64.0
    mu = np.minimum(mu, cap)
    if cap > SINGLE_MAX_FRAME_MEAN and float(np.max(mu, initial=0.0)) > SINGLE_MAX_FRAME_MEAN:
        from slicersim.errors import ParameterError
        raise ParameterError(f"precision 'single' draws at most {SINGLE_MAX_FRAME_MEAN:.4g} e- per frame; this ramp "
                             f"has pixels up to {float(np.max(mu)):.4g} e- per frame with a full well of "
                             f"{p.full_well:.4g} e-: use precision 'double'")
    return mu


FILE_FORMATS = ("hdf5", "jwst-uncal")


def _writer_class(out, file_format):
    """RampWriter or UncalWriter for ``file_format`` (None: from the extension of ``out``)."""
    if str(out).lower().endswith((".gz", ".bz2", ".xz", ".zip")):
        raise ValueError(f"{out}: ramp files are not written compressed by a file suffix; use a plain .h5/.fits "
                         "name (HDF5 compresses internally with compression=)")
    if file_format is None:
        file_format = "jwst-uncal" if str(out).lower().endswith((".fits", ".fit")) else "hdf5"
    if file_format == "hdf5":
        return RampWriter
    if file_format == "jwst-uncal":
        from slicersim.io.uncal import UncalWriter
        return UncalWriter
    raise ValueError(f"file_format must be one of {', '.join(FILE_FORMATS)} (or None), got {file_format!r}")


def _available_memory():
    """Bytes of memory available to this process (Linux MemAvailable, else free pages), or None."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _pixeldq(pixeldq, dead, shape):
    flags = np.zeros(shape, np.uint32) if pixeldq is None else np.asarray(pixeldq, np.uint32).copy()
    flags[dead] |= DQ["DEAD"] | DQ["DO_NOT_USE"]
    return flags


def _version():
    from slicersim.versioning import __version__
    return __version__


def fit_slopes(sci, nmd, tframe, gain=1.0, groupdq=None):
    """Unweighted least-squares slopes over group means [e-/s] of SCI (ngroups, ...) ADU.

    Groups flagged in ``groupdq`` (any bit) are excluded; a ramp broken by flagged groups is fitted
    per segment, the segments combined with read-noise weights.  This is the OLS fit of
    :mod:`slicersim.backends.ramp_fit` (NumPy twin) without jump detection; the full reduction
    (jumps, GLS weights, variances, corrections, files) is
    :func:`slicersim.reduction.ramp_fit.fit_ramps`.  Pixels with no two consecutive good groups give NaN.
    """
    from slicersim.backends.ramp_fit import fit_block_numpy, fit_constants
    sci = np.asarray(sci, dtype=float)
    flat = sci.reshape(1, sci.shape[0], -1)
    flags = np.zeros(flat.shape, np.uint8) if groupdq is None else \
        (np.asarray(groupdq).reshape(flat.shape) != 0).astype(np.uint8)        # DO_NOT_USE
    consts = fit_constants(nmd, tframe, gain, 0.0, 0.0, None, None, "ols")
    fit = fit_block_numpy(flat, flags, np.zeros(flat.shape[2], np.uint32), consts)[0]
    return fit[0].reshape(sci.shape[1:])
