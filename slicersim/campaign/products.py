"""One campaign target: build it, simulate the products its spec asks for, write them.

:func:`run_target` is the unit of work a Dask worker executes.  It depends only on the
spec, the target's row (parameters and readout) and its seeds, so the products are the same
bit for bit whichever worker runs it, in whatever order, however often (on the same kind of
OpenCL device: backends differ by a few ulp in the cube expectation).

Products (``DIR/products/tNNNNNNN/``; HDF5, each written atomically):

==================  ===========================================================================
spectrum.h5         lbda [Å], flambda (input F_λ on lbda) [erg/s/cm²/Å], signal [ADU],
                    variance [ADU²], noisy [ADU] (Philox stream of the extracted spectra)
cube.h5             lbda [Å], signal [ADU], variance [ADU²], noisy [ADU] (nλ, ny, nx), cube_dtype
detector_image.h5   rate [e-/s/px] (float32) on the full H4RG, both fields
ramps.h5            raw MACC ramps (:mod:`slicersim.io.rampfile` layout); ramps.fits with
                    ``products.ramp_format = "jwst-uncal"`` (level-1b, :mod:`slicersim.io.uncal`); with
                    ``products.reference_files`` beside those kept reference/: their JWST reference files
                    (gain, readnoise, saturation, ...; one set per target, as the per-pixel maps come from the
                    ramp seed: :mod:`slicersim.products.reference`; stdatamodels needed)
reduced.h5          with ``products.reduce = "spectra"`` (or true): the ramps reduced as
                    ``slicersim reduce DATASET --spectra`` does (rates/, cubes/<field>/,
                    spectra/<field>/); rates.h5 with ``"rates"`` (as ``slicersim reduce DATASET``)
==================  ===========================================================================

Streaming (``products.reduce``): the ramps are reduced in the same task right after they are
written, then deleted unless ``products.keep_ramps`` keeps them, so a worker holds at most one
exposure's ramps on disk.  The record (written last) lists the products that exist: ``reduced``,
and ``ramps`` only where kept.  The reduction is the reduction layer's, registered here by
:mod:`slicersim.reduction.streaming` (:func:`register_reducer`; campaigns sit below reductions).
"""
from __future__ import annotations

import os
import time
import traceback

import numpy as np

from slicersim import rng
from slicersim.io.dataset import Dataset, ProductFile, product_info

__all__ = ["target_seeds", "run_target", "truth_meta", "SEED_STREAM", "SPECTRUM_GRID", "limit_threads", "mark_failed",
           "register_reducer", "registered_reducer", "REDUCED_FILES"]

#: the file of the reduced product per ``products.reduce`` mode (the names of ``slicersim reduce DATASET``)
REDUCED_FILES = {"spectra": "reduced.h5", "cubes": "reduced.h5", "rates": "rates.h5"}
#: folder of a target's JWST reference files, beside its ramps (slicersim reffiles --ramps)
REFERENCE_DIR = "reference"
_REDUCER = []

#: default memory budget of one campaign task [bytes]: its cube chunks, its ramp blocks and the correlated
#: noise's segment cache (one segment per group: ~3 MB per group on the Lazuli H4RG; with 256 MiB a 62-group
#: ramp synthesised its segments 2.6 times over)
TASK_MAX_BYTES = 2**30

#: Philox stream deriving a target's seeds from (campaign seed, target id)
SEED_STREAM = 0x43414D50          # "CAMP"
#: wavelength grid [Å] on which the input spectra are sampled
SPECTRUM_GRID = (3000.0, 20000.0, 10.0)


def spectrum_grid():
    return np.arange(*SPECTRUM_GRID)


