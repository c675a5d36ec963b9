"""
Closed-loop bias per step
=========================

The closed loop as a user runs it: ``slicersim ramp --redshift Z --seed K --field F`` then
``slicersim reduce RAW --out RED --spectra --field F``, with every other option at its default
(MACC(16, 8, 0) × 1 ramp, CBE; narrow field below z = 0.8, wide from it).  Left: the band flux
recovered over the input (rest frame 4000–6800 Å, truth the ETC's signal in e-/s) per redshift,
± the standard error of the mean over the realisations.  Right: the same at z = 0.5 with each
detector effect switched on in the ramps and corrected (or not) by the reduction's defaults.  The
numbers are read from ``benchmarks/results/closed_loop_defaults*.json``
(``benchmarks/closed_loop_defaults.py``, about a minute per realisation).
"""
import json
from pathlib import Path

import matplotlib.pyplot as plt

import slicersim


def results_folder():
    """``benchmarks/results`` of the repository: above the working directory, else beside the
    package (an editable install, as ``make`` makes)."""
    starts = [Path.cwd(), Path(slicersim.__file__).resolve().parent]
    for start in starts:
        for folder in (start, *start.parents):
            if (folder / "benchmarks" / "results" / "closed_loop_defaults.json").is_file():
                return folder / "benchmarks" / "results"
    raise FileNotFoundError("benchmarks/results/closed_loop_defaults.json: run from the repository")


RESULTS = results_folder()

defaults = json.loads((RESULTS / "closed_loop_defaults.json").read_text())
rows = sorted(defaults["summary"], key=lambda r: r["z"])
effects = []
for path in sorted(RESULTS.glob("closed_loop_defaults_*.json")):
    data = json.loads(path.read_text())
    for r in data["summary"]:
        effects.append((data["effects"] or path.stem, r))

fig, (ax_z, ax_e) = plt.subplots(1, 2, figsize=(12, 4.3), constrained_layout=True,
                                 gridspec_kw={"width_ratios": [1, 1.3]})
for field, marker in (("narrow", "o"), ("wide", "s")):
    sel = [r for r in rows if r["field"] == field]
    ax_z.errorbar([r["z"] for r in sel], [100 * (r["ratio"] - 1) for r in sel],
                  yerr=[100 * r["ratio_err"] for r in sel], fmt=marker, capsize=3, label=f"{field} field")
ax_z.axhline(0, color="k", lw=0.8)
ax_z.axhspan(-1, 1, color="0.9", zorder=0, label="±1 %")
ax_z.set_xlabel("redshift")
ax_z.set_ylabel("band flux / input − 1 [%]")
ax_z.set_title("white noise, per redshift")
ax_z.legend(fontsize=8)

z05 = [r for r in rows if abs(r["z"] - 0.5) < 1e-9]
labels = ["none"] + [name.replace(",", " +\n") for name, _ in effects]
values = [z05[0]] + [r for _, r in effects] if z05 else [r for _, r in effects]
labels = labels if z05 else labels[1:]
ax_e.errorbar(range(len(values)), [100 * (r["ratio"] - 1) for r in values],
              yerr=[100 * r["ratio_err"] for r in values], fmt="o", capsize=3)
ax_e.axhline(0, color="k", lw=0.8)
ax_e.axhspan(-1, 1, color="0.9", zorder=0)
ax_e.set_xticks(range(len(values)), labels, rotation=30, ha="right", fontsize=8)
ax_e.set_ylabel("band flux / input − 1 [%]")
ax_e.set_title("z = 0.5, narrow field, per detector effect")
for r, name in zip(values, labels):
    print(f"{name.replace(chr(10), ' '):45s} {r['ratio']:.4f} ± {r['ratio_err']:.4f}  χ²/dof {r['chi2_dof']:.2f}")
plt.show()
