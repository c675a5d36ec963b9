"""Reduce a campaign dataset: every target's raw ramps → rates (or rates, cubes, spectra), one Dask
task per target; and :func:`reduce_file`, the same for one raw file.

``reduce_dataset(DATASET, OUT)`` reads the dataset a campaign wrote
(:mod:`slicersim.campaign.runner`; its spec must ask for ``ramps``) and writes a *reduction
directory* with the layout of a dataset (:mod:`slicersim.io.dataset`)::

    OUT/spec.toml, spec.json  the reduction's identity: mode, options, the source spec's sha256
    OUT/versions.json         software versions
    OUT/catalog.ecsv          per target: status, error, reduced product and sha256, source ramps
    OUT/products/tNNNNNNN/    rates.h5 (RATE, VAR, ... as ``slicersim reduce``) or, with
                              ``spectra=True``, reduced.h5 (rates/, cubes/<field>/, spectra/<field>/)
    OUT/records/tNNNNNNN.json written last: "done" (product size, sha256, the source's sha256) or
                              "failed" (error)
    OUT/summary.ecsv, report.md, bias_vs_redshift.png, snr_vs_etc.png  with ``spectra=True``: each
                              target against its truth (:mod:`slicersim.reduction.report`)

so ``slicersim campaign status OUT`` reports it too.  The dask client comes from the campaign
runner (an embedded LocalCluster of ``workers`` processes, or ``scheduler="tcp://host:port"``;
every worker must see both directories).

Resumable like a campaign: a target is skipped when its record is "done", its product is there
with the recorded size (``verify``: and sha256), and the source ramps are still the ones it was
reduced from (the campaign's sha256); anything else is reduced again (a product is written under a
temporary name and renamed complete, its record after it: ``kill -9`` leaves nothing half-written
under a final name).  A target that fails is recorded and the others go on; ``retry_failed``
reduces the failed ones again (a failed target whose source ramps changed is retried anyway).
A directory made with other options or from another campaign is refused unless ``force``.
"""
from __future__ import annotations

import os
import time

import numpy as np

from slicersim import validation
from slicersim.errors import DatasetError, ParameterError, RampFileError

__all__ = ["reduce_dataset", "reduce_file", "reduce_target", "is_dataset", "reduction_client"]

#: per-target product names
RATES_FILE, REDUCED_FILE = "rates.h5", "reduced.h5"
#: seconds between two catalog writes while a reduction runs
CATALOG_INTERVAL = 10.0
_KIND = "slicersim reduction"


# ----------------------------------------------------------------------------- one file
#: the reduction's point-source model, part of a dataset reduction's identity (a reduction made with an
#: earlier default is refused, not mixed, when resumed)
SPECTRUM_MODEL = "forward-model extraction on the pixels (v1)"


