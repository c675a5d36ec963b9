"""Run a campaign on Dask: plan every target on the client, simulate them on the workers.

``run_campaign(spec, out)`` starts an embedded :class:`distributed.LocalCluster` (process
workers, one task each at a time, each with its own OpenCL context limited to its share of
the CPU threads) or connects to an existing scheduler (``scheduler="tcp://host:port"``,
e.g. started by dask-jobqueue on Slurm/PBS: every worker must see the dataset directory on a
shared file system and have slicersim installed).

Reproducible and resumable:

* the population, the readouts (batch ETC) and the seeds are computed on the client, each
  target's seeds from (campaign seed, target id) by Philox (:func:`target_seeds`);
* a worker writes a target's products atomically and its record last
  (:mod:`slicersim.io.dataset`), so after ``kill -9`` of the client or of a worker the same
  command computes only what is missing, truncated or corrupted (checksums);
* a failing target is recorded with its error and does not stop the campaign
  (``retry_failed`` runs the failed ones again);
* a directory made from another spec is refused unless ``force``.
"""
from __future__ import annotations


import logging
import os
import sys
import time
from dataclasses import dataclass

import numpy as np

from slicersim.campaign.cluster import DASHBOARD_ADDRESS, dashboard_address, dask_client, tls_security  # noqa: F401
from slicersim.campaign.products import (TASK_MAX_BYTES, build_target, registered_reducer, run_target, spectrum_grid,
                                         target_seeds)
from slicersim.campaign.spec import PRODUCTS, CampaignSpec, load_spec, seed_was_drawn, with_seed
from slicersim.errors import ConfigError, DatasetError
from slicersim.io.dataset import CATALOG, PRODUCTS as PRODUCT_DIR, Dataset, not_a_dataset_directory, spec_digest
from slicersim.io.row_blocks import show_progress
from slicersim.validation import checked_fields, positive_int

__all__ = ["run_campaign", "campaign_status", "plan_campaign", "software_versions", "RunOptions", "TaskWindow",
           "run_task_window", "WORKERS_PER_CPU", "check_workers", "dask_client", "QuietDask", "tls_security",
           "DASHBOARD_ADDRESS"]

#: seconds between two catalog writes while a campaign runs
CATALOG_INTERVAL = 10.0