def target_seeds(campaign_seed, target_ids):
    """(noise seed, ramp seed) per target, uint64, from one Philox block keyed by
    (campaign seed, target id, :data:`SEED_STREAM`): independent of the number of targets,
    their order and the workers."""
    ids = np.asarray(target_ids, dtype=np.uint64)
    words = rng.random_words(int(campaign_seed), ids, stream=SEED_STREAM).astype(np.uint64)
    noise = words[..., 0] | (words[..., 1] << np.uint64(32))
    ramps = words[..., 2] | (words[..., 3] << np.uint64(32))
    return noise, ramps


def limit_threads(threads):
    """Restrict this process's OpenCL CPU threads (before its context exists)."""
    if not threads:
        return
    from slicersim.backends import opencl
    limit = getattr(opencl, "limit_cpu_threads", None)
    if limit is not None:
        try:
            limit(int(threads))
        except Exception:                   # context already made with another count: keep it
            pass
    else:
        os.environ.setdefault("POCL_MAX_PTHREAD_COUNT", str(int(threads)))


#: the former private name (reduction.campaign imports it)
_limit_threads = limit_threads


def register_reducer(reducer):
    """Register the function reducing one target's ramps for streaming campaigns:
    ``reducer(ramps_path, out_path, mode, field)`` writes ``out_path`` atomically (``mode``: "spectra" or
    "rates"; ``field``: the target's).  :mod:`slicersim.reduction.streaming` registers it on import."""
    if not callable(reducer):
        from slicersim.errors import ParameterError
        raise ParameterError(f"reducer must be callable, got {type(reducer).__name__}")
    _REDUCER[:] = [reducer]


def registered_reducer():
    """The registered reducer (:func:`register_reducer`), or None."""
    return _REDUCER[0] if _REDUCER else None


def build_target(spec, row, readout=True):
    """The :class:`~slicersim.targets.LazuliTarget` of one catalog row (its host in the
    scene), with the row's readout applied when ``readout``."""
    from slicersim.targets import LazuliTarget
    obs = spec.observation
    lbda, flux = spec.population.spectrum(row, spectrum_grid())
    redshift = float(row["redshift"])
    target = LazuliTarget(lbda, flux, config=obs["config"], field=str(row["field"]),
                          redshift=redshift if redshift > 0 else None, conventions=obs["conventions"])
    host = spec.population.host(row)
    if host is not None:
        target.set_host(host)
    if readout:
        target.change_detector(nmd=(int(row["n"]), int(row["m"]), int(row["d"])), nramps=int(row["nramps"]))
    return target, (lbda, flux)


def _attrs(row, seed, kind):
    return {"target_id": int(row["target_id"]), "redshift": float(row["redshift"]), "field": str(row["field"]),
            "nmd": np.array([row["n"], row["m"], row["d"]], dtype=np.int64), "nramps": int(row["nramps"]),
            "seed": np.uint64(seed), "product": kind, "software": "slicersim"}


def _write_spectrum(path, target, row, seed, source):
    lbda, signal, variance = target.get_spectrum()
    noisy = target.get_spectrum(incl_error=True, seed=int(seed))[1]
    flambda = np.interp(lbda, source[0], source[1], left=np.nan, right=np.nan)
    with ProductFile(path, overwrite=True) as f:
        f.set_attrs(_attrs(row, seed, "spectrum"))
        f.write("lbda", lbda, {"unit": "Angstrom"})
        f.write("flambda", flambda, {"unit": "erg/s/cm2/Angstrom"})
        f.write("signal", signal, {"unit": "adu"})
        f.write("variance", variance, {"unit": "adu2"})
        f.write("noisy", noisy, {"unit": "adu"})