def reduce_file(raw, out=None, *, spectra=False, overwrite=False, fit_options=None, progress=None, mapper=None,
                **options):
    """Reduce one raw ramp file (our HDF5 or a level-1b FITS), every input checked before any data
    are read (:func:`~slicersim.reduction.checks.check_ramp_file`).

    spectra : False: rates only (:func:`~slicersim.reduction.ramp_fit.fit_ramps`, ``out`` as
        :meth:`RateProduct.write`); True: rates, cubes and spectra
        (:func:`~slicersim.reduction.pipeline.reduce_exposure` with ``options``: field, lbda_edges,
        ncol, rectify_method, extraction, psf, position, aperture, background, propagate)
    fit_options : ``fit_ramps`` keywords (weighting, jump_threshold, refpix, linearity, gain,
        ron (read_noise: its earlier name), with_truth: the truth rate is written as TRUTH_RATE / rates/TRUTH_RATE)
    out : HDF5 path written atomically (None: nothing written)

    Returns ``{"rates": RateProduct, "path": absolute path or None}`` (rates only) or
    reduce_exposure's dict (``rates``, ``cubes``, ``spectra`` and ``path`` with ``out``).
    """
    from slicersim.reduction.checks import check_fit_options, check_ramp_file, check_spectra_options
    _check_path(raw, "raw")
    if out is not None:
        _check_path(out, "out")
        if os.path.exists(out) and os.path.exists(raw) and os.path.samefile(raw, out):
            raise ParameterError(f"out is the raw file itself ({raw}): the ramps would be lost")
    fit = check_fit_options(fit_options)
    if not spectra and options:
        raise ParameterError(f"option(s) {', '.join(sorted(options))} apply only with spectra=True")
    if not spectra and mapper is not None:
        raise ParameterError("mapper applies only with spectra=True")
    opts = check_spectra_options(mapper=mapper, **options) if spectra else {}
    writer = _check_out_file(out, overwrite) if out is not None else None
    shape = None
    if spectra:
        from slicersim.reduction.rectify import _default_mapper
        shape = tuple((mapper or _default_mapper()).detector_shape)
    check_ramp_file(raw, with_truth=bool(fit.get("with_truth")), gain=fit.get("gain"),
                    ron=fit.get("ron"), detector_shape=shape)
    if progress is not None:
        fit["progress"] = progress
    if not spectra:
        from slicersim.reduction.ramp_fit import fit_ramps
        product = fit_ramps(raw, **fit)
        path = product.write(out, overwrite=overwrite) if writer is not None else None
        return {"rates": product, "path": path}
    return _reduce_spectra(raw, out, overwrite, fit, opts, mapper)


def _check_path(path, name):
    """A path (str or os.PathLike, not empty): existence is checked where it is read or written."""
    if not isinstance(path, (str, os.PathLike)) or not os.fspath(path):
        raise ParameterError(f"{name} must be a path, got {validation.short_repr(path)}")


def _check_workers(workers):
    """Workers of the embedded cluster: an integer from 1 to 4 × the CPU count."""
    validation.positive_int("workers", workers)
    most = 4 * (os.cpu_count() or 1)
    if workers > most:
        raise ParameterError(f"workers must be ≤ {most} (4 × the CPU count) for the embedded LocalCluster, got "
                             f"{workers}; connect to a scheduler for more")
    return workers


def _check_out_file(out, overwrite):
    from slicersim.io.atomic import AtomicH5File

    class _Check(AtomicH5File):
        error_class = RampFileError
    return _Check(out, overwrite=overwrite).check()


def _reduce_spectra(raw, out, overwrite, fit, opts, mapper):
    """reduce_exposure (with the truth, its file holds rates/TRUTH_RATE)."""
    from slicersim.reduction.pipeline import reduce_exposure
    kwargs = dict(opts, fit_options=fit or None)
    if mapper is not None:
        kwargs["mapper"] = mapper
    return reduce_exposure(raw, out=out, overwrite=overwrite, **kwargs)


# ----------------------------------------------------------------------------- datasets
def is_dataset(path):
    """True for a directory holding a campaign dataset (spec.json) — or a reduction directory."""
    from slicersim.io.dataset import SPEC_JSON
    return os.path.isdir(path) and os.path.isfile(os.path.join(path, SPEC_JSON))


