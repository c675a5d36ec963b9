"""Demonstration run: exposure time of a z = 1 SN Ia with the Lazuli IFS.

``slicersim demo --outdir DIR`` (or :func:`run_demo`) solves the ETC for a SN Ia
at peak (SNR 20 per resolution element in the rest-frame 4000–6800 Å band),
prints a short report, compares the exact readout search with the slicersim 1.0
reference walk and writes ``spectrum.png``, ``variance_budget.png``,
``instrument.png`` and ``etc_result.json`` in the output directory, and one raw ramp of the
readout the ETC chose on a 600 × 500 px detector window around the source (``raw_ramp.h5``)
with its figure (``raw_ramp_group.png``: the group difference as a slope [ADU/s] next to a raw
group [ADU], titled with the target and the readout).

Running it again: with ``overwrite=True`` (``slicersim demo --overwrite``; ``make demo`` passes
it) the demo replaces its own files, :data:`DEMO_FILES`, each written to a temporary and renamed
in; it never touches any other file of the directory.  Without it, an existing demo file is
refused before any work (FileExistsError).
"""
from __future__ import annotations

import errno
import json
import math
import os
import time

import numpy as np

__all__ = ["run_demo", "DEMO_BAND", "DEMO_FILES"]

#: rest-frame band [Å] in which the SNR is required
DEMO_BAND = (4000.0, 6800.0)


