#!/usr/bin/env python
"""Benchmark: spectro-imaging cubes → 4096² H4RG detector image.

Compares our flux-conserving :class:`slicersim.instrument.mapper.SlicerMapper` (OpenCL
kernel and NumPy twin) with the public reference (``slicersim==1.0.0``,
``LazuliTarget.get_detector_image``, a point painter that interpolates the
spot table with a Delaunay interpolator, see ../shared/reference/README.md
§3.5).  Cases:

* ``default``: our own Lazuli layout (``SlicerMapper.default()``) and our
  CBE cubes (510 bins) of the SN Ia of the reference detector case
  (hsiao-subsampled, z = 1, peak M_B = −19.3 AB, Planck18, readout (16, 8, 0),
  1 ramp, ADU), narrow and wide field (source at the field centre).
* ``reference_table``: the reference's spot table (bilinear) and cubes of the
  same size as the reference's (525 bins, 58 × 116 each): the reference's own
  cubes when ``--reference`` runs it, else our cubes with the reference's
  configuration files (same grid).

For each: mapper construction, cold projection of both fields (weight tables
+ deposit; kernels already compiled), warm projection (tables cached), total
and per-slice flux conservation, OpenCL vs NumPy, repeatability.  Also the
reference's ``trace_xy_pix`` error, and an expected electron-rate image with
dark current, ROIC glow and thermal dark.

The reference itself runs only with ``--reference`` (once, ~45 s) in
``benchmarks/.refvenv``; its timing is saved in
``results/detector_image_reference_run.json`` and reused by later runs.  The
timing of ``../shared/reference/detector/sn_z1.00_cbe_detector.json`` (idle
machine) is always reported too.

    .venv/bin/python benchmarks/detector_image.py [--reference] [--repeat 5] [--skip-numpy]
"""
import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import timed as common_timed, write_json  # noqa: E402  (benchmarks/ is on sys.path)

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
REFVENV = HERE / ".refvenv"
LBDA_IN = np.arange(3000.0, 20000.0, 10.0)
NMD = (16, 8, 0)

REF_CODE = r"""
import sys, time, numpy as np
from slicersim import LazuliTarget
from slicersim.instrument.mapper import SlicerMapper
inp, out, table = sys.argv[1:4]
d = np.load(inp)
t0 = time.perf_counter(); mapper = SlicerMapper.from_data(table); t_map = time.perf_counter() - t0
target = LazuliTarget(d["lbda"], d["flux"], mag=None, band="bessellb")
target.change_detector(nmd=(16, 8, 0), nramps=1)
t0 = time.perf_counter(); (cn, _), (cw, _) = target.get_cube(which="both"); t_cube = time.perf_counter() - t0
t0 = time.perf_counter(); img = target.get_detector_image(mapper, cubes=(cn, cw)); t_proj = time.perf_counter() - t0
import slicersim
np.savez(out, cube_narrow=cn, cube_wide=cw, lbda=np.asarray(target.simulation.spectrograph.lbda),
         image_binned8=img.reshape(512, 8, 512, 8).sum(axis=(1, 3)), image_sum=img.sum(),
         npix=(img != 0).sum(), t_mapper=t_map, t_cube=t_cube, t_project_both=t_proj,
         module=slicersim.__file__, version=slicersim.__version__)
"""


def reference_dir():
    env = os.environ.get("SLICERSIM_REFERENCE_DIR")
    path = Path(env) if env else ROOT.parent / "shared" / "reference"
    return path if (path / "detector").is_dir() else None


def sn_flux():
    import sncosmo
    from astropy.cosmology import Planck18
    model = sncosmo.Model("hsiao-subsampled")
    model.set(z=1.0, t0=0.0)
    model.set_source_peakabsmag(-19.3, "bessellb", "ab", cosmo=Planck18)
    return model.flux(0.0, LBDA_IN)


def our_cubes(flux, config=None):
    """Signal cubes [ADU] (narrow, wide), e-/s cubes, grid, and the dark terms of our simulation."""
    from slicersim.targets import LazuliTarget
    out = {}
    for field in ("narrow", "wide"):
        t = LazuliTarget(LBDA_IN, flux, mag=None, band="bessellb", config=config, field=field)
        t.change_detector(nmd=NMD, nramps=1)
        sim = t.simulation
        out[field] = t.get_cube()[0]
        out[field + "_rate"] = sim.get_projected_scene() * sim.qe[:, None, None]      # e-/s/cell
        out["lbda"], out["edges"] = sim.spectrograph.lbda, sim.spectrograph.lbda_edges
        out["dark"] = dict(dark=sim.detector.dark, thermal_dark=float(sim.thermal_dark),
                           roic_glow=sim.detector.roic_glow, tframe=sim.detector.tframe)
    return out