def reduction_client(workers=None, scheduler=None, threads=None, security=None, dashboard=False):
    """(client, cluster or None) from the campaign runner (:func:`slicersim.campaign.runner.dask_client`):
    an embedded LocalCluster of ``workers`` processes (one task each at a time; 127.0.0.1, TLS with
    temporary credentials, dashboard only when ``dashboard``) or the scheduler at ``scheduler``
    (reached with ``security``, a distributed.Security, or Dask's configuration)."""
    from slicersim.campaign import runner
    workers = runner.check_workers(workers)
    threads = threads or max(1, (os.cpu_count() or 1) // workers)
    return runner.dask_client(workers, scheduler, threads, security, dashboard)


def _source(dataset):
    """(Dataset, spec dict, spec sha256, catalog Table) of a campaign dataset with ramps."""
    from astropy.table import Table

    from slicersim.io.dataset import CATALOG, Dataset, not_a_dataset_directory
    src = Dataset(dataset)
    if not os.path.isdir(src.path):
        raise not_a_dataset_directory(src.path, "run it first: its dataset directory is reduced")
    stored = src.stored_spec()
    if stored is None:
        raise DatasetError(f"{src.path} is not a slicersim campaign dataset (no spec.json)")
    spec, digest = stored
    if isinstance(spec, dict) and spec.get("kind") == _KIND:
        raise DatasetError(f"{src.path} is a reduction directory (made by `slicersim reduce`), not a campaign "
                           "dataset")
    if not isinstance(spec, dict) or not isinstance(spec.get("products"), dict):
        raise DatasetError(f"{src.path}/spec.json is not a campaign spec")
    if not spec["products"].get("ramps"):
        raise DatasetError(f"{src.path} has no raw ramps to reduce (its spec has products.ramps = false)")
    try:
        catalog = Table.read(src.file(CATALOG), format="ascii.ecsv")
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{src.file(CATALOG)} is missing or unreadable ({' '.join(str(exc).split())[:200]}); "
                           "run the campaign again to rebuild it") from None
    if "target_id" not in catalog.colnames:
        raise DatasetError(f"{src.file(CATALOG)} has no target_id column")
    return src, spec, digest, catalog


#: fit_ramps options that do not change the rates (left out of a reduction's identity)
_RUNTIME = {"progress", "max_bytes", "backend", "work_group", "return_groupdq"}
#: fit_ramps option → its key in a reduction's identity: the name the identities were first written
#: with (``read_noise``, before the option became ``ron``), so that a reduction directory made by an
#: earlier release keeps its identity digest and is resumed
_IDENTITY_KEYS = {"ron": "read_noise"}


def _fit_identity(fit):
    """The fit options of a reduction's identity: every rate-shaping option of
    :data:`~slicersim.reduction.ramp_fit.FIT_DEFAULTS` (given value, else default), runtime options
    left out, under their identity keys (:data:`_IDENTITY_KEYS`)."""
    from slicersim.reduction.ramp_fit import FIT_DEFAULTS, FIT_RENAMED
    given = {FIT_RENAMED.get(k, k): v for k, v in fit.items() if v is not None}
    merged = {**FIT_DEFAULTS, **given}
    return {_IDENTITY_KEYS.get(k, k): v for k, v in merged.items() if k not in _RUNTIME}


def _identity(mode, opts, fit, source_digest, mapper):
    """The canonical dict identifying a reduction: every option that shapes the products, the
    defaults filled in (options as JSON; arrays by value or digest)."""
    import hashlib

    from slicersim.reduction.options import ReduceOptions
    fit = _fit_identity(fit)
    if mode == "spectra":
        keys = {"field", "lbda_edges", "ncol", "rectify_method", "extraction", "psf", "position", "aperture",
                "background", "propagate", "dark", "weights", "config", "ipc", "cubes"}
        opts = {**{k: v for k, v in ReduceOptions.defaults().items() if k in keys}, **opts}
        if opts.get("field") is None:
            opts["field"] = "(each target's)"
        # what the default extraction is: reductions made before the forward model are not resumed into it
        opts["spectrum_model"] = SPECTRUM_MODEL
        if opts.get("weights") is None:                      # the default, as reduce_exposure resolves it
            opts["weights"] = "forward" if opts.get("rectify_method") in (None, "lsq") else "data"
    canon = {}
    for key, val in sorted(opts.items()):
        if isinstance(val, np.ndarray):
            val = [float(v) for v in val] if val.ndim == 1 and val.size <= 4096 else \
                {"sha256": hashlib.sha256(np.ascontiguousarray(val, np.float64).tobytes()).hexdigest(),
                 "shape": list(val.shape)}
        elif isinstance(val, tuple):
            val = list(val)
        canon[key] = val
    fit_c = {k: (v if isinstance(v, (bool, int, float, str, type(None))) else repr(v)) for k, v in sorted(fit.items())}
    return {"kind": _KIND, "mode": mode, "options": canon, "fit_options": fit_c,
            "mapper": None if mapper is None else repr(mapper), "source_spec_sha256": source_digest}


