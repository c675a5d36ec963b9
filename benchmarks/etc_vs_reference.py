#!/usr/bin/env python
"""ETC benchmark: our ``slicersim`` against the public reference ``slicersim==1.0.0``.

For N SNe Ia (hsiao-subsampled, peak M_B = -19.3 AB, Planck18) at redshifts
drawn uniformly in [0.1, 1.5], both implementations search the readout mode
(n, m, d) x nramps reaching SNR 20 per resolution element in the observer-frame
band [4000(1+z), 6800(1+z)] Å (Lazuli CBE configuration, narrow field).

* The reference runs in its own virtual environment ``benchmarks/.refvenv``
  (created on demand, ``pip install slicersim==1.0.0``) through
  ``benchmarks/_reference_runner.py``, one ``LazuliTarget`` + ``setup_to_snr``
  per target.
* Our side runs in this interpreter: the batch solver
  ``slicersim.etc.solve_many`` (``search="reference"``: same walk as the
  reference; ``search="exact"``: shortest exposure reaching the target) and the
  single-target ``slicersim.targets.LazuliTarget`` path.

Outputs ``<out>/etc_vs_reference.json``, ``.md`` (commit, CPU, load, wall and CPU speed-ups) and ``.png``.

Usage::

    .venv/bin/python benchmarks/etc_vs_reference.py [--n 50] [--seed 2026]
        [--skip-reference] [--out benchmarks/results]

Environment: ``SLICERSIM_REFERENCE_DIR`` overrides the folder holding the
reference data (default ``<repo>/../shared/reference``; its ``config/`` holds
``lazuli_cbe.toml``).
"""

import argparse
import hashlib
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import cpu_model, jsonable, loadavg  # noqa: E402

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
REFVENV = HERE / ".refvenv"
RUNNER = HERE / "_reference_runner.py"
REFERENCE_SPEC = "slicersim==1.0.0"
REFERENCE_VERSION = "1.0.0"

SNR_DEFAULT = 20.0
LBDA_IN = np.arange(3000, 20000, 10.0)  # Å
BAND_REST = (4000.0, 6800.0)  # Å, rest frame, shifted to the observer frame
TFRAME = 2.83  # s, Lazuli CBE frame time (only for the sanity check T = r N_f t_f)
#: our conventions that reproduce slicersim 1.0 (the default "physical" ones count read noise, dark and
#: full well on 1 px per cell and give other readouts; :mod:`slicersim.physics.conventions`)
REFERENCE_CONVENTIONS = "slicersim-1.0"
#: speed-up goal of the batch solver (reference walk, warm) over slicersim 1.0.0 per target
GOAL_SPEEDUP = 300.0


# --------------------------------------------------------------------------- #
#  small helpers                                                              #
# --------------------------------------------------------------------------- #
def _readout_str(row):
    if not row or not row.get("ok"):
        return "error"
    n, m, d = row["nmd"]
    return f"({n},{m},{d})x{row['nramps']}"


def _same_readout(a, b):
    return bool(a and b and a.get("ok") and b.get("ok")
                and list(a["nmd"]) == list(b["nmd"]) and int(a["nramps"]) == int(b["nramps"]))


def reference_dir():
    env = os.environ.get("SLICERSIM_REFERENCE_DIR")
    if env:
        return Path(env).expanduser().resolve()
    return Path(__file__).resolve().parents[2] / "shared" / "reference"


def reference_config_file():
    """lazuli_cbe.toml of the reference data (None if absent)."""
    base = reference_dir()
    for cand in (base / "config" / "lazuli_cbe.toml", base / "lazuli_cbe.toml"):
        if cand.is_file():
            return cand
    return None


# --------------------------------------------------------------------------- #
#  inputs                                                                     #
# --------------------------------------------------------------------------- #
def build_inputs(n, seed, snr):
    import sncosmo
    from astropy.cosmology import Planck18

    rng = np.random.default_rng(seed=seed)
    zs = np.sort(rng.uniform(0.1, 1.5, size=n))
    fluxes = np.empty((n, LBDA_IN.size))
    for i, z in enumerate(zs):
        model = sncosmo.Model("hsiao-subsampled")
        model.set(z=z, t0=0)
        model.set_source_peakabsmag(-19.3, "bessellb", "ab", cosmo=Planck18)
        fluxes[i] = model.flux(0.0, LBDA_IN)  # erg/s/cm²/Å
    ranges = np.column_stack([BAND_REST[0] * (1 + zs), BAND_REST[1] * (1 + zs)])
    return {"z": zs, "lbda": LBDA_IN.copy(), "fluxes": fluxes, "lbda_ranges": ranges,
            "snr": float(snr), "frame": "obs", "band": "bessellb", "field": "narrow"}


# --------------------------------------------------------------------------- #
#  reference side                                                             #
# --------------------------------------------------------------------------- #
def _refvenv_python():
    return REFVENV / "bin" / "python"