def edges_from_centres(lbda):
    mid = 0.5 * (lbda[1:] + lbda[:-1])
    return np.concatenate([[2 * lbda[0] - mid[0]], mid, [2 * lbda[-1] - mid[-1]]])


def run_reference(flux, table, workdir):
    py = REFVENV / "bin" / "python"
    if not py.exists():
        return {"available": False, "reason": f"{py} not found (create it with benchmarks/etc_vs_reference.py)"}
    inp, out = Path(workdir) / "ref_in.npz", Path(workdir) / "ref_out.npz"
    np.savez(inp, lbda=LBDA_IN, flux=flux)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env.update(VIRTUAL_ENV=str(REFVENV), PYTHONNOUSERSITE="1")
    print("[reference] get_detector_image (~45 s) ...", flush=True)
    t0 = time.perf_counter()
    proc = subprocess.run([str(py), "-c", REF_CODE, str(inp), str(out), str(table)], cwd=workdir, env=env,
                          capture_output=True, text=True, timeout=3600)
    wall = time.perf_counter() - t0
    if proc.returncode != 0 or not out.exists():
        return {"available": False, "reason": f"reference failed (rc={proc.returncode})",
                "stderr_tail": (proc.stderr or "").strip().splitlines()[-10:]}
    d = dict(np.load(out))
    res = {"available": True, "process_wall_s": wall, "version": str(d["version"]), "module": str(d["module"])}
    for k in ("t_mapper", "t_cube", "t_project_both", "image_sum", "npix"):
        res[k] = float(d[k])
    return res, d


def timed(fn, repeat):
    """Result, wall-clock times and process CPU times (all threads, PoCL workers included)."""
    t = common_timed(fn, repeat)
    return t.result, t.walls, t.cpus


def bench_projection(mapper, lbda, edges, narrow, wide, backend, repeat):
    """Cold (tables + deposit) and warm (cached tables) projection of both fields."""
    mapper.clear_cache()
    run = lambda: mapper.project_fields(lbda, edges, narrow=narrow, wide=wide, backend=backend)   # noqa: E731
    img, cold, cold_cpu = timed(run, 1)
    img2, warm, warm_cpu = timed(run, repeat)
    return img, img2, {"cold_s": cold[0], "cold_cpu_s": cold_cpu[0], "warm_s": warm, "warm_cpu_s": warm_cpu,
                       "warm_min_s": min(warm), "warm_cpu_min_s": min(warm_cpu)}


def per_slice_flux_error(mapper, lbda, edges, cube, field):
    """max |image(slice alone) − cube row| / cube row over the field's slices."""
    err = []
    for row in range(cube.shape[1]):
        one = np.zeros_like(cube)
        one[:, row] = cube[:, row]
        img = mapper.project_cube(one, lbda, edges, field)
        err.append(abs(img.sum() / cube[:, row].sum() - 1))
    return float(max(err))


def flux_report(mapper, lbda, edges, img, narrow, wide, per_slice):
    total = narrow.sum() + wide.sum()
    rep = {"cube_sum": float(total), "image_sum": float(img.sum()),
           "total_rel_error": float(abs(img.sum() / total - 1)),
           "top_half_over_narrow_cube_rel_error": float(abs(img[2048:].sum() / narrow.sum() - 1)),
           "painted_pixels": int((img != 0).sum())}
    if per_slice:
        rep["per_slice_max_rel_error"] = max(per_slice_flux_error(mapper, lbda, edges, narrow, "narrow"),
                                             per_slice_flux_error(mapper, lbda, edges, wide, "wide"))
    return rep


def trace_errors(refdir):
    from slicersim.instrument.mapper import SlicerMapper
    d = np.load(refdir / "detector" / "sn_z1.00_cbe_detector.npz")
    table = refdir / "config" / "mapping_spotdata.csv"
    out = {}
    for name, kw in (("bilinear", {}), ("triangles", {"interpolation": "triangles",
                                                      "face_diagonal": d["mapper_face_diagonal"]})):
        m = SlicerMapper.from_table(table, **kw)
        px, py = m.forward(m.slice_ids[:, None, None], d["trace_fieldpos"][None, :, None],
                           d["trace_lbda_AA"][None, None, :])
        out[name + "_max_px"] = float(np.hypot(px - d["trace_xy_pix"][..., 0], py - d["trace_xy_pix"][..., 1]).max())
    rng = np.random.default_rng(1)
    s, phi, lam = rng.integers(1, 117, 200000), rng.uniform(-1, 1, 200000), rng.uniform(3500, 17002, 200000)
    a = np.array(SlicerMapper.from_table(table).forward(s, phi, lam))
    b = np.array(m.forward(s, phi, lam))
    dist = np.hypot(*(a - b))
    out["bilinear_vs_triangles_interior_max_px"] = float(dist.max())
    out["bilinear_vs_triangles_interior_median_px"] = float(np.median(dist))
    return out