def _check_identity(ds, identity, force):
    from slicersim.io.dataset import changed_keys, spec_digest
    stored = ds.stored_spec()
    if stored is not None and stored[1] != spec_digest(identity) and not force:
        changed = sorted(changed_keys(stored[0], identity))
        raise DatasetError(f"{ds.path} was reduced with other options or from another dataset (changed: "
                           f"{', '.join(changed[:6]) or 'content'}); use a new directory, or --force to discard "
                           "its products and start again")


def _toml(identity, source_path):
    """A human-readable TOML rendering of the identity (spec.toml of the reduction directory)."""
    import json
    lines = [f"# {_KIND} of {source_path}", f'kind = "{_KIND}"', f'mode = "{identity["mode"]}"',
             f'source_spec_sha256 = "{identity["source_spec_sha256"]}"']
    for table in ("options", "fit_options"):
        lines.append(f"[{table}]")
        for key, val in identity[table].items():
            if val is not None:
                lines.append(f"{key} = {json.dumps(val, ensure_ascii=False)}")
    return "\n".join(lines) + "\n"


def _lock(ds):
    try:
        return ds.lock()
    except DatasetError as exc:
        if "in use" not in str(exc):              # e.g. a lock that is a symbolic link
            raise
        raise DatasetError(f"reduction directory {ds.path} is in use by another process "
                           f"({str(exc).rsplit('(', 1)[-1].split(')')[0]}); wait for it or stop it") from None