def _write_cube(path, target, row, seed, spec, max_bytes):
    obs, prod = spec.observation, spec.products
    dtype = np.dtype(prod["cube_dtype"])
    from slicersim.products.cube import build_cube
    cube = build_cube(target.simulation, seed=int(seed), psf_profile=obs["psf_profile"], max_bytes=max_bytes,
                      progress=False, dtype=dtype, precision=prod.get("precision", "auto"))
    signal, variance, noisy = cube.signal, cube.variance, cube.noisy
    with ProductFile(path, overwrite=True) as f:
        # the precision the kernels ran in ("auto" resolves per device): recorded with the product
        f.set_attrs({**_attrs(row, seed, "cube"), "psf_profile": obs["psf_profile"],
                     "precision": cube.paths["precision"], "noise_precision": cube.paths["noise_precision"]})
        f.write("lbda", target.simulation.lbda, {"unit": "Angstrom"})
        for name, cube, unit in (("signal", signal, "adu"), ("variance", variance, "adu2"), ("noisy", noisy, "adu")):
            f.write(name, cube, {"unit": unit})      # stored as computed (cube_dtype); contiguous: one write each


def _write_image(path, target, row, seed):
    from slicersim.backends.precision import resolve_precision
    precision = resolve_precision("auto", "auto", "projection")[1]      # the deposit's, as "auto" picks it
    image = target.get_detector_image(precision=precision)
    with ProductFile(path, overwrite=True) as f:
        f.set_attrs({**_attrs(row, seed, "detector_image"), "precision": precision})
        f.write("rate", np.asarray(image, dtype=np.float32), {"unit": "electron/s"}, chunks=(256, 4096),
                compression="gzip", compression_opts=1, shuffle=True)     # mostly dark: ~10× smaller


#: catalog columns that are not the target's truth (readout, plan, seeds, status)
_NOT_TRUTH = {"n", "m", "d", "nramps", "seed", "ramp_seed", "status", "error", "exposure_time", "snr", "data_volume",
              "data_volume_compressed", "redshift", "field"}


def truth_meta(spec, row):
    """The attributes of a target's ``truth/target`` from its catalog row (target_id, phase,
    peak_absmag, x1, c, host_*, ...: the population's draws) and its population (source, band,
    magsys of a SN Ia model)."""
    meta = {k: v for k, v in dict(row).items() if k not in _NOT_TRUTH and not k.endswith(("_product", "_sha256"))
            and isinstance(v, (int, float, str, np.integer, np.floating))}
    for key in ("source", "band", "magsys"):
        value = getattr(spec.population, key, None)
        if isinstance(value, str):
            meta.setdefault(key, value)
    return meta


def _write_ramps(path, target, row, seed, spec, memory):
    comp = spec.products["compression"]
    named = spec.products.get("effects", "none")
    effects = None
    if named != "none":                              # checked with the spec; the same names as `ramp --effects`
        from slicersim.physics.effects import DetectorEffects
        effects = DetectorEffects.from_text(named)
    extra = {}
    rows = reduced_rows(spec, row, target)
    if rows is not None:              # reduced now and deleted: no compression to undo a minute later
        extra["rows"], comp = rows, "none"
    target.get_ramps(out=path, seed=int(seed), compression=None if comp == "none" else comp,
                     overwrite=True, max_bytes=memory, progress=False, target_meta=truth_meta(spec, row),
                     effects=effects, **extra)
    from slicersim.products import reference         # the JWST reference files of the ramps kept, beside them
    if spec.products.get("reference_files") and spec.keeps_ramps(int(row["target_id"])):   # (maps of the ramp seed)
        reference.write_reference_files_for_ramps(path, os.path.join(os.path.dirname(path), REFERENCE_DIR),
                                                  overwrite=True)


def reduced_rows(spec, row, target):
    """The detector rows to simulate for a target whose ramps are reduced as they are made and not kept
    (``products.reduce`` "spectra" or "cubes"): the rows its field's reduction reads
    (``detector_rows()`` of :class:`~slicersim.instrument.footprints.FieldFootprints`, 27 % of the Lazuli H4RG); the
    spectra and cubes are those of the full-detector ramp (to rounding), the rate images NaN elsewhere.
    None (every row) when the ramps are kept, written as level-1b files, or reduced to rates only."""
    if spec.products.get("reduce") not in ("spectra", "cubes") or spec.keeps_ramps(int(row["target_id"])) \
            or spec.products.get("ramp_format") == "jwst-uncal":
        return None
    from slicersim.assembly import default_mapper
    from slicersim.instrument.footprints import field_footprints
    footprints = field_footprints(default_mapper(), target.field, spectrograph=target.simulation.spectrograph)
    return footprints.detector_rows()