def opencl_info():
    try:
        from slicersim.backends import opencl
        if opencl.is_available():
            dev = opencl.get_device()
            return {"device": dev.name.strip(), "platform": dev.platform.name.strip(),
                    "type": opencl.device_type(dev), "fp64": opencl.device_supports_fp64()}
    except Exception as exc:  # pragma: no cover - informative
        return {"error": str(exc)}
    return {"device": None}


def make_plot(path, img_default, rate_img, img_ref_table, ref_npz_binned, timing_rows):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    def binned(img):
        return img.reshape(512, 8, 512, 8).sum(axis=(1, 3))

    fig, ax = plt.subplots(2, 3, figsize=(16, 10.5))
    panels = [(ax[0, 0], binned(img_default), "ours, default layout: SN z=1, ADU per 8×8 px"),
              (ax[0, 2], binned(rate_img), "ours: expected rate incl. dark, glow, thermal [e-/s per 8×8]"),
              (ax[1, 0], binned(img_ref_table), "ours, reference spot table, same-size cubes [ADU/8×8]")]
    if ref_npz_binned is not None:
        panels.append((ax[1, 1], ref_npz_binned, "reference painter (not flux conserving) [ADU/8×8]"))
    for a, im, title in panels:
        pos = im[im > 0]
        norm = LogNorm(vmin=np.percentile(pos, 1), vmax=pos.max()) if pos.size else None
        h = a.imshow(im, origin="lower", norm=norm, cmap="magma", extent=(0, 4096, 0, 4096))
        a.set_title(title, fontsize=9)
        fig.colorbar(h, ax=a, fraction=0.046)
    r, c = np.unravel_index(np.argmax(np.where(np.arange(4096)[:, None] >= 2048, img_default, 0)), img_default.shape)
    r0, c0 = max(0, min(r - 128, 4096 - 256)), max(0, min(c - 128, 4096 - 256))
    cut = img_default[r0:r0 + 256, c0:c0 + 256]
    h = ax[0, 1].imshow(cut, origin="lower", cmap="magma", norm=LogNorm(vmin=max(cut.max() * 1e-4, 1e-6)),
                        extent=(c0, c0 + 256, r0, r0 + 256))
    ax[0, 1].set_title("ours, default layout: narrow-field SN trace, ADU/px", fontsize=9)
    fig.colorbar(h, ax=ax[0, 1], fraction=0.046)
    if ref_npz_binned is None:
        ax[1, 1].axis("off")
    a = ax[1, 2]
    labels = [row[0] for row in timing_rows]
    vals = [row[1] for row in timing_rows]
    a.barh(labels, vals, color=["tab:gray" if "reference" in lab else "tab:blue" for lab in labels])
    a.set_xscale("log")
    a.set_xlabel("seconds (both fields, 2 × 58 × 116 × nλ cells → 4096² image)")
    for i, v in enumerate(vals):
        a.text(v, i, f" {v:.3g} s", va="center", fontsize=8)
    a.set_title("projection wall time", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reference", action="store_true", help="run the reference get_detector_image once (~45 s)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--skip-numpy", action="store_true")
    ap.add_argument("--out", default=str(HERE / "results"))
    args = ap.parse_args(argv)
    outdir = Path(args.out)
    outdir.mkdir(parents=True, exist_ok=True)

    import slicersim
    from slicersim.backends import projection as compute_project, opencl
    from slicersim.instrument.mapper import SlicerMapper, detector_rate_image

    refdir = reference_dir()
    result = {"machine": {"cpu": platform.processor() or platform.machine(), "ncpu": os.cpu_count(),
                          "platform": platform.platform(), "load_average_start": os.getloadavg()},
              "opencl": opencl_info(), "versions": {"slicersim": slicersim.__version__, "numpy": np.__version__,
                                                     "python": platform.python_version()},
              "inputs": {"source": "SN Ia hsiao-subsampled z=1, peak M_B=-19.3 AB (Planck18), no renormalisation",
                         "readout_nmd": NMD, "nramps": 1, "units": "ADU per ramp"}}
    have_ocl = opencl.is_available() and opencl.device_supports_fp64()
    backends = (["opencl"] if have_ocl else []) + ([] if args.skip_numpy else ["numpy"])
    if have_ocl:                                    # compile the kernels outside the timings
        tiny = compute_project.build_tables(np.array([[1.0, 2.0, 1.0, 1.0, 2.0, 1.0]] * 4), (1, 2, 2),
                                            detector_shape=(64, 64), backend="opencl")
        compute_project.deposit(np.ones((1, 2, 2)), tiny, backend="opencl")

    flux = sn_flux()
    print("[ours] cubes (CBE) ...", flush=True)
    cubes = our_cubes(flux)
    t0 = time.perf_counter()
    mapper = SlicerMapper.default()
    t_map = time.perf_counter() - t0
    timing_rows, images = [], {}
    case = {"mapper_construct_s": t_map, "nlbda": int(cubes["lbda"].size), "backends": {}}
    for be in backends:
        print(f"[ours] default layout, {be} ...", flush=True)
        img, img2, tm = bench_projection(mapper, cubes["lbda"], cubes["edges"], cubes["narrow"], cubes["wide"],
                                         be, args.repeat if be == "opencl" else 1)
        tm["repeat_bit_identical"] = bool(np.array_equal(img, img2))
        case["backends"][be] = tm
        images[be] = img
        timing_rows += [(f"ours {be} warm", tm["warm_min_s"]), (f"ours {be} cold", tm["cold_s"])]
    main_img = images[backends[0]]
    if len(images) == 2:
        case["opencl_vs_numpy_max_abs_over_peak"] = float(np.abs(images["opencl"] - images["numpy"]).max()
                                                          / np.abs(images["numpy"]).max())
    print("[ours] default layout, flux per slice ...", flush=True)
    case["flux"] = flux_report(mapper, cubes["lbda"], cubes["edges"], main_img, cubes["narrow"], cubes["wide"], True)
    tables = [mapper.projection_tables(s, 116, cubes["edges"]) for s in (range(1, 59), range(59, 117))]
    case["tables_MB"] = float(sum(t.nbytes() for t in tables) / 2**20)
    rate = detector_rate_image(mapper, cubes["lbda"], cubes["edges"], narrow=cubes["narrow_rate"],
                               wide=cubes["wide_rate"], **cubes["dark"])
    dk = cubes["dark"]
    floor = dk["dark"] + dk["thermal_dark"] + dk["roic_glow"] / dk["tframe"]
    photo = cubes["narrow_rate"].sum() + cubes["wide_rate"].sum()
    case["rate_image"] = {"dark_terms": dk, "floor_e_per_s": floor, "min_pixel_e_per_s": float(rate.min()),
                          "sum_minus_floor_over_cube_rate": float((rate.sum() - floor * rate.size) / photo)}
    result["default"] = case
    mapper.clear_cache()

    ref_binned, ref_run = None, None
    if refdir is not None:
        table = refdir / "config" / "mapping_spotdata.csv"
        ref_json = json.loads((refdir / "detector" / "sn_z1.00_cbe_detector.json").read_text())
        result["trace_vs_reference"] = trace_errors(refdir)
        ref_npz = np.load(refdir / "detector" / "sn_z1.00_cbe_detector.npz")
        ref_binned = ref_npz["image_binned8_adu"].astype(np.float64)
        saved = outdir / "detector_image_reference_run.json"
        if args.reference:
            with tempfile.TemporaryDirectory() as tmp:
                got = run_reference(flux, table, tmp)
            if isinstance(got, tuple):
                ref_run, rd = got
                rcubes = {"narrow": rd["cube_narrow"], "wide": rd["cube_wide"], "lbda": rd["lbda"]}
                ref_binned = rd["image_binned8"]
                src = "cubes computed by the reference in this run"
                ref_run["measured"] = time.strftime("%Y-%m-%d %H:%M:%S")
                ref_run["load_average_after"] = os.getloadavg()
                saved.write_text(json.dumps(ref_run, indent=2))
            else:
                ref_run = got
        elif saved.is_file():
            ref_run = dict(json.loads(saved.read_text()), note="measured by an earlier --reference run")
        if "rcubes" not in locals():
            print("[ours] reference-config cubes ...", flush=True)
            rc = our_cubes(flux, config=str(refdir / "config" / "lazuli_cbe.toml"))
            rcubes = {"narrow": rc["narrow"], "wide": rc["wide"], "lbda": rc["lbda"]}
            src = "our cubes with the reference configuration files (same 525-bin grid)"
        redges = edges_from_centres(rcubes["lbda"])
        t0 = time.perf_counter()
        rmapper = SlicerMapper.from_table(table)
        rcase = {"cubes": src, "edges": "mid-points of the bin centres (ends extrapolated)",
                 "mapper_construct_s": time.perf_counter() - t0, "nlbda": int(rcubes["lbda"].size), "backends": {}}
        rimages = {}
        for be in backends:
            print(f"[ours] reference table, {be} ...", flush=True)
            img, img2, tm = bench_projection(rmapper, rcubes["lbda"], redges, rcubes["narrow"], rcubes["wide"], be,
                                             args.repeat if be == "opencl" else 1)
            tm["repeat_bit_identical"] = bool(np.array_equal(img, img2))
            rcase["backends"][be] = tm
            rimages[be] = img
        if len(rimages) == 2:
            rcase["opencl_vs_numpy_max_abs_over_peak"] = float(np.abs(rimages["opencl"] - rimages["numpy"]).max()
                                                               / np.abs(rimages["numpy"]).max())
        rimg = rimages[backends[0]]
        print("[ours] reference table, flux per slice ...", flush=True)
        rcase["flux"] = flux_report(rmapper, rcubes["lbda"], redges, rimg, rcubes["narrow"], rcubes["wide"], True)
        rcase["reference_painter_image_over_cube"] = ref_json["results"]["image_over_cube_total"]
        result["reference_table"] = rcase
        npix = ref_npz["image_binned8_npix"] > 0
        ours8 = rimg.reshape(512, 8, 512, 8).sum(axis=(1, 3))
        rcase["footprint_vs_reference"] = {
            "our_flux_in_8x8_bins_painted_by_reference": float(ours8[npix].sum() / ours8.sum()),
            "our_flux_in_painted_bins_or_their_neighbours": float(
                ours8[np.pad(npix, 1)[:-2, 1:-1] | np.pad(npix, 1)[2:, 1:-1] | np.pad(npix, 1)[1:-1, :-2]
                      | np.pad(npix, 1)[1:-1, 2:] | npix].sum() / ours8.sum())}
        t_json = ref_json["timings"]["get_detector_image_given_cubes_s"]["median_s"]
        t_here = ref_run["t_project_both"] if ref_run and ref_run.get("available") else None
        result["reference"] = {"run_here": ref_run, "json_timings": {k: ref_json["timings"][k] for k in (
            "get_detector_image_given_cubes_s", "get_detector_image_total_s", "project_narrow_field_s",
            "project_wide_field_s")}}
        timing_rows.append(("reference painter (json, idle)", t_json))
        if t_here:
            timing_rows.append(("reference painter (run here)", t_here))
        for be in backends:
            tm = rcase["backends"][be]
            timing_rows += [(f"ours {be} warm (ref. table)", tm["warm_min_s"]),
                            (f"ours {be} cold (ref. table)", tm["cold_s"])]
        result["speedup_vs_reference"] = {
            f"vs_{name}": {f"{be}_{k}": t / rcase["backends"][be][key] for be in backends
                           for k, key in (("warm", "warm_min_s"), ("cold", "cold_s"))}
            for name, t in (("json_idle_machine", t_json), ("run_here", t_here)) if t}
    else:
        rimg = None
        result["reference"] = {"available": False, "reason": "../shared/reference not found"}

    result["machine"]["load_average_end"] = os.getloadavg()
    write_json(outdir / "detector_image.json", result, indent=2)
    make_plot(outdir / "detector_image.png", main_img, rate, rimg if rimg is not None else main_img,
              ref_binned, sorted(timing_rows, key=lambda r: -r[1]))
    print(json.dumps({k: result[k] for k in result if k in ("speedup_vs_reference", "trace_vs_reference")},
                     indent=1, default=float))
    for name in ("default", "reference_table"):
        if name in result:
            c = result[name]
            print(name, "(cold, warm) wall/cpu s:",
                  {be: (round(v["cold_s"], 3), round(v["warm_min_s"], 3), round(v["cold_cpu_s"], 3),
                        round(v["warm_cpu_min_s"], 3)) for be, v in c["backends"].items()},
                  "flux", c["flux"]["total_rel_error"], c["flux"].get("per_slice_max_rel_error"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