def reduce_dataset(dataset, out, *, workers=None, scheduler=None, spectra=False, retry_failed=False, force=False,
                   verify=False, progress=None, window=None, fit_options=None, **options):
    """Reduce (or resume reducing) every target's ramps of campaign dataset ``dataset`` into the
    reduction directory ``out`` (module docstring), one Dask task per target.

    workers : embedded LocalCluster size (default: the CPU count); scheduler : "tcp://host:port"
    spectra : rates, cubes and spectra (reduce_exposure) instead of rates only; ``options`` are
        reduce_exposure's (:class:`~slicersim.reduction.options.ReduceOptions` fields: ``mapper``, the
        SlicerMapper of the ramps' detector, ``field``, which defaults to each target's own field, ...)
    fit_options : fit_ramps keywords
    progress : None (a progress bar when stderr is a terminal), True or False
    retry_failed : reduce the targets recorded as failed again
    force : start again in a directory made with other options or from another dataset
    verify : check every reduced product's sha256 when resuming (default: its size)
    window : tasks in flight at once (default 2 per worker)
    security : (keyword) a distributed.Security to reach ``scheduler`` (None: Dask's configuration); the
        embedded cluster always uses TLS with temporary credentials on 127.0.0.1
    dashboard : (keyword) the embedded cluster's dashboard, on 127.0.0.1 (default False)

    Returns {"dataset", "out", "targets", "done", "failed", "missing", "unavailable" (targets
    the campaign has no ramps for: failed or not yet simulated), "computed", "seconds",
    "failed_targets": [(id, error)], "report"}: with ``spectra``, ``out`` also gets the summary against
    each target's truth (summary.ecsv, report.md and figures: :mod:`slicersim.reduction.report`), and
    "report" is the path of report.md (None otherwise; "report_error" says why when it failed).
    """
    from slicersim.campaign.runner import software_versions
    from slicersim.io.dataset import Dataset
    from slicersim.reduction.checks import check_fit_options, check_spectra_options
    t0 = time.perf_counter()
    fit = check_fit_options(fit_options)
    fit.pop("progress", None)                      # no progress bars on the workers
    dask = {"security": options.pop("security", None), "dashboard": options.pop("dashboard", False)}
    if not spectra and options:
        raise ParameterError(f"option(s) {', '.join(sorted(options))} apply only with spectra=True")
    mapper = options.pop("mapper", None)
    opts = check_spectra_options(mapper=mapper, **options) if spectra else {}
    progress = _progress(progress)
    _check_path(dataset, "dataset")
    _check_path(out, "out")
    if workers is not None and scheduler is None:
        _check_workers(workers)
    if window is not None:
        validation.positive_int("window", window)
    src, _, source_digest, catalog = _source(dataset)
    out_path = _check_out_dir(out, src)
    identity = _identity("spectra" if spectra else "rates", opts, fit, source_digest, mapper)
    ds = Dataset(Dataset.check_path(out_path, force=force))
    stored = ds.stored_spec()
    if stored is not None and not (isinstance(stored[0], dict) and stored[0].get("kind") == _KIND):
        raise DatasetError(f"{ds.path} is a campaign dataset, not a reduction directory: choose another output "
                           "directory (it is never overwritten, even with force)")
    _check_identity(ds, identity, force)            # refuse early: other options or another source
    mapper = _portable(mapper)
    ids = [int(t) for t in catalog["target_id"]]
    connection = reduction_client(workers, scheduler, security=dask["security"]) if scheduler else None
    try:
        created = ds.create()                        # atomic: of two runs on one new folder, one creates it
        _lock(ds)
    except BaseException:
        if connection:
            connection[0].close()
        raise
    try:
        digest = ds.initialise(_toml(identity, src.path), identity, software_versions(), force=force)
        sources = _sources(src, ids)
        records, todo = _todo(ds.state(ids, deep=verify), sources, ids, retry_failed)
        base = _base_catalog(catalog)
        ds.write_catalog(_catalog(base, records, sources, src))
        try:
            if todo:
                tasks = {tid: _task(ds, tid, sources[tid], digest, spectra, opts, fit, mapper)
                         for tid in todo}
                _dispatch(ds, tasks, records, (workers, scheduler, dask), progress, window, connection,
                          lambda: ds.write_catalog(_catalog(base, records, sources, src)))
            elif connection:
                connection[0].close()
        finally:                                    # also on Ctrl-C: the catalog says what is done
            final = _catalog(base, records, sources, src)
            ds.write_catalog(final)
    except BaseException:
        ds.unlock()
        if connection:
            connection[0].close()                  # closing twice is harmless
        if created:                                # a failed run leaves nothing new behind
            ds.remove_new()
        raise
    ds.unlock()
    status = [str(s) for s in final["status"]]
    failed = [(int(t), str(e)) for t, s, e in zip(final["target_id"], status, final["error"]) if s == "failed"]
    unavailable = [(int(t), str(e)) for t, s, e in zip(final["target_id"], status, final["error"])
                   if s == "unavailable"]
    report = report_error = None
    if spectra:                                    # the spectra against their truth: summary.ecsv, report.md
        from slicersim.errors import SlicersimError
        from slicersim.reduction.report import campaign_report
        try:
            report = campaign_report(src.path, ds.path, reduced=ds.path)["report"]
        except (SlicersimError, OSError) as exc:   # the reduction stands: `slicersim campaign report` redoes it
            report_error = f"{type(exc).__name__}: {' '.join(str(exc).split())}"
    return {"dataset": src.path, "out": ds.path, "targets": len(ids), "done": status.count("done"),
            "failed": len(failed), "missing": status.count("missing"), "unavailable": status.count("unavailable"),
            "computed": len(todo), "seconds": time.perf_counter() - t0, "failed_targets": failed,
            "unavailable_targets": unavailable, "report": report, "report_error": report_error}


def _check_out_dir(out, src):
    """The reduction directory's absolute path; refused where it is the dataset, contains it or lies in
    its products or records."""
    out_path = os.path.abspath(os.fspath(out))
    real_out, real_src = os.path.realpath(out_path), os.path.realpath(src.path)
    if real_out == real_src or real_out.startswith(os.path.join(real_src, "products") + os.sep) \
            or real_out.startswith(os.path.join(real_src, "records") + os.sep) or real_src.startswith(real_out + os.sep):
        raise DatasetError(f"the reduction directory {out_path} must not be the dataset {src.path}, contain it "
                           "or lie in its products or records")
    return out_path