def software_versions():
    """Versions of the packages that determine the products."""
    from importlib import metadata
    out = {"python": sys.version.split()[0]}
    for dist in ("slicersim", "numpy", "scipy", "astropy", "sncosmo", "h5py", "pyopencl", "dask", "distributed"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = None
    return out


def plan_campaign(spec):
    """Catalog of the campaign before any simulation: the population's parameters, the
    field, the readout of the batch ETC (one call per field), the exposure time, the SNR,
    the raw data volume and the seeds.  Targets the ETC cannot serve get ``status`` "failed"
    and their error in ``error``."""
    from slicersim.campaign.plan import plan_survey
    obs, survey = spec.observation, spec.survey
    from slicersim.campaign.plan import check_client_memory
    lbda = spectrum_grid()
    check_client_memory(getattr(spec.population, "n", 0), lbda.size)
    table = spec.population.draw(spec.seed)
    if len(table) == 0:
        raise ConfigError("the population is empty: nothing to simulate")
    check_client_memory(len(table), lbda.size)
    fluxes = np.asarray(spec.population.spectra(table, lbda), dtype=float)
    fluxes = np.where(np.isfinite(fluxes), fluxes, 0.0)      # outside a model's coverage: no flux
    z = np.asarray(table["redshift"], dtype=float)
    if obs["field"] is not None:
        zswitch, fields = (np.inf, (obs["field"],) * 2)
    else:
        zswitch, fields = obs["field_switch_redshift"], ("narrow", "wide")
    plan = plan_survey(z, lbda, fluxes, snr=obs["snr"], lbda_range=tuple(obs["lbda_range"]),
                       frame=obs["frame"], z_switch=zswitch, fields=fields, config=obs["config"],
                       search=obs["search"], conventions=obs["conventions"], overhead=survey["overhead"],
                       efficiency=survey["efficiency"], compression_ratio=survey["compression_ratio"],
                       target_ids=np.asarray(table["target_id"]), per_resolution=obs["per_resolution"])
    cat = table.copy()
    ptab = plan.table
    for name in ptab.colnames:
        if name not in ("target_id", "redshift"):
            cat[name] = ptab[name]
    if getattr(spec.population, "hosts", None) is not None:
        _host_aware_readouts(spec, cat, plan)
    seed, ramp_seed = target_seeds(spec.seed, cat["target_id"])
    cat["seed"], cat["ramp_seed"] = seed, ramp_seed
    if "status" not in cat.colnames:
        cat["status"] = "planned"
    if "error" not in cat.colnames:
        cat["error"] = ""
    if "phase" in cat.colnames:
        cat["phase"].unit, cat["phase"].description = "d", "rest-frame days from B-band maximum"
    cat.meta = {"name": spec.name, "seed": spec.seed, "totals": _jsonable(plan.totals), "phase_frame": "rest"}
    return cat, plan


def _host_aware_readouts(spec, cat, plan, progress=None):
    """Readouts with each target's host in the scene (its light adds photon noise the batch
    ETC, which knows point sources only, does not see): the single-target ETC per target,
    ~0.1 s each.  Updates ``cat`` and ``plan.totals`` in place."""
    from tqdm.auto import tqdm

    from slicersim.campaign.plan import BYTES_PER_READ, survey_totals
    obs, survey = spec.observation, spec.survey
    rows = [i for i in range(len(cat)) if str(cat["status"][i]) != "failed"]
    status, error = [str(v) for v in cat["status"]], [str(v) for v in cat["error"]]   # no fixed-width truncation
    shape = None
    bar = show_progress(progress) and len(rows) >= 20
    for i in tqdm(rows, desc="ETC with hosts", unit="target", disable=not bar):
        row = _row_dict(cat[i])
        try:
            target, _ = build_target(spec, row, readout=False)
            res = target.setup_to_snr(obs["snr"], tuple(obs["lbda_range"]), frame=obs["frame"], search=obs["search"],
                                      per_resolution=obs["per_resolution"], allow_partial=True)
        except Exception as exc:                   # recorded like the batch ETC's failures
            status[i], error[i] = "failed", f"{type(exc).__name__}: target {row['target_id']}: {' '.join(str(exc).split())}"
            continue
        n, m, d = res["nmd"]
        shape = target.simulation.detector.shape
        cat["n"][i], cat["m"][i], cat["d"][i], cat["nramps"][i] = n, m, d, res["nramps"]
        cat["exposure_time"][i] = res["exposure_time"]
        cat["snr"][i] = res["snr_per_resolution"] if obs["per_resolution"] else res["snr"]
        volume = res["nramps"] * n * int(shape[0]) * int(shape[1]) * BYTES_PER_READ
        cat["data_volume"][i] = volume
        cat["data_volume_compressed"][i] = round(volume / survey["compression_ratio"])
    cat["status"], cat["error"] = status, error
    plan.totals.update(survey_totals(cat, survey["overhead"], survey["efficiency"], survey["compression_ratio"]))
    plan.totals["hosts_in_etc"] = True


def _jsonable(d):
    return {k: (v.item() if hasattr(v, "item") else v) for k, v in d.items()}


def _catalog_with_records(base, records, wanted):
    """The catalog: the plan plus, per target, its status, error and products (file, sha256)."""
    cat = base.copy(copy_data=True)
    status, error = [], []
    names = PRODUCTS + ("reduced",)              # reduced: a streaming campaign's (products.reduce)
    files = {p: [] for p in names}
    sums = {p: [] for p in names}
    for row in base:
        tid = int(row["target_id"])
        planned_fail = str(row["status"]) == "failed"
        rec = records.get(tid)
        if planned_fail:
            status.append("failed")
            error.append(str(row["error"]))
        elif rec is None:
            status.append("missing")
            error.append("")
        else:
            status.append(rec["status"])
            error.append(rec.get("error", ""))
        prods = (rec or {}).get("products", {}) if rec and rec.get("status") == "done" else {}
        for p in names:
            info = prods.get(p)
            files[p].append(f"{PRODUCT_DIR}/{_key(tid)}/{info['file']}" if info else "")
            sums[p].append(info["sha256"] if info else "")
    cat["status"], cat["error"] = status, error
    for p in names:
        if p in wanted or any(files[p]):
            cat[f"{p}_product"], cat[f"{p}_sha256"] = files[p], sums[p]
    return cat


def _key(tid):
    from slicersim.io.dataset import target_key
    return target_key(tid)


#: most workers of an embedded LocalCluster per CPU (more only thrash; connect to a scheduler instead)
WORKERS_PER_CPU = 4


def check_workers(workers):
    """Workers of the embedded cluster: None (the CPU count) or an integer from 1 to
    :data:`WORKERS_PER_CPU` × the CPU count (ParameterError naming ``workers`` otherwise)."""
    if workers is None:
        return max(1, os.cpu_count() or 1)
    most = WORKERS_PER_CPU * (os.cpu_count() or 1)
    return positive_int(f"workers (--workers; at most {WORKERS_PER_CPU} × the CPU count for the embedded "
                        "LocalCluster: connect to a scheduler for more)", workers, high=most)


#: the former private name (reduction.campaign imports it)
_check_workers = check_workers


def _check_positive_int(value, name, lo=1):
    """An integer ≥ ``lo`` (ParameterError naming ``name``); :func:`slicersim.validation.positive_int`."""
    return positive_int(name, value, lo)


@checked_fields
@dataclass(frozen=True)
class RunOptions:
    """How a campaign runs (none of it changes the products): ``workers`` of the embedded cluster,
    ``scheduler`` address or None, ``progress`` bar (True/False; :meth:`checked` resolves None),
    ``max_bytes`` memory budget of one task's cube chunks / ramp blocks [bytes], ``threads_per_worker`` (OpenCL CPU threads; None: CPUs / workers),
    ``window`` tasks in flight (None: 2 per worker)."""
    workers: int
    scheduler: str | None = None
    progress: bool = False
    max_bytes: int = TASK_MAX_BYTES
    threads_per_worker: int | None = None
    window: int | None = None
    #: a distributed.Security for ``scheduler`` (None: Dask's configuration)
    security: object = None
    #: the embedded cluster's dashboard: False, True (127.0.0.1:8787) or "127.0.0.1:PORT"
    dashboard: object = False

    @classmethod
    def checked(cls, workers=None, scheduler=None, progress=None, max_bytes=TASK_MAX_BYTES, threads_per_worker=None,
                window=None):
        """Options with every value checked (ParameterError naming the keyword)."""
        return cls(check_workers(workers), scheduler, show_progress(progress),
                   positive_int("max_bytes", max_bytes, 2**20),
                   None if threads_per_worker is None else positive_int("threads_per_worker (--threads-per-worker)",
                                                                         threads_per_worker),
                   None if window is None else positive_int("window", window))

    @property
    def threads(self):
        """OpenCL CPU threads per worker."""
        return self.threads_per_worker or max(1, (os.cpu_count() or 1) // self.workers)


def _check_cube_precision(spec, scheduler):
    """The embedded cluster's workers share this machine's device: a precision it cannot run (e.g.
    "double" without fp64) is one error here, not one failure per target."""
    if scheduler is None and spec.products.get("cube"):
        from slicersim.backends.precision import resolve_precision
        resolve_precision(spec.products.get("precision", "auto"), "auto", "cube")


def _resumed_seed(spec, ds, force):
    """A spec without a seed (one was drawn) resumes the dataset it made: the stored seed replaces
    the drawn one when the rest of the spec is the same (otherwise the drawn seed stands, and a
    dataset of another spec is refused as usual)."""
    if force or not seed_was_drawn(spec):
        return spec
    try:
        stored = ds.stored_spec()
    except DatasetError:                    # damaged: check_spec says so
        return spec
    if stored is None or not isinstance(stored[0].get("seed"), int):
        return spec
    resumed = with_seed(spec, stored[0]["seed"])
    return resumed if spec_digest(resumed.canonical()) == stored[1] else spec


def _plan_and_connect(spec, run):
    """(catalog, plan, connection or None): a remote scheduler (:class:`RunOptions` ``run``) is
    reached before anything is written, and nothing is written before the plan succeeds."""
    connection = dask_client(1, run.scheduler, 1, run.security) if run.scheduler else None
    try:
        catalog, plan = plan_campaign(spec)
    except BaseException:
        if connection:
            connection[0].close()
        raise
    return catalog, plan, connection


def run_campaign(spec, out, workers=None, scheduler=None, force=False, retry_failed=False, progress=None,
                 max_bytes=TASK_MAX_BYTES, threads_per_worker=None, window=None, security=None, dashboard=False):
    """Run (or resume) a campaign into dataset directory ``out``.

    Parameters
    ----------
    spec : CampaignSpec or str or path-like
        A ``CampaignSpec`` or the path of its TOML file.
    out : str or path-like
        The dataset directory.
    workers : int, optional
        Embedded LocalCluster size (default: the CPU count; at most ``WORKERS_PER_CPU`` (4)
        × the CPU count); ignored with ``scheduler``.
    scheduler : str, optional
        Address of an existing Dask scheduler ("tcp://host:port").
    force : bool, optional
        Start again in a directory made from another spec (its products are discarded).
    retry_failed : bool, optional
        Run the targets recorded as failed again.
    progress : bool or None, optional
        None (a bar only when stderr is a terminal), True or False.
    max_bytes : int, optional
        Memory budget of one task's cube chunks / ramp blocks [bytes] (default 1 GiB).
    threads_per_worker : int, optional
        OpenCL CPU threads per worker (default: CPUs / workers).
    window : int, optional
        Tasks in flight at once (default 2 per worker): bounds the client's memory.
    security : distributed.Security, optional
        Security to reach ``scheduler`` (e.g. ``tls_security``; None: Dask's configuration);
        the embedded cluster always uses TLS with temporary credentials.
    dashboard : bool or str, optional
        The embedded cluster's dashboard: False (default), True (on 127.0.0.1:8787) or
        "127.0.0.1:PORT".

    Returns
    -------
    dict
        The summary: ``dataset`` (its path), ``targets``, ``done``, ``failed``, ``missing``
        (counts), ``computed`` (targets run now), ``seconds`` (wall time [s]) and ``totals``
        (of the survey plan).
    """
    from dataclasses import replace
    spec = spec if isinstance(spec, CampaignSpec) else load_spec(spec)
    run = replace(RunOptions.checked(workers, scheduler, progress, max_bytes, threads_per_worker, window),
                  security=security, dashboard=dashboard_address(dashboard) or False)
    _check_cube_precision(spec, scheduler)
    ds = Dataset(Dataset.check_path(out, force=force))
    spec = _resumed_seed(spec, ds, force)
    t0 = time.perf_counter()
    ds.check_spec(spec.canonical(), force)            # refuse early, before planning
    catalog, plan, connection = _plan_and_connect(spec, run)
    try:
        created = ds.create()                         # atomic: of two runs on one new folder, one creates it
    except BaseException:
        if connection:
            connection[0].close()
        raise
    try:
        return _run(spec, ds, (catalog, plan, connection), run, (force, retry_failed, t0))
    except BaseException:
        if connection:
            connection[0].close()                   # closing twice is harmless
        if created:                                 # a failed run leaves nothing new behind
            ds.remove_new()
        raise


def _run(spec, ds, planned, run, flags):
    """Initialise (or resume) dataset ``ds`` and simulate what is missing (``planned``: catalog,
    plan, connection or None; ``flags``: force, retry_failed, start time); the summary dict."""
    catalog, plan, connection = planned
    force, retry_failed, t0 = flags
    with ds:
        digest = ds.initialise(spec.text, spec.canonical(), software_versions(), force=force)
        ids = [int(t) for t in catalog["target_id"]]
        rows = {int(r["target_id"]): r for r in catalog}
        state = _consistent(ds.state(ids), rows)
        records = {tid: rec for tid, (st, rec, _) in state.items() if st in ("done", "failed")}
        todo = [tid for tid, (st, _, _) in state.items()
                if str(rows[tid]["status"]) != "failed" and (st == "missing" or (st == "failed" and retry_failed))]
        ds.write_catalog(_catalog_with_records(catalog, records, spec.recorded))
        try:
            if todo:
                _dispatch(spec, ds, catalog, (todo, records, digest), run, connection)
            elif connection:
                connection[0].close()
        finally:                                   # also on Ctrl-C: the catalog says what is done
            final = _catalog_with_records(catalog, records, spec.recorded)
            ds.write_catalog(final)
    counts = {s: int(np.count_nonzero(np.asarray(final["status"]) == s)) for s in ("done", "failed", "missing")}
    return {"dataset": ds.path, "targets": len(final), **counts, "computed": len(todo),
            "seconds": time.perf_counter() - t0, "totals": plan.totals}


def _consistent(state, rows):
    """A done record whose readout or seeds differ from its catalog row (the plan changed
    under it, e.g. an input file edited) counts as missing: its products are stale."""
    out = dict(state)
    for tid, (st, rec, why) in state.items():
        if st != "done" or tid not in rows:
            continue
        row = rows[tid]
        expect = [int(row["n"]), int(row["m"]), int(row["d"]), int(row["nramps"])]
        if rec.get("readout") != expect or rec.get("seed") != int(row["seed"]) \
                or rec.get("ramp_seed") != int(row["ramp_seed"]):
            out[tid] = ("missing", rec, f"stale: record readout {rec.get('readout')} / seeds differ from the "
                                        f"catalog's {expect}")
    return out


def _row_dict(row):
    return {name: (row[name].item() if hasattr(row[name], "item") else row[name]) for name in row.colnames}


def _dispatch(spec, ds, catalog, work, run, connection=None):
    """Simulate the targets ``work`` = (todo ids, records dict filled in place, spec digest) on
    Dask with :class:`RunOptions` ``run``."""
    todo, records, digest = work
    threads = run.threads
    quiet = QuietDask()
    client, cluster = connection or dask_client(run.workers, run.scheduler, threads, run.security, run.dashboard)
    if cluster is not None and run.dashboard:
        print(f"Dask dashboard: {client.dashboard_link} (this machine only)", file=sys.stderr)
    try:
        spec_future = client.scatter(spec, broadcast=True)
    except BaseException:
        client.close()
        if cluster is not None:
            cluster.close()
        quiet.restore()
        raise
    rows = {int(r["target_id"]): _row_dict(r) for r in catalog}
    reducer = registered_reducer() if spec.products.get("reduce") else None    # sent by reference

    def submit(tid):
        return client.submit(run_target, spec_future, rows[tid], ds.path, digest, run.max_bytes, threads, reducer,
                             key=f"slicersim-target-{digest[:12]}-{tid}", pure=False, retries=0)

    def lost(tid, exc):
        return {"target_id": tid, "status": "failed", "spec_sha256": digest,
                "error": f"{type(exc).__name__}: {' '.join(str(exc).split())}"}
    run_task_window(client, cluster, quiet, todo, submit, records, ds, window=run.window, workers=run.workers,
                    progress=run.progress, desc="campaign", lost_record=lost,
                    checkpoint=lambda: ds.write_catalog(_catalog_with_records(catalog, records, spec.recorded)))


@dataclass(frozen=True)
class TaskWindow:
    """How :func:`run_task_window` feeds Dask: ``window`` tasks in flight (None: 2 per worker),
    ``workers`` expected (when the scheduler reports none yet), a tqdm bar (``progress``, ``desc``),
    ``lost_record(id, exc)`` → the record of a task whose worker died, ``checkpoint()`` run every
    :data:`CATALOG_INTERVAL` s."""
    window: int | None
    workers: int
    progress: bool
    desc: str
    lost_record: object
    checkpoint: object


def run_task_window(client, cluster, quiet, ids, submit, records, ds, **options):
    """One Dask task per id (``submit(id)`` → future of its record), at most ``window`` in flight
    (``options``: the fields of :class:`TaskWindow`): ``records[id]`` gets each record as it
    completes, or ``lost_record(id, exc)`` (written to ``ds``) when the worker died or the task was
    lost; a tqdm bar counts the failures.  Closes the client (and an embedded cluster) and
    restores the Dask loggers (``quiet``) at the end."""
    opts = TaskWindow(**options)
    try:
        nworkers = max(1, len(client.scheduler_info().get("workers", {})) or opts.workers)
        _collect(ids, submit, records, ds, opts, opts.window or 2 * nworkers)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
        quiet.restore()


def _collect(ids, submit, records, ds, opts, window):
    """Submit ``ids`` keeping ``window`` futures in flight; collect each record as it completes."""
    from distributed import as_completed
    from tqdm.auto import tqdm
    pending = list(ids)
    futures = {}

    def start(tid):
        fut = submit(tid)
        futures[fut] = tid
        return fut

    queue = as_completed([start(pending.pop(0)) for _ in range(min(window, len(pending)))])
    last = time.monotonic()
    with tqdm(total=len(ids), desc=opts.desc, unit="target", disable=not opts.progress) as bar:
        for fut in queue:
            tid = futures.pop(fut)
            try:
                rec = fut.result()
            except Exception as exc:           # the worker died (KilledWorker) or the task was lost
                rec = opts.lost_record(tid, exc)
                ds.write_record(tid, rec)
            records[tid] = rec
            bar.update(1)
            nfail = sum(1 for r in records.values() if r.get("status") == "failed")
            if nfail:
                bar.set_postfix(failed=nfail)
            if pending:
                queue.add(start(pending.pop(0)))
            if time.monotonic() - last > CATALOG_INTERVAL:
                opts.checkpoint()
                last = time.monotonic()


class QuietDask:
    """Silence distributed's loggers on the client while a campaign runs: worker deaths and
    task errors are recorded per target and summarised; their tracebacks would bury the one
    line the CLI prints."""

    NAMES = ("distributed", "distributed.worker", "distributed.nanny", "distributed.scheduler",
             "distributed.client", "distributed.core", "distributed.comm", "distributed.batched")

    def __init__(self):
        self.levels = {}
        for name in self.NAMES:
            logger = logging.getLogger(name)
            self.levels[name] = logger.level
            logger.setLevel(logging.CRITICAL)

    def restore(self):
        for name, level in self.levels.items():
            logging.getLogger(name).setLevel(level)


#: the former private name (reduction.campaign imports it)
_QuietDask = QuietDask


def campaign_status(out, verify=True):
    """State of a campaign dataset.

    Parameters
    ----------
    out : str or path-like
        The dataset directory.
    verify : bool, optional
        Check every product's checksum.

    Returns
    -------
    dict
        ``targets``, ``done``, ``failed``, ``missing`` (counts), ``failed_targets`` (a list of
        (id, error)) and ``missing_targets`` (ids).
    """
    from astropy.table import Table
    ds = Dataset(out)
    if not os.path.isdir(ds.path):
        raise not_a_dataset_directory(ds.path, "run_campaign(spec, out) writes the dataset directory out")
    if ds.stored_spec() is None:
        raise DatasetError(f"{ds.path} is not a slicersim dataset (no spec.json)")
    try:
        catalog = Table.read(ds.file(CATALOG), format="ascii.ecsv")
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{ds.file(CATALOG)} is missing or unreadable ({exc}); run the campaign again "
                           "to rebuild it") from None
    ids = [int(t) for t in catalog["target_id"]]
    planned_fail = {int(r["target_id"]): str(r["error"]) for r in catalog
                    if "error" in catalog.colnames and str(r["status"]) == "failed" and r["error"]}
    state = _consistent(ds.state(ids, deep=verify), {int(r["target_id"]): r for r in catalog}) \
        if {"n", "m", "d", "nramps", "seed", "ramp_seed"} <= set(catalog.colnames) else ds.state(ids, deep=verify)
    out = {"dataset": ds.path, "targets": len(ids), "done": 0, "failed": 0, "missing": 0,
           "failed_targets": [], "missing_targets": []}
    for tid in ids:
        st, rec, why = state[tid]
        if st == "missing" and tid in planned_fail:
            st, why = "failed", planned_fail[tid]
        out[st] += 1
        if st == "failed":
            out["failed_targets"].append((tid, why))
        elif st == "missing":
            out["missing_targets"].append((tid, why))
    return out
