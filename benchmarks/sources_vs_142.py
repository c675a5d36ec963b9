#!/usr/bin/env python
"""Power-law targets: ours (``slicersim.targets.sources.LazuliPowerLaw``) vs slicersim 1.4.2, side by side.

Cases: F_λ ∝ (λ/5500 Å)^α with α ∈ {−2, 0, 1}, normalised to 20 and 22 AB in bessellr
(1.4.2's default band sdssr needs a download), narrow field, CBE.  For each case:

* the input F_λ at 5000–15000 Å (the α convention and the normalisation);
* the band SNR per resolution element, observer 4000–6800 Å, at the readout (16, 8, 0) × 1;
* ``setup_to_snr(20, lbda_range=(4000, 6800), frame="obs")``: readout, total exposure time, SNR.

Columns: 1.4.2 (``benchmarks/.refvenv142``, via ``_sources_142_runner.py``) with its own
instrumental blur and with ours (σ_x = 0.568 cells, blur mode "physical" of
``_blur_reference_runner.py``); ours on the shared reference ``lazuli_cbe.toml`` (1.4.2's
own, up to whitespace and its ``name`` key) with the reference walk and the exact search;
ours on the built-in ``cbe`` (our own Lazuli curves).  Every difference > 2 % is split into
the links of that chain (blur, model residual, search, configuration).

Writes benchmarks/results/sources_vs_142.{json,md}.  Usage:
    .venv/bin/python benchmarks/sources_vs_142.py [--skip-reference] [--out benchmarks/results]
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _common import cpu_model, write_json  # noqa: E402

REFVENV = HERE / ".refvenv142"
CASES = [(-2, 20), (0, 20), (1, 20), (-2, 22), (0, 22), (1, 22)]
BAND, WAVES, BAND_OBS, SNR, NMD = "bessellr", [5000.0, 6000.0, 8000.0, 10000.0, 15000.0], (4000.0, 6800.0), 20.0, (16, 8, 0)
TOLERANCE = 0.02


def reference_config():
    env = os.environ.get("SLICERSIM_REFERENCE_DIR")
    root = Path(env) if env else HERE.parents[1] / "shared" / "reference"
    cfg = root / "config" / "lazuli_cbe.toml"
    return str(cfg) if cfg.is_file() else None


def run_142():
    py = REFVENV / "bin" / "python"
    if not py.exists():
        subprocess.run([sys.executable, "-m", "venv", str(REFVENV)], check=True)
        subprocess.run([str(py), "-m", "pip", "install", "-q", "slicersim==1.4.2"], check=True)
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHON")}
    spec = {"cases": CASES, "band": BAND, "waves": WAVES, "band_obs": BAND_OBS, "snr": SNR, "nmd": NMD,
            "blur_modes": ["native", "physical"]}
    with tempfile.TemporaryDirectory() as tmp:
        inp, out, npz = Path(tmp) / "in.json", Path(tmp) / "out.json", Path(tmp) / "out.npz"
        inp.write_text(json.dumps(spec))
        subprocess.run([str(py), str(HERE / "_sources_142_runner.py"), str(inp), str(out), str(npz)],
                       check=True, env=env, cwd=tmp)
        return json.loads(out.read_text())


def run_ours(config, search):
    from slicersim.targets.sources import LazuliPowerLaw
    rows = []
    for alpha, mag in CASES:
        target = LazuliPowerLaw(alpha, mag, band=BAND, config=config, field="narrow")
        target.change_detector(nmd=NMD, nramps=1)
        row = {"alpha": alpha, "mag": mag, "nbins": int(target.simulation.lbda.size),
               "flux_at_waves": target.pointsource.flambda(np.array(WAVES)).tolist(),
               "snr_at_nmd": target.get_band_snr(BAND_OBS, per_resolution=True),
               "exposure_time_at_nmd": target.get_exposure_time()}
        t0 = time.perf_counter()
        etc = target.setup_to_snr(SNR, BAND_OBS, frame="obs", search=search)
        row.update(etc_s=time.perf_counter() - t0, nmd=list(etc["nmd"]), nramps=etc["nramps"],
                   snr=target.get_band_snr(BAND_OBS, per_resolution=True), exposure_time=target.get_exposure_time())
        rows.append(row)
    return rows


def readout(row):
    n, m, d = row["nmd"]
    return f"({n},{m},{d})×{row['nramps']} {row['exposure_time']:.0f} s"


def explain(columns, i):
    """Links of the chain 1.4.2 → 1.4.2 with our blur → ours (walk) → ours (exact) → ours (built-in cbe),
    for the exposure time and the SNR at the fixed readout; those off by > 2 % are named."""
    chain = [("blur (1.4.2's σ_x = 0.284 → our 0.568 cells)", "142_native", "142_physical_blur"),
             ("model residual (1.4.2 with our blur → ours, same TOML and walk)", "142_physical_blur", "ours_ref_walk"),
             ("search (reference walk, ends within ±0.5/bin of the target → exact, cheapest readout ≥ target)",
              "ours_ref_walk", "ours_ref_exact"),
             ("configuration (1.4.2's curves → our own built-in Lazuli CBE curves)", "ours_ref_exact", "ours_cbe_exact")]
    out = []
    for key, label in (("exposure_time", "exposure time"), ("snr_at_nmd", "SNR at (16,8,0)×1")):
        for name, a, b in chain:
            if key == "snr_at_nmd" and "search" in name:
                continue
            if a not in columns or b not in columns:
                continue
            ratio = columns[b][i][key] / columns[a][i][key]
            if abs(ratio - 1) > TOLERANCE:
                steps = ""
                if key == "exposure_time":
                    smooth = (columns[a][i]["snr"] / columns[b][i]["snr"]) ** 2 * ratio
                    steps = (f"; reached SNR {columns[a][i]['snr']:.2f} → {columns[b][i]['snr']:.2f}, "
                             f"ratio at equal SNR (T·(SNR_a/SNR_b)²) {smooth:.3f}: the rest is whole groups/ramps")
                out.append(f"{label} ×{ratio:.3f}: {name}{steps}")
    return out


def markdown(result):
    cols = result["columns"]
    names = [("142_native", "1.4.2"), ("142_physical_blur", "1.4.2, our blur"), ("ours_ref_walk", "ours, ref TOML, walk"),
             ("ours_ref_exact", "ours, ref TOML, exact"), ("ours_cbe_exact", "ours, built-in cbe, exact")]
    names = [(k, v) for k, v in names if k in cols]
    lines = ["# Power law: ours vs slicersim 1.4.2", "",
             f"F_λ ∝ (λ/5500 Å)^α normalised to `mag` AB in {BAND}, Lazuli CBE narrow field, SNR {SNR:g} per "
             f"resolution element over observer {BAND_OBS[0]:.0f}–{BAND_OBS[1]:.0f} Å "
             "(`python benchmarks/sources_vs_142.py`).", "",
             "**α convention and normalisation** (input F_λ, ours / 1.4.2, at " +
             ", ".join(f"{w:.0f}" for w in WAVES) + " Å):", ""]
    if "142_native" in cols:
        for i, (alpha, mag) in enumerate(CASES):
            ratio = np.array(cols["ours_cbe_exact"][i]["flux_at_waves"]) / np.array(cols["142_native"][i]["flux_at_waves"])
            lines.append(f"* α = {alpha:+d}, mag {mag}: " + ", ".join(f"{r:.6f}" for r in ratio))
        lines += ["", "Same convention (F_λ index α, λ_ref = 5500 Å) and normalisation.  The ≤ 2e-5 offsets: 1.4.2 "
                  "normalises and samples the power law on its 525-bin spectrograph grid (these values are linear "
                  "interpolations between its bins), ours on a 5 Å grid; 1.4.2's function on a dense 2 Å grid gives "
                  "ours to < 5e-6 (tests/sources/test_more_sources.py).", ""]
    lines += ["| α | mag | " + " | ".join(v for _, v in names) + " |", "|---|---|" + "---:|" * len(names)]
    for i, (alpha, mag) in enumerate(CASES):
        lines.append(f"| {alpha:+d} | {mag} | " + " | ".join(readout(cols[k][i]) for k, _ in names) + " |")
    lines += ["", "SNR per resolution element at (16,8,0)×1 (362 s):", "",
              "| α | mag | " + " | ".join(v for _, v in names) + " |", "|---|---|" + "---:|" * len(names)]
    for i, (alpha, mag) in enumerate(CASES):
        lines.append(f"| {alpha:+d} | {mag} | " + " | ".join(f"{cols[k][i]['snr_at_nmd']:.3f}" for k, _ in names) + " |")
    lines += ["", "## Differences > 2 %, link by link", ""]
    for i, (alpha, mag) in enumerate(CASES):
        for text in result["explanations"][i]:
            lines.append(f"* α = {alpha:+d}, mag {mag}: {text}")
    lines += ["", result["summary"]]
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--skip-reference", action="store_true", help="do not run slicersim 1.4.2")
    ap.add_argument("--out", default=str(HERE / "results"))
    args = ap.parse_args(argv)
    columns = {}
    if not args.skip_reference:
        ref = run_142()
        for mode, key in (("native", "142_native"), ("physical", "142_physical_blur")):
            columns[key] = [row for row in ref["cases"] if row["blur_mode"] == mode]
    cfg = reference_config()
    if cfg is not None:
        columns["ours_ref_walk"] = run_ours(cfg, "reference")
        columns["ours_ref_exact"] = run_ours(cfg, "exact")
    columns["ours_cbe_exact"] = run_ours("cbe", "exact")
    explanations = [explain(columns, i) for i in range(len(CASES))]
    residual = []
    if "142_physical_blur" in columns and "ours_ref_walk" in columns:
        residual = [abs(columns["ours_ref_walk"][i]["snr_at_nmd"] / columns["142_physical_blur"][i]["snr_at_nmd"] - 1)
                    for i in range(len(CASES))]
        same = sum(columns["ours_ref_walk"][i]["nmd"] == columns["142_physical_blur"][i]["nmd"]
                   and columns["ours_ref_walk"][i]["nramps"] == columns["142_physical_blur"][i]["nramps"]
                   for i in range(len(CASES)))
        summary = (f"With 1.4.2's blur replaced by ours, 1.4.2 and ours (same TOML, reference walk) agree: SNR at the "
                   f"fixed readout to {max(residual):.1e} (max relative), the same readout for {same}/{len(CASES)} cases. "
                   "The remaining differences are the blur (1.4.2 divides the aberration width by the anamorphosis "
                   "once more, README 'instrumental blur'), the search (the walk stops within ±0.5 per bin of the "
                   "target, exact returns the cheapest readout reaching it) and the built-in CBE curves, which are "
                   "our own (slicersim/data/lazuli/README.md: 510 bins instead of 525, our throughput and QE models; "
                   "11–31 % more SNR here).")
    else:
        summary = "slicersim 1.4.2 not run (--skip-reference) or reference TOML absent."
    result = {"cases": CASES, "band": BAND, "waves": WAVES, "band_obs": BAND_OBS, "snr": SNR, "nmd": NMD,
              "columns": columns, "explanations": explanations, "snr_residual_142_blur_vs_ours": residual,
              "summary": summary, "reference_config": cfg, "cpu": cpu_model()}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "sources_vs_142.json", result)
    text = markdown(result)
    (out / "sources_vs_142.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