def _todo(state, sources, ids, retry_failed):
    """({target id: record} of the targets done or failed from their current ramps, [targets to reduce]):
    those not reduced yet, reduced from other ramps, or failed (with ``retry_failed``)."""
    records, todo = {}, []
    for tid in ids:
        st, rec, _ = state[tid]
        info = sources.get(tid)
        same = rec is not None and info is not None and rec.get("source_sha256") == info["sha256"]
        if st in ("done", "failed") and same:
            records[tid] = rec
        if info is not None and (not same or st == "missing" or (st == "failed" and retry_failed)):
            todo.append(tid)
    return records, todo


def _progress(progress):
    """progress as True/False: None means a bar only when stderr is a terminal."""
    from slicersim.io.row_blocks import show_progress
    return show_progress(progress)


def _portable(mapper):
    """A mapper the workers can receive: a used SlicerMapper holds OpenCL buffers (not picklable),
    so it travels as a fresh one built from its nodes; anything else must pickle."""
    import pickle
    if mapper is None:
        return None
    try:
        pickle.dumps(mapper)
        return mapper
    except Exception as exc:
        from slicersim.instrument.mapper import SlicerMapper
        if type(mapper) is not SlicerMapper:
            raise ParameterError(f"mapper cannot be sent to the Dask workers ({type(exc).__name__}: {exc})") from None
    return SlicerMapper(mapper.slice_ids, mapper.fieldpos_nodes, mapper.lbda_nodes, mapper.values,
                        pixel_size_um=mapper.pixel_size_um, detector_shape=mapper.detector_shape,
                        interpolation=mapper.interpolation, face_diagonal=mapper.face_diagonal,
                        table_cache=mapper.table_cache)


def _sources(src, ids):
    """{target id: the campaign's ramps product info (file, bytes, sha256) + path} of the done targets."""
    out = {}
    for tid, (st, rec, _) in src.state(ids, deep=False).items():
        info = (rec or {}).get("products", {}).get("ramps") if st == "done" else None
        if info:
            out[tid] = dict(info, path=os.path.join(src.product_dir(tid), info["file"]),
                            field=str(rec.get("field", "")))
    return out


def _unavailable_reason(src, tid):
    """Why target ``tid`` of campaign dataset ``src`` has no ramps to reduce: not simulated, failed, or its
    ramps file missing or damaged (named, with the command that recomputes it)."""
    st, rec, why = src.state([tid], deep=False)[tid]
    if st == "failed":
        return f"the campaign's simulation of this target failed ({why})"
    if st == "done":
        return "the campaign made no ramps for this target (products.ramps is false)"
    if rec is not None and rec.get("status") == "done":
        return (f"the campaign's ramps of this target are damaged ({why}): `slicersim campaign run` on the "
                "dataset recomputes them")
    return "no ramps in the campaign dataset (target not simulated yet)"


def _base_catalog(catalog):
    cols = [c for c in ("target_id", "redshift", "field") if c in catalog.colnames]
    return catalog[cols].copy(copy_data=True)


def _catalog(base, records, sources, src):
    """Per target: status ("done", "failed", "missing": not reduced yet, "unavailable": no ramps in
    the campaign), error, product and sha256, the source ramps and their sha256."""
    from slicersim.io.dataset import PRODUCTS, target_key
    cat = base.copy(copy_data=True)
    status, error, product, sha, source, source_sha = [], [], [], [], [], []
    for tid in (int(t) for t in base["target_id"]):
        rec, info = records.get(tid), sources.get(tid)
        if info is None:
            st, err = "unavailable", _unavailable_reason(src, tid)
        elif rec is None:
            st, err = "missing", ""
        else:
            st, err = rec.get("status", "missing"), rec.get("error", "")
        prod = (rec or {}).get("products", {}) if st == "done" else {}
        name, pinfo = next(iter(prod.items()), (None, None))
        status.append(st)
        error.append(err)
        product.append(f"{PRODUCTS}/{target_key(tid)}/{pinfo['file']}" if pinfo else "")
        sha.append(pinfo["sha256"] if pinfo else "")
        source.append(os.path.relpath(info["path"], src.path) if info else "")
        source_sha.append(info["sha256"] if info else "")
    cat["status"], cat["error"], cat["product"], cat["sha256"] = status, error, product, sha
    cat["source"], cat["source_sha256"] = source, source_sha
    cat.meta = {"dataset": src.path}
    return cat


