"""The paper's survey numbers next to ours: time and raw data volume vs redshift, survey totals.

* per target at z = 0.2, 1.0, 1.5 (hsiao-subsampled at peak, M_B = −19.3, Planck18; CBE;
  narrow field below z = 0.8, wide above; SNR 20 and 25 per resolution element in
  rest-frame 4000–6800 Å; exact search): readout, exposure time, raw data volume, with our
  physical default and with ``conventions="slicersim-1.0"``; slicersim 1.0.0's own outputs
  from ``../shared/reference/cases`` where a case exists (read at run time, not copied);
* 8000 SNe Ia, z uniform in 0.05–1.5 (seed 1): survey duration (100 % efficiency, no
  overheads) and total raw volume, for SNR 20 and 25, both conventions;
* the paper's figure (time rightwards, volume leftwards, redshift upwards) as a PNG.

Paper (slicersim 1.0, §"simulate a survey"): 23 GB of grouped raw data at z = 1.5, ~1 GB
at z = 0.2; 8000 SNe Ia z = 0–1.5: ~1 yr on sky at SNR 20, 1.5 yr at SNR 25.
Writes benchmarks/results/survey_vs_paper.{json,md,png}.
Usage: ``python benchmarks/survey_vs_paper.py [--n 8000]``
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _common import cpu_model, loadavg, write_json  # noqa: E402

PAPER = {"volume_gb": {0.2: 1.0, 1.5: 23.0}, "years": {20: 1.0, 25: 1.5}}
ZS = (0.2, 1.0, 1.5)


def reference_case(z, snr, field="narrow"):
    """slicersim 1.0.0's ETC output for a public case, or None."""
    root = Path(os.environ.get("SLICERSIM_REFERENCE_DIR", HERE.parent.parent / "shared" / "reference"))
    path = root / "cases" / f"sn_z{z:.2f}_cbe_{field}_snr{snr}.json"
    if not path.exists():
        return None
    out = json.loads(path.read_text())["outputs"]
    return {"field": field, "nmd": out["nmd"], "nramps": out["nramps"], "exposure_time_s": out["exposure_time_total_s"],
            "data_volume_gb": out["data_volume_GB"]}


def per_redshift(snr, conventions):
    from slicersim.campaign.plan import plan_survey
    from slicersim.campaign.population import SNIaPopulation
    from slicersim.campaign.products import spectrum_grid
    from astropy.table import Table
    lbda = spectrum_grid()
    pop = SNIaPopulation(1)
    flux = np.nan_to_num(pop.spectra(Table({"redshift": list(ZS), "phase": [0.0] * 3, "peak_absmag": [-19.3] * 3}),
                                     lbda))
    plan = plan_survey(np.array(ZS), lbda, flux, snr=snr, conventions=conventions)
    return [{"z": z, "field": str(r["field"]), "nmd": [int(r["n"]), int(r["m"]), int(r["d"])],
             "nramps": int(r["nramps"]), "exposure_time_s": float(r["exposure_time"]),
             "data_volume_gb": int(r["data_volume"]) / 1e9} for z, r in zip(ZS, plan.table)]


def survey(n, snr, conventions):
    from slicersim.campaign.plan import plan_survey
    from slicersim.campaign.population import SNIaPopulation
    from slicersim.campaign.products import spectrum_grid
    pop = SNIaPopulation(n, redshift={"distribution": "uniform", "min": 0.05, "max": 1.5})
    t0 = time.perf_counter()
    tab = pop.draw(1)
    lbda = spectrum_grid()
    flux = np.nan_to_num(pop.spectra(tab, lbda))
    plan = plan_survey(np.asarray(tab["redshift"]), lbda, flux, snr=snr, conventions=conventions)
    return plan, time.perf_counter() - t0


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=8000)
    ap.add_argument("--out", default=str(HERE / "results"), help="results folder (default benchmarks/results)")
    args = ap.parse_args()
    res = {"cpu": cpu_model(), "cores": os.cpu_count(), "load_before": loadavg(), "n": args.n, "paper": PAPER,
           "per_redshift": {}, "reference_1_0_0": {}, "survey": {}}
    for snr in (20, 25):
        for conv in ("physical", "slicersim-1.0"):
            res["per_redshift"][f"{conv} snr{snr}"] = per_redshift(snr, conv)
        res["reference_1_0_0"][f"snr{snr}"] = {z: reference_case(z, snr) for z in ZS}
    plans = {}
    for snr in (20, 25):
        for conv in ("physical", "slicersim-1.0"):
            plan, secs = survey(args.n, snr, conv)
            t = plan.totals
            res["survey"][f"{conv} snr{snr}"] = {"years": t["duration_years"], "data_volume_tb": t["data_volume"] / 1e12,
                                                "failed": t["failed"], "seconds": secs,
                                                "per_field": t["targets_per_field"]}
            print(f"[survey] {conv} SNR {snr}: {t['duration_years']:.3f} yr, {t['data_volume'] / 1e12:.1f} TB "
                  f"({secs:.1f} s)", flush=True)
            if conv == "physical":
                plans[f"SNR {snr}"] = plan
    res["load_after"] = loadavg()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from slicersim.campaign.plan import plot_time_and_volume
    paper_pts = {"volumes (text)": (np.array([0.2, 1.5]), None, np.array([1.0, 23.0]))}
    plot_time_and_volume(plans, out / "survey_vs_paper.png", paper=paper_pts)
    write_json(out / "survey_vs_paper.json", res)
    md = markdown(res)
    (out / "survey_vs_paper.md").write_text(md)
    print(md)


def _fmt_row(r):
    if r is None:
        return "—", "—", "—"
    n, m, d = r["nmd"]
    return f"({n},{m},{d})×{r['nramps']} {r['field']}", f"{r['exposure_time_s'] / 3600:.2f}", f"{r['data_volume_gb']:.1f}"


def markdown(res):
    lines = [f"`python benchmarks/survey_vs_paper.py` on {res['cpu']} ({res['cores']} cores).", "",
             "| z | SNR | paper: volume | 1.0.0 reference case (narrow): readout, h, GB | ours (physical): readout, h, GB "
             "| ours (slicersim-1.0 conventions): readout, h, GB |", "|---|---|---|---|---|---|"]
    for snr in (20, 25):
        phys = res["per_redshift"][f"physical snr{snr}"]
        old = res["per_redshift"][f"slicersim-1.0 snr{snr}"]
        for i, z in enumerate(ZS):
            ref = res["reference_1_0_0"][f"snr{snr}"][z]
            pv = PAPER["volume_gb"].get(z)
            lines.append(f"| {z} | {snr} | {'~%g GB' % pv if pv else '—'} | {' · '.join(_fmt_row(ref))} | "
                         f"{' · '.join(_fmt_row(phys[i]))} | {' · '.join(_fmt_row(old[i]))} |")
    lines += ["", f"| {res['n']} SNe Ia, z U(0.05, 1.5), seed 1 | paper | ours (physical) | ours (slicersim-1.0) |",
              "|---|---|---|---|"]
    for snr in (20, 25):
        a, b = res["survey"][f"physical snr{snr}"], res["survey"][f"slicersim-1.0 snr{snr}"]
        lines.append(f"| SNR {snr}: on-sky time | ~{PAPER['years'][snr]:g} yr | {a['years']:.2f} yr | {b['years']:.2f} yr |")
        lines.append(f"| SNR {snr}: raw data (uncompressed) | — | {a['data_volume_tb']:.1f} TB | "
                     f"{b['data_volume_tb']:.1f} TB |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
