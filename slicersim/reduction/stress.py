"""The pipeline stress harness: run ramp pipelines on every exposure of a campaign dataset, on
Dask, and score them against the truth the ramp files carry (``slicersim stress DATASET --out DIR``).

``stress_dataset(DATASET, OUT, pipelines=("stcal", "slicersim"))`` runs one Dask task per exposure
(the campaign's ramps of each target; the embedded LocalCluster of ``slicersim reduce`` or an
existing scheduler, :func:`slicersim.reduction.campaign.reduction_client`).  Each task reads the
ramp file once, runs every pipeline on it (:mod:`slicersim.reduction.stress_pipelines`) and scores
each output (:mod:`slicersim.reduction.stress_score`); a pipeline that fails is recorded as failed
with its error's one line, and the others go on.  The folder OUT gets (written under a temporary
name and renamed complete; an existing OUT only with ``overwrite``)::

    stress.ecsv         one row per exposure × pipeline and one aggregate row per pipeline
                        (target_id −1), units and descriptions in the column metadata
    report.md           one page: per pipeline, recall, false flags, saturation, lost pixels, the
                        slope bias and pulls per flux bin, and the bins where it is biased
    recall_vs_sigma.png, pull_vs_flux.png
"""
from __future__ import annotations

import os
import shutil
import time

import numpy as np

from slicersim import validation
from slicersim.errors import DatasetError, ParameterError
from slicersim.reduction import stress_score as score
from slicersim.reduction.stress_pipelines import EXEC_TIMEOUT

__all__ = ["stress_dataset", "stress_exposure", "score_output", "STRESS_TABLE", "REPORT", "FIGURES"]

STRESS_TABLE, REPORT = "stress.ecsv", "report.md"
FIGURES = ("recall_vs_sigma.png", "pull_vs_flux.png")


def _jump_truth(exposure):
    """(truth jumps or None, notes): the cosmic-ray truth, empty when the ramps were simulated without
    cosmic rays, None (scores NaN) when they had them and the file holds no truth."""
    import json
    from slicersim.products.effects import CR_DTYPE
    if "cosmic_rays" in exposure.truth:
        return exposure.truth["cosmic_rays"], []
    text = exposure.attrs.get("EFFECTS") or "{}"
    try:
        enabled = json.loads(text).get("effects", {}).get("enabled", []) if isinstance(text, str) else []
    except ValueError:
        enabled = []
    if "cosmic_rays" in enabled:
        return None, ["cosmic rays simulated but no truth/cosmic_rays in the file: jump scores are NaN"]
    return np.zeros(0, CR_DTYPE), ["no cosmic rays simulated: jump recall is NaN (no truth jump), false flags scored"]


def score_output(exposure, output, flux_bins=score.FLUX_BINS):
    """Score one pipeline's output against the exposure's truth.

    Parameters
    ----------
    exposure : slicersim.reduction.stress_pipelines.Exposure
    output : slicersim.reduction.stress_pipelines.PipelineOutput
    flux_bins : sequence of float
        Edges of the expected-rate bins [e-/s].

    Returns
    -------
    slicersim.reduction.stress_score.Score
        Every score column (NaN with a note where the truth or the output lacks what it needs).
    """
    from slicersim.reduction.stress_pipelines import expected_rate
    sc = score.Score()
    sc.notes += exposure.notes + output.notes
    expected, good, notes = expected_rate(exposure)
    sc.notes += notes
    shape = exposure.sci.shape[2:]
    a = exposure.attrs
    deposits, jnotes = _jump_truth(exposure)
    sc.notes += jnotes
    jump_cols = [f"{k}_{label}" for label in score.bin_labels(score.SIGMA_BINS, "sigma") +
                 score.bin_labels(score.CHARGE_BINS, "e")
                 for k in ("jump_recall", "jump_recall_err", "n_jump", "n_jump_found")] + \
        ["false_jump_rate", "n_false_jump", "n_pixel_groups"]
    if output.groupdq is None:
        sc.nan(jump_cols, "the pipeline gives no group flags: jump scores are NaN")
    elif deposits is None:
        sc.nan(jump_cols, jnotes[0])
    else:
        rate_for_sigma = expected if expected is not None else np.zeros(shape)
        if expected is None:
            sc.notes.append("no truth/rate: jump sizes in σ use the read noise alone")
        sigma = score.group_difference_sigma(rate_for_sigma, float(a["READNOISE"]), float(a["GAIN"]), exposure.nmd,
                                             float(a["TFRAME"]))
        jumps = score.truth_jumps(deposits, exposure.nmd, exposure.sci.shape[0], shape)
        sc.update(score.score_jumps(jumps, sigma, (output.groupdq & 4) != 0, good, exposure.saturated,
                                    ipc="ipc_kernel" in exposure.truth))
    if expected is None:
        cols = [f"{k}_{label}" for label in score.bin_labels(flux_bins)
                for k in ("n_slope", "slope_bias", "slope_resid_std", "slope_bias_err", "slope_rel_bias",
                          "pull_mean", "pull_width", "pull_outlier_frac")]
        sc.nan(cols, notes[0])
    else:
        sc.update(score.score_slopes(output.rate, output.err, expected, good, flux_bins))
    sat_cols = ["sat_recall", "sat_false_rate", "sat_agreement", "n_sat_truth", "n_sat_flagged"]
    if output.groupdq is None:
        sc.nan(sat_cols, "the pipeline gives no group flags: saturation scores are NaN")
    elif exposure.saturated is None:
        sc.nan(sat_cols, "no saturation truth in the ramp file: saturation scores are NaN")
    else:
        sc.update(score.score_saturation((output.groupdq & 2) != 0, exposure.saturated, good))
    sc.update(score.score_lost(output.rate, output.dq, good))
    return sc