def _task(ds, tid, info, digest, spectra, opts, fit, mapper):
    opts = dict(opts)
    if spectra and "field" not in opts:            # each target in its own field
        opts["field"] = info.get("field") or "narrow"
    return {"target_id": tid, "source": info, "out": ds.path, "digest": digest, "spectra": bool(spectra),
            "options": opts, "fit_options": dict(fit), "mapper": mapper}


def reduce_target(task, threads=None):
    """The unit of work of a worker: reduce one target's ramps (checked against the campaign's
    record: size and sha256), write its product atomically and its record last; returns the
    record.  Errors are recorded (status "failed"), never raised."""
    from slicersim.campaign.products import limit_threads, mark_failed
    from slicersim.io.atomic import sha256_file
    from slicersim.io.dataset import Dataset, product_info
    limit_threads(threads)
    tid, info = int(task["target_id"]), task["source"]
    ds = Dataset(task["out"])
    record = {"target_id": tid, "spec_sha256": task["digest"], "source": info["path"],
              "source_sha256": info["sha256"], "mode": "spectra" if task["spectra"] else "rates"}
    t0 = time.perf_counter()
    try:
        ds.clean_target(tid)
        path = info["path"]
        try:
            size = os.path.getsize(path)
        except OSError as exc:
            raise RampFileError(f"{path}: cannot read the campaign's ramps ({exc.strerror})") from None
        if size != info["bytes"]:
            raise RampFileError(f"{path}: {size} bytes, the campaign recorded {info['bytes']} (truncated or replaced)")
        if sha256_file(path) != info["sha256"]:
            raise RampFileError(f"{path}: checksum differs from the campaign's record (corrupted or replaced)")
        pdir = ds.target_dir(tid, make=True)           # a real folder inside the reduction directory
        out = os.path.join(pdir, REDUCED_FILE if task["spectra"] else RATES_FILE)
        reduce_file(path, out, spectra=task["spectra"], overwrite=True, progress=False,
                    fit_options=task["fit_options"], mapper=task["mapper"], **task["options"])
        record.update(status="done", products={"reduced": product_info(out)})
    except Exception as exc:
        mark_failed(ds, tid, record, exc)
    ds.write_timing(tid, time.perf_counter() - t0)
    ds.write_record(tid, record)
    return record


def _dispatch(ds, tasks, records, cluster_options, progress, window, connection, checkpoint):
    """Submit one task per target (at most ``window`` in flight), collect the records;
    ``cluster_options``: (workers, scheduler, {"security", "dashboard"})."""
    import sys

    from slicersim.campaign.runner import QuietDask, check_workers, run_task_window
    workers, scheduler, dask = cluster_options
    quiet = QuietDask()
    nw = check_workers(workers)
    threads = max(1, (os.cpu_count() or 1) // nw)
    client, cluster = connection or reduction_client(nw, scheduler, threads, **dask)
    if cluster is not None and dask["dashboard"]:
        print(f"Dask dashboard: {client.dashboard_link} (this machine only)", file=sys.stderr)

    def submit(tid):
        return client.submit(reduce_target, tasks[tid], threads, pure=False, retries=0,
                             key=f"slicersim-reduce-{tasks[tid]['digest'][:12]}-{tid}")

    def lost(tid, exc):
        return {"target_id": tid, "status": "failed", "spec_sha256": tasks[tid]["digest"],
                "source_sha256": tasks[tid]["source"]["sha256"],
                "error": f"{type(exc).__name__}: {' '.join(str(exc).split())}"}
    run_task_window(client, cluster, quiet, list(tasks), submit, records, ds, window=window, workers=nw,
                    progress=progress, desc="reduce", lost_record=lost, checkpoint=checkpoint)