def _plain(value):
    """JSON-serialisable copy (numpy scalars/arrays → Python, tuples → lists, NaN/inf → None)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, (bool, int, float, str)) or value is None:
        return value
    return str(value)


def _etc_summary(target, res, snr, search):
    nmd = tuple(int(v) for v in res["nmd"])
    texp = float(res["exposure_time"])
    return {"search": search,
            "nmd": list(nmd),
            "nramps": int(res["nramps"]),
            "exposure_time": texp,
            "exposure_time_min": texp / 60.0,
            "snr_per_resolution": float(res["snr_per_resolution"]),
            "snr_target_per_resolution": float(snr),
            "snr_per_bin": float(res["snr"]),
            "snr_target_per_bin": float(res["snr_target"]),
            "reached": bool(res["snr_per_resolution"] >= snr * (1 - 1e-12)),
            "lbda_range_obs": [float(v) for v in res["lbda_range_obs"]],
            "data_volume_gb": float(target.get_data_volume())}


def _pct(name, frac):
    pct = 100.0 * frac
    return f"{name} {pct:.1f}%" if abs(pct) >= 0.05 else f"{name} <0.1%"


def _report_lines(title, s):
    n, m, d = s["nmd"]
    ok = "reached" if s["reached"] else "not reached: the walk accepts 0.5 below target per bin"
    return [title,
            f"  readout (n, m, d) x ramps : ({n}, {m}, {d}) x {s['nramps']}",
            f"  exposure time             : {s['exposure_time']:.1f} s = {s['exposure_time_min']:.1f} min",
            f"  band SNR per resol. elem. : {s['snr_per_resolution']:.2f} (target {s['snr_target_per_resolution']:g}, "
            f"{ok})",
            f"  band SNR per bin          : {s['snr_per_bin']:.2f} (target {s['snr_target_per_bin']:.2f})",
            f"  data volume               : {s['data_volume_gb']:.2f} GB"]


#: files written by :func:`run_demo` (the last two only with ``ramp_nmd``)
DEMO_FILES = ("spectrum.png", "variance_budget.png", "instrument.png", "etc_result.json", "raw_ramp.h5",
              "raw_ramp_group.png")


def run_demo(outdir="demo_output", redshift=1.0, snr=20.0, config="cbe", field="narrow", verbose=True,
             ramp_nmd="etc", overwrite=False, ramp_window=(600, 500)):
    """Run the demonstration ETC and write its figures and JSON summary into ``outdir``.

    Parameters
    ----------
    outdir : output directory (created if needed)
    redshift : SN Ia redshift
    snr : target band SNR per resolution element in the rest-frame band :data:`DEMO_BAND`
    config, field : Lazuli configuration ("cbe", "eol", TOML path(s)) and field ("narrow", "wide")
    verbose : print the report
    ramp_nmd : readout of the raw ramp: "etc" (default: the (n, m, d) the ETC chose, one of its
        ramps), an (n, m, d) triple, or None (no ramp)
    ramp_window : (rows, cols) [px] of the detector window around the source that the ramp
        covers (None: the full detector)
    overwrite : replace the demo's own output files (:data:`DEMO_FILES`; no other file of
        ``outdir`` is touched); default: refuse with FileExistsError before any work

    Returns
    -------
    dict (JSON-serialisable, also written to ``outdir/etc_result.json``): target and
    instrument, the exact-search result (nmd, nramps, exposure_time [s], SNRs,
    data_volume_gb, variance_budget fractions in the band), the reference-search
    result under ``"reference"`` and the written ``files``.
    """
    from slicersim.versioning import __version__
    from slicersim.targets import LazuliSupernova

    t0 = time.perf_counter()
    out = print if verbose else (lambda *a, **k: None)
    if os.path.lexists(outdir) and not os.path.isdir(outdir):       # makedirs said only "File exists"
        raise NotADirectoryError(errno.ENOTDIR, "--outdir (outdir) must be a directory, not a file", str(outdir))
    _refuse_existing(outdir, ramp_nmd, overwrite)
    os.makedirs(outdir, exist_ok=True)
    target = LazuliSupernova(redshift, config=config, field=field)
    exact = _exact_etc(target, snr)
    # slicersim 1.0 reference walk, for comparison
    ref_target = LazuliSupernova(redshift, config=config, field=field)
    reference = _etc_summary(ref_target, ref_target.setup_to_snr(snr, lbda_range=DEMO_BAND, frame="rest",
                                                                 search="reference"), snr, "reference")
    ramp = None if not ramp_nmd else (tuple(exact["nmd"]) if isinstance(ramp_nmd, str) and ramp_nmd == "etc"
                                      else tuple(ramp_nmd), ramp_window)
    files = _write_figures(target, outdir, ramp, overwrite, _ramp_title(target, exact, redshift, snr))
    lo, hi = DEMO_BAND
    summary = {"slicersim_version": __version__,
               "target": {"kind": "SN Ia (hsiao-subsampled, peak, M_B = -19.3)", "redshift": float(redshift),
                          "phase": float(getattr(target, "phase", 0.0))},
               "instrument": {"name": "Lazuli IFS", "config": config, "field": field},
               "band_rest": [lo, hi],
               **exact,
               "reference": reference,
               "files": files}
    summary = _plain(summary)
    from slicersim.io.atomic import atomic_bytes     # a temporary renamed in: a rerun replaces it whole
    atomic_bytes(files["etc_result"], (json.dumps(summary, indent=2) + "\n").encode("utf-8"), overwrite=True)
    summary["elapsed_s"] = time.perf_counter() - t0
    _print_report(out, summary, exact, reference, (redshift, snr, config, field, outdir))
    return summary


def _refuse_existing(outdir, ramp_nmd, overwrite):
    """FileExistsError (before any work) for an output file already in ``outdir``, unless ``overwrite``."""
    if overwrite:
        return
    for name in DEMO_FILES[:None if ramp_nmd else 4]:
        path = os.path.join(outdir, name)
        if os.path.lexists(path):
            raise FileExistsError(errno.EEXIST, "output file exists (use --overwrite / overwrite=True "
                                  "to replace it)", path)


def _exact_etc(target, snr):
    """The exact search (default) on ``target`` and its band variance budget (fractions)."""
    res = target.setup_to_snr(snr, lbda_range=DEMO_BAND, frame="rest")
    exact = _etc_summary(target, res, snr, "exact")
    budget = target.get_band_variance_contribution(lbda_range=DEMO_BAND, frame="rest")
    exact["variance_budget"] = {k[len("frac_"):]: float(v) for k, v in budget.items() if k.startswith("frac_")}
    exact["band_signal_adu"] = float(budget["signal"])
    exact["band_variance_adu2"] = float(budget["variance"])
    return exact


def _ramp_title(target, exact, redshift, snr):
    """Title of the raw-ramp figure: the target (type, redshift) and the readout the ETC chose."""
    n, m, d = exact["nmd"]
    lo, hi = DEMO_BAND
    return (f"{type(target).__name__}: SN Ia at peak, z = {redshift:g}; ETC readout for SNR {snr:g} per resolution "
            f"element in rest {lo:.0f}–{hi:.0f} Å: (n, m, d) = ({n}, {m}, {d}) × {exact['nramps']} ramp(s), "
            f"{exact['exposure_time']:.0f} s")


def _write_figures(target, outdir, ramp, overwrite, ramp_title=None):
    """Spectrum, variance budget and instrument figures, and (with ``ramp``: (nmd, window)) a raw
    ramp and its figure (titled ``ramp_title``); returns the paths (with the JSON summary's).
    Figures are written atomically (a temporary renamed in, replacing a previous run's); the
    ramp replaces a previous one with ``overwrite``."""
    from slicersim.app.plotting import plot_instrument, plot_ramp_group, plot_spectrum, plot_variance_budget
    files = {"spectrum": os.path.join(outdir, "spectrum.png"),
             "variance_budget": os.path.join(outdir, "variance_budget.png"),
             "instrument": os.path.join(outdir, "instrument.png"),
             "etc_result": os.path.join(outdir, "etc_result.json")}
    plot_spectrum(target, seed=1, savefile=files["spectrum"])
    plot_variance_budget(target, savefile=files["variance_budget"])
    plot_instrument(target.simulation, savefile=files["instrument"])
    if ramp:
        files["ramp"] = os.path.join(outdir, "raw_ramp.h5")
        files["ramp_group"] = os.path.join(outdir, "raw_ramp_group.png")
        nmd, window = ramp
        origin = _write_ramp(target, nmd, window, files["ramp"], overwrite)
        chosen = tuple(int(v) for v in target.get_readout_config()["nmd"])
        title = ramp_title + ("\nshown: one of these ramps" if tuple(nmd) == chosen
                              else f"\nshown: one ramp of readout (n, m, d) = {tuple(nmd)}")
        if window is not None:
            title += f", on a {window[0]} × {window[1]} px detector window around the source"
        plot_ramp_group(files["ramp"], savefile=files["ramp_group"], title=title, origin=origin)
    return files


def _write_ramp(target, nmd, window, path, overwrite):
    """One raw ramp of readout ``nmd`` (seed 2026) written to ``path``: of the full detector
    (``window`` None) or of a (rows, cols) [px] window around the source (the detector terms of
    the target's configuration, as :meth:`~slicersim.targets.Target.get_ramps`); returns the
    window's first pixel (row, col) on the detector."""
    if window is None:
        target.get_ramps(out=path, nmd=nmd, nramps=1, seed=2026, progress=False, overwrite=overwrite)
        return 0, 0
    from slicersim.plotting import source_zoom
    from slicersim.products.ramps import simulate
    image = target.get_detector_image()
    r0, r1, c0, c1 = source_zoom(image, half=(window[0] // 2, window[1] // 2))
    sim, det = target.simulation, target.simulation.detector
    simulate(image[r0:r1, c0:c1], nmd=nmd, nramps=1, seed=2026, out=path, overwrite=overwrite, progress=False,
             tframe=det.tframe, ron=det.ron, dark=det.dark, thermal_dark=sim.thermal_dark, roic_glow=det.roic_glow,
             gain=det.gain, saturation=min(det.saturation, 65535.0))
    return r0, c0


def _print_report(out, summary, exact, reference, run):
    """The demo's text report through ``out`` (print or a no-op); ``run``: (redshift, snr, config,
    field, outdir)."""
    from slicersim.versioning import __version__
    redshift, snr, config, field, outdir = run
    lo, hi = DEMO_BAND
    cfg = config if isinstance(config, str) else "+".join(map(str, config))
    out(f"slicersim {__version__} demo: SN Ia at z = {redshift:g} with the Lazuli IFS "
        f"({cfg}, {field} field)")
    out(f"goal: band SNR {snr:g} per resolution element in rest-frame {lo:.0f}-{hi:.0f} Å "
        f"(observed {exact['lbda_range_obs'][0]:.0f}-{exact['lbda_range_obs'][1]:.0f} Å)")
    out("")
    for line in _report_lines("exact search (default):", exact):
        out(line)
    out("  band variance budget      : " + ", ".join(
        _pct(k, v) for k, v in sorted(exact["variance_budget"].items(), key=lambda kv: -kv[1]) if v != 0.0))
    out("")
    for line in _report_lines("reference search (slicersim 1.0 walk, tolerance 0.5 per bin):", reference):
        out(line)
    dt = reference["exposure_time"] - exact["exposure_time"]
    out(f"  vs exact                  : {dt:+.1f} s exposure, "
        f"{reference['snr_per_resolution'] - exact['snr_per_resolution']:+.2f} SNR per resolution element")
    out("")
    out(f"wrote {', '.join(os.path.basename(p) for p in summary['files'].values())} in {os.path.abspath(outdir)}")
    out(f"({summary['elapsed_s']:.1f} s)")