def _ref_env():
    """Environment for the reference interpreter: no PYTHONPATH & co, which
    could make it import our package (or anything else) instead of its own."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP", "PYTHONSAFEPATH",
                        "VIRTUAL_ENV", "PYTHONUSERBASE", "__PYVENV_LAUNCHER__")}
    env["VIRTUAL_ENV"] = str(REFVENV)
    env["PYTHONNOUSERSITE"] = "1"
    return env


def _reference_importable():
    py = _refvenv_python()
    if not py.exists():
        return False, "no interpreter"
    # run outside the repository so that our own ./slicersim cannot shadow it
    proc = subprocess.run(
        [str(py), "-c", "import slicersim, sys; sys.stdout.write(slicersim.__version__ + '|' + slicersim.__file__)"],
        cwd=tempfile.gettempdir(), env=_ref_env(), capture_output=True, text=True, timeout=300)
    if proc.returncode != 0:
        return False, proc.stderr.strip().splitlines()[-1:] or "import failed"
    version, path = proc.stdout.split("|", 1)
    if version != REFERENCE_VERSION:
        return False, f"found slicersim {version} at {path}"
    if not Path(path).resolve().is_relative_to(REFVENV.resolve()):
        return False, f"slicersim imported from outside the venv: {path}"
    return True, path


def ensure_reference_venv():
    """Create benchmarks/.refvenv and install the reference (idempotent).

    Returns (ok, message).
    """
    ok, info = _reference_importable()
    if ok:
        return True, f"reference venv ready ({info})"
    log = REFVENV / "install.log"
    try:
        if not _refvenv_python().exists():
            print(f"[refvenv] creating {REFVENV} ...", flush=True)
            subprocess.run([sys.executable, "-m", "venv", "--clear", str(REFVENV)],
                           check=True, capture_output=True, text=True, timeout=600)
        print(f"[refvenv] pip install {REFERENCE_SPEC} (log: {log}) ...", flush=True)
        with open(log, "a") as fh:
            proc = subprocess.run(
                [str(_refvenv_python()), "-m", "pip", "install", "--disable-pip-version-check",
                 REFERENCE_SPEC],
                cwd=tempfile.gettempdir(), env=_ref_env(), stdout=fh, stderr=subprocess.STDOUT,
                timeout=1800)
        if proc.returncode != 0:
            tail = log.read_text(errors="replace").strip().splitlines()[-5:]
            return False, f"pip install {REFERENCE_SPEC} failed (rc={proc.returncode}): " + " | ".join(tail)
    except (subprocess.SubprocessError, OSError) as exc:
        return False, f"could not set up {REFVENV}: {exc.__class__.__name__}: {exc}"
    ok, info = _reference_importable()
    if not ok:
        return False, f"reference not importable after install: {info}"
    return True, f"reference installed ({info})"


def run_reference(input_npz, workdir):
    output = Path(workdir) / "reference_output.json"
    cmd = [str(_refvenv_python()), str(RUNNER), str(input_npz), str(output)]
    cfg = reference_config_file()
    if cfg is not None:
        cmd += ["--fallback-config", str(cfg)]
    print("[reference] " + " ".join(cmd), flush=True)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=workdir, env=_ref_env(), stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, text=True, timeout=3600)
    wall = time.perf_counter() - t0
    if proc.returncode != 0 or not output.exists():
        tail = (proc.stderr or proc.stdout or "").strip().splitlines()[-15:]
        return {"available": False, "reason": f"reference runner failed (rc={proc.returncode})",
                "stderr_tail": tail, "process_wall_s": wall}
    result = json.loads(output.read_text())
    result["available"] = True
    result["process_wall_s"] = wall
    if not Path(result.get("module_file", "/")).resolve().is_relative_to(REFVENV.resolve()):
        result["warning"] = "reference module not imported from benchmarks/.refvenv"
    return result


# --------------------------------------------------------------------------- #
#  our side                                                                   #
# --------------------------------------------------------------------------- #
def _import_ours():
    if str(REPO) not in sys.path:
        sys.path.insert(0, str(REPO))
    out = {}
    try:
        import slicersim
        out["slicersim"] = slicersim
    except Exception as exc:
        out["error"] = f"import slicersim: {exc.__class__.__name__}: {exc}"
        return out
    try:
        from slicersim.etc.solve import solve_many
        out["solve_many"] = solve_many
    except Exception as exc:
        out["solve_many_error"] = f"{exc.__class__.__name__}: {exc}"
    try:
        from slicersim.targets import LazuliTarget
        out["LazuliTarget"] = LazuliTarget
    except Exception as exc:
        out["LazuliTarget_error"] = f"{exc.__class__.__name__}: {exc}"
    return out


def _table_rows(table, n):
    rows = []
    cols = set(table.colnames)
    for i in range(n):
        rec = table[i]
        row = {"index": i, "ok": True,
               "nmd": [int(rec["n"]), int(rec["m"]), int(rec["d"])],
               "nramps": int(rec["nramps"]),
               "exposure_time": float(rec["exposure_time"])}
        if "snr" in cols:
            row["snr"] = float(rec["snr"])
        rows.append(row)
    return rows


def run_ours_batch(solve_many, inputs, config, search, repeat, precision="auto", conventions=None):
    """Time solve_many (wall and CPU of this process, PoCL's threads included); first call = cold,
    min of the others = warm."""
    args = dict(snr=inputs["snr"], lbda_ranges=inputs["lbda_ranges"], frame=inputs["frame"],
                config=config, field=inputs["field"], search=search, precision=precision,
                conventions=conventions or REFERENCE_CONVENTIONS)
    n = len(inputs["z"])
    times, cpu, table, err = [], [], None, None
    for _ in range(max(1, repeat)):
        try:
            c0 = time.process_time()
            t0 = time.perf_counter()
            table = solve_many(inputs["lbda"], inputs["fluxes"], **args)
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        except Exception as exc:
            err = f"{exc.__class__.__name__}: {exc}"
            print(f"[ours] solve_many(search={search!r}) failed: {err}", flush=True)
            traceback.print_exc(limit=4)
            break
    if table is None:
        return {"available": False, "search": search, "error": err}
    res = {"available": True, "search": search, "config": str(config),
           "precision": table.meta.get("precision"),
           "call_seconds": times, "call_cpu_seconds": cpu,
           "cold_seconds": times[0],
           "warm_seconds": min(times[1:]) if len(times) > 1 else None,
           "cold_cpu_seconds": cpu[0],
           "warm_cpu_seconds": min(cpu[1:]) if len(cpu) > 1 else None}
    best = res["warm_seconds"] if res["warm_seconds"] is not None else res["cold_seconds"]
    best_cpu = res["warm_cpu_seconds"] if res["warm_cpu_seconds"] is not None else res["cold_cpu_seconds"]
    res["cold_seconds_per_target"] = res["cold_seconds"] / n
    res["warm_seconds_per_target"] = best / n
    res["cold_cpu_seconds_per_target"] = res["cold_cpu_seconds"] / n
    res["warm_cpu_seconds_per_target"] = best_cpu / n
    try:
        res["rows"] = _table_rows(table, n)
    except Exception as exc:
        res["rows"] = [{"index": i, "ok": False, "error": f"table parsing: {exc}"} for i in range(n)]
    if err:
        res["error_after_first_call"] = err
    return res


def run_ours_single(LazuliTarget, inputs, config, warmup=1, conventions=None):
    def solve(flux, lo, hi):
        t0 = time.perf_counter()
        target = LazuliTarget(inputs["lbda"], flux, mag=None, band=inputs["band"],
                              config=config, field=inputs["field"],
                              conventions=conventions or REFERENCE_CONVENTIONS)
        t1 = time.perf_counter()
        target.setup_to_snr(inputs["snr"], lbda_range=(float(lo), float(hi)),
                            frame=inputs["frame"], search="reference")
        t2 = time.perf_counter()
        return target, t1 - t0, t2 - t1, t2 - t0

    warm = []
    for i in range(min(warmup, len(inputs["z"]))):
        t0 = time.perf_counter()
        try:
            solve(inputs["fluxes"][i], *inputs["lbda_ranges"][i])
            warm.append(time.perf_counter() - t0)
        except Exception as exc:
            warm.append(None)
            print(f"[ours] single-target warm-up failed: {exc.__class__.__name__}: {exc}", flush=True)

    rows = []
    for i, (flux, (lo, hi)) in enumerate(zip(inputs["fluxes"], inputs["lbda_ranges"])):
        row = {"index": i}
        try:
            target, tc, ts, tt = solve(flux, lo, hi)
            ro = target.get_readout_config()
            row.update({"ok": True, "nmd": [int(v) for v in ro["nmd"]],
                        "nramps": int(ro["nramps"]),
                        "exposure_time": float(target.get_exposure_time()),
                        "construct_s": tc, "setup_to_snr_s": ts, "seconds": tt})
        except Exception as exc:
            row.update({"ok": False, "error": f"{exc.__class__.__name__}: {exc}"})
        rows.append(row)
    ok = [r["seconds"] for r in rows if r.get("ok")]
    return {"available": bool(ok), "search": "reference", "config": str(config),
            "warmup_seconds": warm, "rows": rows,
            "n_ok": len(ok),
            "total_seconds": float(sum(ok)) if ok else None,
            "mean_seconds_per_target": float(np.mean(ok)) if ok else None,
            "median_seconds_per_target": float(np.median(ok)) if ok else None}


def opencl_info():
    try:
        from slicersim.backends.opencl import device_info
    except Exception as exc:
        return {"available": False, "reason": f"{exc.__class__.__name__}: {exc}"}
    try:
        return {"available": True, "device": jsonable(device_info())}
    except Exception as exc:
        return {"available": False, "reason": f"device_info(): {exc.__class__.__name__}: {exc}"}


def _versions_here(ours_module):
    out = {"python": platform.python_version()}
    for name in ("numpy", "scipy", "astropy", "sncosmo", "pyopencl"):
        try:
            out[name] = __import__(name).__version__
        except Exception:
            out[name] = None
    out["slicersim (ours)"] = getattr(ours_module, "__version__", None) if ours_module else None
    return out


# --------------------------------------------------------------------------- #
#  report                                                                     #
# --------------------------------------------------------------------------- #
def _rows_or_none(block, n):
    if block and block.get("available") and block.get("rows"):
        return block["rows"]
    return [None] * n


def build_report(inputs, ref, batch_ref, batch_exact, single, comparable):
    n = len(inputs["z"])
    r_ref = _rows_or_none(ref, n)
    r_bref = _rows_or_none(batch_ref, n)
    r_bex = _rows_or_none(batch_exact, n)
    r_single = _rows_or_none(single, n)

    rows = []
    for i in range(n):
        a, b, e, s = r_ref[i], r_bref[i], r_bex[i], r_single[i]
        flags = []
        if a and b and a.get("ok") and b.get("ok") and not _same_readout(a, b):
            flags.append("R")
        if b and s and b.get("ok") and s.get("ok") and not _same_readout(b, s):
            flags.append("S")
        if a and e and a.get("ok") and e.get("ok") and e["exposure_time"] > a["exposure_time"] * (1 + 1e-9):
            flags.append("E")
        if any(x is not None and not x.get("ok") for x in (a, b, e, s)):
            flags.append("!")

        def pick(x, keys=("nmd", "nramps", "exposure_time", "snr", "seconds", "error")):
            if x is None:
                return None
            return {k: x[k] for k in keys if k in x} | {"ok": x.get("ok", False)}

        rows.append({"index": i, "z": float(inputs["z"][i]),
                     "lbda_range": [float(v) for v in inputs["lbda_ranges"][i]],
                     "reference": pick(a), "ours_reference_batch": pick(b),
                     "ours_exact_batch": pick(e), "ours_reference_single": pick(s),
                     "flags": "".join(flags)})

    summary = {"n_targets": n, "readouts_comparable": comparable}

    def count_same(xs, ys):
        pairs = [(x, y) for x, y in zip(xs, ys) if x and y and x.get("ok") and y.get("ok")]
        return sum(_same_readout(x, y) for x, y in pairs), len(pairs)

    if ref.get("available"):
        summary["reference_cpu_seconds_per_target_mean"] = ref["summary"].get("mean_cpu_seconds_per_target")
        summary["reference_seconds_per_target_mean"] = ref["summary"]["mean_seconds_per_target"]
        summary["reference_seconds_per_target_median"] = ref["summary"]["median_seconds_per_target"]
        summary["reference_exposure_time_sum"] = float(sum(x["exposure_time"] for x in r_ref if x and x.get("ok")))
    if ref.get("available") and batch_ref.get("available"):
        same, npair = count_same(r_ref, r_bref)
        summary["identical_readouts_batch_reference_mode"] = same
        summary["compared_targets_batch"] = npair
    if ref.get("available") and single.get("available"):
        same, npair = count_same(r_ref, r_single)
        summary["identical_readouts_single_reference_mode"] = same
        summary["compared_targets_single"] = npair
    if batch_ref.get("available") and single.get("available"):
        same, npair = count_same(r_bref, r_single)
        summary["single_equals_batch"] = same
    t_ref = summary.get("reference_seconds_per_target_mean")
    for key, block in (("batch_reference", batch_ref), ("batch_exact", batch_exact)):
        if block.get("available"):
            summary[f"ours_{key}_seconds_per_target_cold"] = block["cold_seconds_per_target"]
            summary[f"ours_{key}_seconds_per_target_warm"] = block["warm_seconds_per_target"]
            summary[f"ours_{key}_cpu_seconds_per_target_warm"] = block["warm_cpu_seconds_per_target"]
            summary[f"ours_{key}_cpu_seconds_per_target_cold"] = block["cold_cpu_seconds_per_target"]
            if t_ref:
                summary[f"speedup_{key}_warm"] = t_ref / block["warm_seconds_per_target"]
                summary[f"speedup_{key}_cold"] = t_ref / block["cold_seconds_per_target"]
            c_ref = summary.get("reference_cpu_seconds_per_target_mean")
            if c_ref:
                summary[f"speedup_{key}_cpu_warm"] = c_ref / block["warm_cpu_seconds_per_target"]
                summary[f"speedup_{key}_cpu_cold"] = c_ref / block["cold_cpu_seconds_per_target"]
            summary[f"ours_{key}_exposure_time_sum"] = float(
                sum(x["exposure_time"] for x in block["rows"] if x.get("ok")))
    if single.get("available"):
        summary["ours_single_seconds_per_target_mean"] = single["mean_seconds_per_target"]
        if t_ref:
            summary["speedup_single"] = t_ref / single["mean_seconds_per_target"]
    if batch_ref.get("available") and batch_exact.get("available"):
        pairs = [(x, y) for x, y in zip(r_bref, r_bex) if x and y and x.get("ok") and y.get("ok")]
        summary["exact_le_walk_sum"] = bool(sum(y["exposure_time"] for _, y in pairs)
                                            <= sum(x["exposure_time"] for x, _ in pairs) * (1 + 1e-12))
        summary["n_exact_longer_than_walk"] = int(sum(y["exposure_time"] > x["exposure_time"] * (1 + 1e-9)
                                                      for x, y in pairs))
        snr_goal = rows[0].get("snr_goal") if rows else None
        goal = snr_goal if snr_goal is not None else 20.0
        below = [x for x, _ in pairs if x.get("snr") is not None and x["snr"] < goal * (1 - 1e-9)]
        summary["n_walk_below_target"] = len(below)
        summary["n_exact_below_target"] = int(sum(y.get("snr") is not None and y["snr"] < goal * (1 - 1e-9)
                                                  for _, y in pairs))
        longer_ok = [(x, y) for x, y in pairs if y["exposure_time"] > x["exposure_time"] * (1 + 1e-9)]
        summary["n_exact_longer_and_walk_reached_target"] = int(sum(
            x.get("snr") is not None and x["snr"] >= goal * (1 - 1e-9) for x, _ in longer_ok))
    return rows, summary


def print_table(rows, summary, ref_note, ours_note):
    w = 24
    head = (f"{'#':>3} {'z':>7} | {'reference':<{w}} | {'ours ref-walk (batch)':<{w}} | "
            f"{'ours exact (batch)':<{w}} | flags")
    print()
    print(head)
    print("-" * len(head))

    def cell(x):
        if x is None:
            return f"{'-':<{w}}"
        if not x.get("ok"):
            return f"{'ERROR':<{w}}"
        return f"{_readout_str(x):<14}{x['exposure_time']:>10.2f}"

    for r in rows:
        print(f"{r['index']:>3} {r['z']:7.4f} | {cell(r['reference'])} | "
              f"{cell(r['ours_reference_batch'])} | {cell(r['ours_exact_batch'])} | {r['flags']}")
    print("flags: R = ours(reference mode) readout != reference; S = single-target != batch; "
          "E = exact T > reference T; ! = an error occurred")
    print()
    if ref_note:
        print(f"reference: {ref_note}")
    if ours_note:
        print(f"ours:      {ours_note}")
    n = summary["n_targets"]
    if "identical_readouts_batch_reference_mode" in summary:
        tag = "" if summary["readouts_comparable"] else "  (NOT comparable: our own 'cbe' curves were used)"
        print(f"identical readouts, reference mode (batch):  "
              f"{summary['identical_readouts_batch_reference_mode']}/{n} (goal {n}/{n}){tag}")
    if "identical_readouts_single_reference_mode" in summary:
        print(f"identical readouts, reference mode (single): "
              f"{summary['identical_readouts_single_reference_mode']}/{n}")

    def fmt_t(v):
        return "n/a" if v is None else f"{v * 1e3:.3f} ms"

    if "reference_seconds_per_target_mean" in summary:
        print(f"reference per target: mean {fmt_t(summary['reference_seconds_per_target_mean'])}, "
              f"median {fmt_t(summary['reference_seconds_per_target_median'])}, "
              f"CPU mean {fmt_t(summary.get('reference_cpu_seconds_per_target_mean'))}")
    for key, label in (("batch_reference", "batch ref-walk"), ("batch_exact", "batch exact")):
        if f"ours_{key}_seconds_per_target_warm" in summary:
            line = (f"ours {label:<15} per target: warm {fmt_t(summary[f'ours_{key}_seconds_per_target_warm'])}"
                    f", cold {fmt_t(summary[f'ours_{key}_seconds_per_target_cold'])}")
            if f"speedup_{key}_warm" in summary:
                line += (f"  -> reference/ours = {summary[f'speedup_{key}_warm']:.1f}x warm, "
                         f"{summary[f'speedup_{key}_cold']:.1f}x cold")
                if key == "batch_reference":
                    line += f" (goal >= {GOAL_SPEEDUP:g}x)"
            if f"speedup_{key}_cpu_warm" in summary:
                line += (f"\n     {'':<15} CPU per target: warm "
                         f"{fmt_t(summary[f'ours_{key}_cpu_seconds_per_target_warm'])} -> reference/ours "
                         f"(CPU-s) = {summary[f'speedup_{key}_cpu_warm']:.1f}x warm")
            print(line)
    if "ours_single_seconds_per_target_mean" in summary:
        line = f"ours single-target     per target: mean {fmt_t(summary['ours_single_seconds_per_target_mean'])}"
        if "speedup_single" in summary:
            line += f"  -> reference/ours = {summary['speedup_single']:.1f}x"
        print(line)
    sums = [(k, summary.get(k)) for k in ("reference_exposure_time_sum", "ours_batch_reference_exposure_time_sum",
                                          "ours_batch_exact_exposure_time_sum")]
    if any(v is not None for _, v in sums):
        print("total exposure time: " + ", ".join(
            f"{k.replace('_exposure_time_sum', '')} = {v:.2f} s" for k, v in sums if v is not None))
    if "exact_le_walk_sum" in summary:
        print(f"exact <= reference walk (sum): {summary['exact_le_walk_sum']}; "
              f"targets where exact is longer: {summary['n_exact_longer_than_walk']}")
    if "n_walk_below_target" in summary:
        print(f"reference walk ends BELOW the target SNR for {summary['n_walk_below_target']}/{n} targets "
              f"(its 0.5-per-bin tolerance); exact search below target: {summary['n_exact_below_target']}/{n}; "
              f"exact longer although the walk reached the target: "
              f"{summary['n_exact_longer_and_walk_reached_target']} (must be 0)")


def git_commit():
    """HEAD of the repository (with "+dirty" when tracked files differ), or None."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True,
                              timeout=30).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO,
                               capture_output=True, text=True, timeout=30).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return (head + ("+dirty" if dirty else "")) or None