def run_target(spec, row, dataset_path, spec_sha256, max_bytes=TASK_MAX_BYTES, threads=None, reducer=None):
    """Simulate and write the products of one target; returns its record (also written to
    ``records/``).  Any error is caught and recorded (status "failed") so a campaign goes on.
    With ``products.reduce`` the ramps are then reduced by ``reducer`` (None: the registered one,
    :func:`register_reducer`) and deleted unless kept (``products.keep_ramps``)."""
    limit_threads(threads)
    row = dict(row)
    tid = int(row["target_id"])
    ds = Dataset(dataset_path)
    seed, ramp_seed = int(row["seed"]), int(row["ramp_seed"])
    record = {"target_id": tid, "spec_sha256": spec_sha256, "seed": seed, "ramp_seed": ramp_seed,
              "readout": [int(row["n"]), int(row["m"]), int(row["d"]), int(row["nramps"])],
              "field": str(row["field"])}
    t0 = time.perf_counter()
    try:
        ds.clean_target(tid)
        pdir = ds.target_dir(tid, make=True)           # a real folder inside the dataset
        target, source = build_target(spec, row)
        products = {}
        for name in spec.wanted:
            fits = name == "ramps" and spec.products.get("ramp_format") == "jwst-uncal"    # level-1b
            path = os.path.join(pdir, f"{name}.fits" if fits else f"{name}.h5")
            if name == "spectrum":
                _write_spectrum(path, target, row, seed, source)
            elif name == "cube":
                _write_cube(path, target, row, seed, spec, max_bytes)
            elif name == "detector_image":
                _write_image(path, target, row, seed)
            else:
                _write_ramps(path, target, row, ramp_seed, spec, max(max_bytes, 64 * 2**20))
            products[name] = product_info(path)
        if spec.products.get("reduce"):
            _stream(spec, row, pdir, products, reducer)
        record.update(status="done", products=products, device=_device_name())
    except Exception as exc:                       # recorded, the campaign goes on
        mark_failed(ds, tid, record, exc)
    ds.write_timing(tid, time.perf_counter() - t0)
    ds.write_record(tid, record)
    return record


def _stream(spec, row, pdir, products, reducer):
    """Reduce the target's ramps just written into ``products["reduced"]``; delete them (and their
    entry) unless ``products.keep_ramps`` keeps them."""
    from slicersim.errors import ConfigError
    reducer = reducer or registered_reducer()
    if reducer is None:
        raise ConfigError("products.reduce needs the reduction: import slicersim.reduction.streaming "
                          "(importing slicersim does)")
    mode = spec.products["reduce"]
    ramps = os.path.join(pdir, products["ramps"]["file"])
    out = os.path.join(pdir, REDUCED_FILES[mode])
    reducer(ramps, out, mode, str(row["field"]))
    products["reduced"] = product_info(out)
    if not spec.keeps_ramps(row["target_id"]):
        os.remove(ramps)
        del products["ramps"]


def mark_failed(ds, tid, record, exc):
    """Record a target's failure (one-line error and a short traceback) and remove its partial
    products, so that a rerun starts it afresh."""
    record.update(status="failed", error=f"{type(exc).__name__}: {' '.join(str(exc).split())}",
                  traceback=traceback.format_exc(limit=8))
    try:
        ds.clean_target(tid)
    except OSError:                 # DatasetError included (a link in the dataset): nothing removed
        pass


def _device_name():
    try:
        from slicersim.backends import opencl
        return str(opencl.get_device().name).strip()
    except Exception:
        return "numpy"