def stress_exposure(task, threads=None):
    """The unit of work of a worker: read one exposure, run every pipeline on it and score each.

    Parameters
    ----------
    task : dict
        ``target_id``, ``path`` (ramp file), ``pipelines`` [(name, argv or None)], ``flux_bins``,
        ``workdir`` (temporary files of exec pipelines).
    threads : int, optional
        Threads per worker (BLAS, OpenCL).

    Returns
    -------
    dict
        ``target_id``, ``path``, ``status`` ("done"), ``rows``: one dict per pipeline with
        ``pipeline``, ``status`` ("done" or "failed"), ``error``, ``seconds``, ``values``, ``notes``.
        Errors are recorded, never raised.
    """
    from slicersim.campaign.products import limit_threads
    from slicersim.reduction.stress_pipelines import load_exposure, run_pipeline
    limit_threads(threads)
    rows = []
    try:
        exposure = load_exposure(task["path"])
    except Exception as exc:
        err = _one_line(exc)
        rows = [{"pipeline": name, "status": "failed", "error": f"cannot read the exposure: {err}", "seconds": 0.0,
                 "values": {}, "notes": []} for name, _ in task["pipelines"]]
        return {"target_id": task["target_id"], "path": task["path"], "status": "done", "rows": rows}
    for name, argv in task["pipelines"]:
        t0 = time.perf_counter()
        try:
            out = run_pipeline(name, argv, exposure, task.get("workdir"), task.get("exec_timeout", EXEC_TIMEOUT))
            seconds = time.perf_counter() - t0
            sc = score_output(exposure, out, task["flux_bins"])
            rows.append({"pipeline": name, "status": "done", "error": "", "seconds": seconds, "values": sc.values,
                         "notes": sc.notes})
        except Exception as exc:
            rows.append({"pipeline": name, "status": "failed", "error": _one_line(exc),
                         "seconds": time.perf_counter() - t0, "values": {}, "notes": []})
    return {"target_id": task["target_id"], "path": task["path"], "status": "done", "rows": rows}


def _one_line(exc):
    return f"{type(exc).__name__}: {' '.join(str(exc).split())}"[:500]


class _NoRecords:
    """The record sink of :func:`slicersim.campaign.runner.run_task_window`: the harness writes its
    results at the end, in one table."""

    def write_record(self, tid, record):
        pass


def _check_out(out, dataset, overwrite):
    path = os.path.abspath(os.fspath(out))
    if os.path.lexists(path):
        if not overwrite:
            raise ParameterError(f"--out {path} exists: pass --overwrite (overwrite=True) to replace it")
        if os.path.islink(path) or not os.path.isdir(path):
            raise ParameterError(f"--out {path} exists and is not a folder: it is not replaced, even with --overwrite")
        if os.path.isfile(os.path.join(path, "spec.json")):
            raise ParameterError(f"--out {path} is a dataset or reduction directory: it is never replaced")
    parent = os.path.dirname(path)
    if not os.path.isdir(parent):
        raise ParameterError(f"--out {path}: its parent {parent} " +
                             ("is not a folder" if os.path.lexists(parent) else "does not exist"))
    real, src = os.path.realpath(path), os.path.realpath(os.fspath(dataset))
    if real == src or real.startswith(src + os.sep) or src.startswith(real + os.sep):
        raise ParameterError(f"--out {path} must not be the dataset {src}, lie inside it or contain it")
    return path