def write_text_atomic(path, text):
    """Write ``text`` to ``path`` through a temporary name and a rename."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


def markdown_report(result):
    """The results as a markdown page: machine, timings (wall and CPU), speed-ups, readouts."""
    s, m = result["summary"], result["machine"]

    def ms(v):
        return "–" if v is None else f"{v * 1e3:.3f} ms"

    def x(v):
        return "–" if v is None else f"{v:.0f}×"
    n = s["n_targets"]
    lines = ["# ETC: ours against slicersim 1.0.0 (same run)", "",
             f"`benchmarks/etc_vs_reference.py --n {result['settings']['n']} --precision "
             f"{result['settings']['precision']} --conventions {result['settings']['conventions']}`, "
             f"{result['created']}; commit `{result.get('commit')}`.", "",
             f"Machine: {m.get('cpu_model')} ({m.get('cpu_count')} CPUs), load average {m.get('loadavg_start')} "
             f"at the start and {m.get('loadavg_end')} at the end (other jobs share the machine: wall times "
             f"are inflated by them, CPU times of each process much less), niceness {m.get('niceness')}.", "",
             f"{n} SNe Ia z = 0.1–1.5, SNR 20 per resolution element in [4000, 6800]·(1+z) Å, Lazuli CBE narrow "
             "field.  Per target: the reference's mean over its targets; ours: a `solve_many` call over all "
             "of them / N (warm: the best of the calls after the first).  CPU: `time.process_time` of the "
             "process (ours includes PoCL's worker threads).", "",
             "| solver | wall / target | CPU / target | reference / ours (wall) | reference / ours (CPU) |",
             "|---|---:|---:|---:|---:|",
             f"| slicersim 1.0.0 `setup_to_snr` | {ms(s.get('reference_seconds_per_target_mean'))} | "
             f"{ms(s.get('reference_cpu_seconds_per_target_mean'))} | 1× | 1× |"]
    ours = result["ours"]
    for key, label in (("batch_reference", "ours `solve_many`, search='reference'"),
                       ("batch_exact", "ours `solve_many`, search='exact'")):
        if f"ours_{key}_seconds_per_target_warm" not in s:
            continue
        prec = ours.get(key, {}).get("precision")
        for when in ("warm", "cold"):
            lines.append(f"| {label} ({when}, {prec}) | {ms(s.get(f'ours_{key}_seconds_per_target_{when}'))} | "
                         f"{ms(s.get(f'ours_{key}_cpu_seconds_per_target_{when}'))} | "
                         f"{x(s.get(f'speedup_{key}_{when}'))} | {x(s.get(f'speedup_{key}_cpu_{when}'))} |")
    if "ours_single_seconds_per_target_mean" in s:
        lines.append(f"| ours `LazuliTarget.setup_to_snr` | {ms(s['ours_single_seconds_per_target_mean'])} | – | "
                     f"{x(s.get('speedup_single'))} | – |")
    lines += ["", f"Goal: reference / ours ≥ {GOAL_SPEEDUP:g}× (search='reference', warm).", ""]
    if "identical_readouts_batch_reference_mode" in s:
        lines.append(f"Identical readouts (n, m, d) × ramps, search='reference' vs the reference: "
                     f"{s['identical_readouts_batch_reference_mode']}/{n} (batch), "
                     f"{s.get('identical_readouts_single_reference_mode', '–')}/{n} (single target).")
    if "n_walk_below_target" in s:
        lines.append(f"The walk ends below the target SNR for {s['n_walk_below_target']}/{n} targets; the exact "
                     f"search for {s['n_exact_below_target']}/{n}.")
    if not s.get("readouts_comparable"):
        lines.append("Readouts NOT comparable: the reference configuration files were not found.")
    return "\n".join(lines) + "\n"


def make_plot(path, rows, summary):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(13, 5))
    z = np.array([r["z"] for r in rows])
    styles = (("reference", "reference slicersim 1.0.0", dict(marker="o", ms=7, mfc="none", color="k", ls="")),
              ("ours_reference_batch", "ours, search='reference'", dict(marker="x", ms=6, color="tab:orange", ls="")),
              ("ours_exact_batch", "ours, search='exact'", dict(marker="+", ms=8, color="tab:blue", ls="")))
    for key, label, style in styles:
        t = np.array([r[key]["exposure_time"] if r[key] and r[key].get("ok") else np.nan for r in rows])
        if np.isfinite(t).any():
            ax1.plot(z, t, label=label, **style)
    ax1.set_yscale("log")
    ax1.set_xlabel("redshift z")
    ax1.set_ylabel("total exposure time [s]")
    ax1.set_title("SN Ia, SNR 20 / res. element, [4000, 6800](1+z) Å, CBE narrow")
    ax1.grid(alpha=0.3, which="both")
    if ax1.get_legend_handles_labels()[0]:
        ax1.legend()
    else:
        ax1.text(0.5, 0.5, "no exposure time available", ha="center", transform=ax1.transAxes)

    bars = [("reference\n(per target)", summary.get("reference_seconds_per_target_mean"), "k"),
            ("ours single\nLazuliTarget", summary.get("ours_single_seconds_per_target_mean"), "tab:green"),
            ("ours batch\nref-walk (cold)", summary.get("ours_batch_reference_seconds_per_target_cold"), "moccasin"),
            ("ours batch\nref-walk (warm)", summary.get("ours_batch_reference_seconds_per_target_warm"), "tab:orange"),
            ("ours batch\nexact (cold)", summary.get("ours_batch_exact_seconds_per_target_cold"), "lightsteelblue"),
            ("ours batch\nexact (warm)", summary.get("ours_batch_exact_seconds_per_target_warm"), "tab:blue")]
    bars = [b for b in bars if b[1] is not None]
    if bars:
        x = np.arange(len(bars))
        vals = np.array([b[1] for b in bars])
        ax2.bar(x, vals, color=[b[2] for b in bars])
        ax2.set_xticks(x, [b[0] for b in bars], fontsize=8)
        ax2.set_yscale("log")
        ref_t = summary.get("reference_seconds_per_target_mean")
        for xi, v in zip(x, vals):
            txt = f"{v * 1e3:.3g} ms"
            if ref_t and v > 0 and not math.isclose(v, ref_t):
                txt += f"\n{ref_t / v:.0f}x"
            ax2.annotate(txt, (xi, v), ha="center", va="bottom", fontsize=8)
    else:
        ax2.text(0.5, 0.5, "no timing available", ha="center", transform=ax2.transAxes)
    ax2.set_ylabel("wall time per target [s]")
    ax2.set_title("ETC wall time per target")
    ax2.grid(alpha=0.3, axis="y", which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# --------------------------------------------------------------------------- #
#  main                                                                       #
# --------------------------------------------------------------------------- #
def main(argv=None):
    parser = argparse.ArgumentParser(description="ETC benchmark: ours vs slicersim==1.0.0")
    parser.add_argument("--n", type=int, default=50, help="number of SNe Ia (default 50)")
    parser.add_argument("--seed", type=int, default=2026, help="numpy default_rng seed (default 2026)")
    parser.add_argument("--snr", type=float, default=SNR_DEFAULT, help="SNR per resolution element (default 20)")
    parser.add_argument("--skip-reference", action="store_true", help="do not run the reference")
    parser.add_argument("--repeat", type=int, default=2,
                        help="solve_many calls per search mode; 1st = cold, min of the rest = warm (default 2)")
    parser.add_argument("--precision", default="auto", choices=("auto", "double", "single"),
                        help="precision of solve_many's band-variance kernel (default auto: the dial's choice)")
    parser.add_argument("--conventions", default=REFERENCE_CONVENTIONS, choices=("slicersim-1.0", "physical"),
                        help="our conventions (default slicersim-1.0: the reference's, same readouts)")
    parser.add_argument("--out", default=str(HERE / "results"), help="output folder (default benchmarks/results)")
    args = parser.parse_args(argv)
    load_start = loadavg()

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    print(f"Building {args.n} SN Ia inputs (seed {args.seed}) ...", flush=True)
    inputs = build_inputs(args.n, args.seed, args.snr)

    with tempfile.TemporaryDirectory(prefix="etc_vs_reference_") as tmp:
        npz = Path(tmp) / "inputs.npz"
        np.savez(npz, **{k: np.asarray(v) for k, v in inputs.items()})

        # ---------------- reference ----------------
        if args.skip_reference:
            ref = {"available": False, "reason": "skipped (--skip-reference)"}
        else:
            ok, msg = ensure_reference_venv()
            print(f"[refvenv] {msg}", flush=True)
            if ok:
                try:
                    ref = run_reference(npz, tmp)
                except (subprocess.SubprocessError, OSError, ValueError) as exc:
                    ref = {"available": False, "reason": f"{exc.__class__.__name__}: {exc}"}
            else:
                ref = {"available": False, "reason": msg}
            if not ref.get("available"):
                print("*" * 72)
                print(f"REFERENCE UNAVAILABLE: {ref.get('reason')}")
                for line in ref.get("stderr_tail", []):
                    print(f"    {line}")
                print("Continuing with our side only.")
                print("*" * 72, flush=True)

    # ---------------- ours ----------------
    ours = _import_ours()
    cfg_file = reference_config_file()
    comparable = cfg_file is not None
    config = str(cfg_file) if comparable else "cbe"
    ours_note = (f"config={config!r}" if comparable else
                 "reference configuration files not found (set SLICERSIM_REFERENCE_DIR); "
                 "using config='cbe' (our own curves): readouts cannot be compared with the reference")
    batch_ref = batch_exact = single = {"available": False}
    if "error" in ours:
        ours_note = f"our package is not importable: {ours['error']}"
    else:
        if "solve_many" in ours:
            print("[ours] solve_many(search='reference') ...", flush=True)
            batch_ref = run_ours_batch(ours["solve_many"], inputs, config, "reference", args.repeat, args.precision,
                                       args.conventions)
            print("[ours] solve_many(search='exact') ...", flush=True)
            batch_exact = run_ours_batch(ours["solve_many"], inputs, config, "exact", args.repeat, args.precision,
                                         args.conventions)
        else:
            batch_ref = batch_exact = {"available": False,
                                       "reason": f"slicersim.etc.solve_many: {ours['solve_many_error']}"}
            print(f"[ours] batch mode unavailable: {ours['solve_many_error']}", flush=True)
        if "LazuliTarget" in ours:
            print("[ours] single-target LazuliTarget ...", flush=True)
            single = run_ours_single(ours["LazuliTarget"], inputs, config, conventions=args.conventions)
        else:
            single = {"available": False, "reason": f"slicersim.targets.LazuliTarget: {ours['LazuliTarget_error']}"}
            print(f"[ours] single-target mode unavailable: {ours['LazuliTarget_error']}", flush=True)

    if not any(b.get("available") for b in (batch_ref, batch_exact, single)):
        reasons = "; ".join(sorted({b.get("reason") or b.get("error") or "" for b in (batch_ref, batch_exact, single)}
                                   - {""})) or ours.get("error", "")
        ours_note = f"UNAVAILABLE ({reasons}) [{ours_note}]"
    rows, summary = build_report(inputs, ref, batch_ref, batch_exact, single, comparable)
    ref_note = None
    if ref.get("available"):
        ref_note = (f"{ref.get('reference_package')} from {ref.get('module_file')}; "
                    f"default config {ref['config'].get('package_config_dir')}/lazuli_cbe.toml"
                    + (f" (identical to shared copy: {ref['config'].get('packaged_equals_shared')})"
                       if "packaged_equals_shared" in ref["config"] else ""))
    else:
        ref_note = f"unavailable ({ref.get('reason')})"
    print_table(rows, summary, ref_note, ours_note)

    machine = {"platform": platform.platform(), "machine": platform.machine(),
               "cpu_model": cpu_model(), "cpu_count": os.cpu_count(),
               "loadavg_start": load_start, "loadavg_end": loadavg(), "niceness": os.nice(0),
               "python": sys.version.split()[0],
               "opencl": opencl_info() if "error" not in ours else {"available": False}}
    flux_hash = hashlib.sha256(np.ascontiguousarray(inputs["fluxes"]).tobytes()).hexdigest()

    def strip_rows(block):
        return {k: v for k, v in block.items() if k != "rows"}

    result = {
        "benchmark": "etc_vs_reference",
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "settings": {"n": args.n, "seed": args.seed, "snr_per_resolution_element": args.snr,
                     "redshift_range": [0.1, 1.5], "sncosmo_source": "hsiao-subsampled",
                     "peak_absmag": -19.3, "peak_absmag_band": "bessellb", "magsys": "ab",
                     "cosmology": "Planck18", "input_lbda": "numpy.arange(3000, 20000, 10.) AA",
                     "band_rest": list(BAND_REST), "frame": "obs", "field": "narrow",
                     "configuration": "cbe", "our_config": config, "repeat": args.repeat,
                     "precision": args.precision, "conventions": args.conventions, "fluxes_sha256": flux_hash},
        "commit": git_commit(),
        "machine": machine,
        "versions": {"ours": _versions_here(ours.get("slicersim")),
                     "reference": ref.get("versions") if ref.get("available") else None},
        "reference": strip_rows(ref),
        "ours": {"batch_reference": strip_rows(batch_ref), "batch_exact": strip_rows(batch_exact),
                 "single_reference": strip_rows(single), "note": ours_note},
        "summary": summary,
        "rows": rows,
    }
    json_path = out / "etc_vs_reference.json"
    write_text_atomic(json_path, json.dumps(jsonable(result), indent=1))
    md_path = out / "etc_vs_reference.md"
    write_text_atomic(md_path, markdown_report(result))
    png_path = out / "etc_vs_reference.png"
    try:
        make_plot(png_path, rows, summary)
    except Exception as exc:
        print(f"plot failed: {exc.__class__.__name__}: {exc}")
        png_path = None
    print(f"\nwrote {json_path}, {md_path}" + (f" and {png_path}" if png_path else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