def _exposures(dataset):
    """(dataset path, [(target id, ramp path)], {target id: (ramp path, why)} of the targets whose ramps
    the campaign made but are missing or damaged now, [target ids without ramps: not simulated, failed])."""
    from slicersim.reduction.campaign import _source, _sources, _unavailable_reason
    src, _, _, catalog = _source(dataset)
    ids = [int(t) for t in catalog["target_id"]]
    found = _sources(src, ids)
    damaged, without = {}, []
    for tid, (st, rec, _) in src.state([t for t in ids if t not in found], deep=False).items():
        info = (rec or {}).get("products", {}).get("ramps") if (rec or {}).get("status") == "done" else None
        if st != "done" and isinstance(info, dict) and info.get("file"):
            damaged[tid] = (os.path.join(src.product_dir(tid), str(info["file"])), _unavailable_reason(src, tid))
        else:
            without.append(tid)
    if not found and not damaged:
        raise DatasetError(f"{src.path}: no ramps to stress (no target done with its ramps; run the campaign first)")
    return src.path, [(tid, found[tid]["path"]) for tid in ids if tid in found], damaged, without


def stress_dataset(dataset, out, *, pipelines=("stcal", "slicersim"), workers=None, scheduler=None, security=None,
                   dashboard=False, overwrite=False, progress=None, flux_bins=score.FLUX_BINS, window=None,
                   exec_timeout=None):
    """Run ``pipelines`` on every exposure of campaign ``dataset`` and write the scores into ``out``.

    Parameters
    ----------
    dataset : path
        A campaign dataset with ramps (``products.ramps = true``).
    out : path
        The folder written (module docstring); refused when it exists, unless ``overwrite``.
    pipelines : sequence of str
        "stcal", "slicersim", "exec:COMMAND" (:func:`slicersim.reduction.stress_pipelines.parse_pipelines`).
    workers : int, optional
        Workers of the embedded LocalCluster (default: the CPU count).
    scheduler : str, optional
        An existing Dask scheduler (every worker must see the dataset; the results come back to this
        process).
    security : distributed.Security, optional
        To reach ``scheduler``.
    dashboard : bool
        The embedded cluster's dashboard.
    overwrite : bool
        Replace an existing ``out`` folder.
    progress : bool or None
        Progress bar (None: when stderr is a terminal).
    flux_bins : sequence of float
        Expected-rate bin edges of the slope scores [e-/s].
    window : int, optional
        Tasks in flight (default 2 per worker).
    exec_timeout : float, optional
        Seconds an ``exec:`` pipeline may run on one exposure (default
        :data:`~slicersim.reduction.stress_pipelines.EXEC_TIMEOUT`, an hour); then it is killed and
        the exposure is failed for it.

    Returns
    -------
    dict
        ``out``, ``table`` (astropy Table of stress.ecsv), ``report``, ``figures`` (paths),
        ``exposures`` (those of the targets the campaign made ramps for, a missing or damaged ramp
        file failed in every pipeline), ``failed`` [(target id, pipeline, error)], ``without_ramps``
        [target ids with no ramps: not simulated, failed or made without], ``biased`` {pipeline:
        [bins]}, ``seconds``.
    """
    from slicersim.campaign.runner import QuietDask, check_workers, run_task_window
    from slicersim.io.atomic import temporary_path
    from slicersim.io.row_blocks import show_progress
    from slicersim.reduction.campaign import reduction_client
    from slicersim.reduction.stress_pipelines import parse_pipelines, require_stcal
    from slicersim.reduction.stress_report import write_outputs
    t0 = time.perf_counter()
    parsed = parse_pipelines(pipelines)
    if any(name == "stcal" for name, _ in parsed):
        require_stcal()
    flux_bins = tuple(float(v) for v in flux_bins)
    if len(flux_bins) < 2 or any(not b > a for a, b in zip(flux_bins[:-1], flux_bins[1:])) or flux_bins[0] < 0:
        raise ParameterError(f"flux_bins must be ≥ 2 increasing edges ≥ 0 [e-/s], got {flux_bins}")
    if not isinstance(dataset, (str, os.PathLike)) or not os.fspath(dataset):
        raise ParameterError(f"dataset must be a path, got {validation.short_repr(dataset)}")
    if not os.path.isdir(dataset):
        raise DatasetError(f"{dataset}: not a campaign dataset directory")
    path = _check_out(out, dataset, overwrite)
    src_path, exposures, damaged, without = _exposures(dataset)
    progress = show_progress(progress)
    nw = check_workers(workers) if scheduler is None else 1
    if window is not None:
        validation.positive_int("window", window)
    exec_timeout = EXEC_TIMEOUT if exec_timeout is None else validation.number("exec_timeout [s]", exec_timeout,
                                                                                 low=0.0, low_open=True)
    _remove_stale_folders(path)
    tmp = temporary_path(path)
    os.mkdir(tmp)
    try:
        work = os.path.join(tmp, ".work")
        os.mkdir(work)
        tasks = {tid: {"target_id": tid, "path": p, "pipelines": parsed, "flux_bins": flux_bins, "workdir": work,
                      "exec_timeout": exec_timeout}
                 for tid, p in exposures}
        threads = max(1, (os.cpu_count() or 1) // nw)
        records = {}

        def submit(tid):
            return client.submit(stress_exposure, tasks[tid], threads, pure=False, retries=0,
                                 key=f"slicersim-stress-{os.getpid()}-{tid}")

        def lost(tid, exc):
            return {"target_id": tid, "path": tasks[tid]["path"], "status": "failed",
                    "rows": [{"pipeline": name, "status": "failed", "error": f"task lost: {_one_line(exc)}",
                              "seconds": 0.0, "values": {}, "notes": []} for name, _ in parsed]}
        if tasks:
            client, cluster = reduction_client(nw, scheduler, threads, security, dashboard)
            run_task_window(client, cluster, QuietDask(), list(tasks), submit, records, _NoRecords(), window=window,
                            workers=nw, progress=progress, desc="stress", lost_record=lost, checkpoint=lambda: None)
        for tid, (ramp, why) in damaged.items():        # made by the campaign, unreadable now: failed, not skipped
            records[tid] = {"target_id": tid, "path": ramp, "status": "failed",
                            "rows": [{"pipeline": name, "status": "failed", "error": f"no ramps to read: {why}",
                                      "seconds": 0.0, "values": {}, "notes": []} for name, _ in parsed]}
        shutil.rmtree(work, ignore_errors=True)
        order = sorted({tid for tid, _ in exposures} | set(damaged))
        result = write_outputs(tmp, [records[tid] for tid in order if tid in records], parsed, src_path, flux_bins)
        _publish(tmp, path, overwrite)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    failed = [(int(r["target_id"]), row["pipeline"], row["error"]) for r in records.values() for row in r["rows"]
              if row["status"] == "failed"]
    return {"out": path, "table": result["table"], "report": os.path.join(path, REPORT),
            "figures": [os.path.join(path, f) for f in FIGURES], "exposures": len(exposures) + len(damaged),
            "failed": failed, "without_ramps": without,
            "biased": result["biased"], "seconds": time.perf_counter() - t0}


def _remove_stale_folders(path):
    """Remove the temporary folders of ``path`` left by harness runs that were killed (a dead process of
    this host); a running writer's folder is kept."""
    from slicersim.io.atomic import remove_stale_temporaries
    directory, base = os.path.split(path)
    remove_stale_temporaries(directory or ".", final=base, folders=True)


def _publish(tmp, path, overwrite):
    """Give the complete folder ``tmp`` the name ``path`` (an existing one replaced only with ``overwrite``)."""
    from slicersim.io.atomic import temporary_path
    if not os.path.lexists(path):
        try:
            os.rename(tmp, path)
            return
        except OSError:
            if not os.path.lexists(path):
                raise
    if not overwrite:
        raise ParameterError(f"--out {path} appeared while the harness ran: pass --overwrite to replace it")
    old = temporary_path(path)
    os.rename(path, old)
    os.rename(tmp, path)
    shutil.rmtree(old, ignore_errors=True)

