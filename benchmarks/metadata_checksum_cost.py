#!/usr/bin/env python
"""Cost of the metadata checksums of HDF5 files (issue 33: keep it ≤ 2 %).

Question: what do checksummed object headers (attributes, layouts: HDF5's 1.8 file format,
``slicersim.io.atomic.HDF5_LIBVER``) cost ``simulate(out=...)`` and ``fit_ramps(file)``?
Baseline: the same calls writing HDF5's earliest format (no metadata checksums), in the same run,
alternated ``--repeat`` times, the median kept, in wall and CPU seconds (this process and its
threads).  The data chunks carry Fletcher-32 in both.  Acceptance: ratio ≤ 1.02.

Writes ``<out>/metadata_checksum_cost.json`` and ``.md`` (commit, CPU, device, load).

    .venv/bin/python benchmarks/metadata_checksum_cost.py [--side 2048] [--ngroups 8] [--repeat 3]
"""
import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))

from _common import cpu_model, loadavg, markdown_table, write_results  # noqa: E402
from slicersim.io import atomic  # noqa: E402


def _timed(fn):
    """(wall s, CPU s) of ``fn()``."""
    w, c = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - w, time.process_time() - c


def _commit():
    try:
        return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--side", type=int, default=2048)
    p.add_argument("--ngroups", type=int, default=8)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--out", default=str(HERE / "results"))
    args = p.parse_args(argv)
    from slicersim.products.ramps import simulate
    from slicersim.reduction.ramp_fit import fit_ramps
    rate = np.random.default_rng(1).gamma(2.0, 2.0, (args.side, args.side))
    checked = atomic.HDF5_LIBVER
    rows = {"with": {"simulate": [], "fit": []}, "without": {"simulate": [], "fit": []}}
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(-1, args.repeat):                # i = -1: warm-up (kernels built, caches filled), not kept
            order = (("with", checked), ("without", "earliest"))
            for label, libver in (order if i % 2 == 0 else order[::-1]):
                atomic.HDF5_LIBVER = libver
                path = os.path.join(tmp, f"r_{label}_{i}.h5")
                sim = _timed(lambda: simulate(rate, nmd=(args.ngroups, 1, 0), seed=1, out=path))
                fit = _timed(lambda: fit_ramps(path))
                os.remove(path)
                if i >= 0:
                    rows[label]["simulate"].append(sim)
                    rows[label]["fit"].append(fit)
    atomic.HDF5_LIBVER = checked
    result = {"question": "cost of checksummed HDF5 metadata on simulate(out=...) and fit_ramps(file)",
              "baseline": "the same calls writing HDF5's earliest format (no metadata checksums)",
              "acceptance": "median ratio ≤ 1.02", "commit": _commit(), "cpu": cpu_model(), "device": "default backend",
              "load": loadavg(), "side": args.side, "ngroups": args.ngroups, "repeat": args.repeat, "rows": {}}
    table = []
    for step in ("simulate", "fit"):
        w_with, c_with = np.median(np.array(rows["with"][step]), axis=0)
        w_wo, c_wo = np.median(np.array(rows["without"][step]), axis=0)
        result["rows"][step] = {"wall_with": w_with, "wall_without": w_wo, "cpu_with": c_with, "cpu_without": c_wo,
                                "ratio_wall": w_with / w_wo, "ratio_cpu": c_with / c_wo}
        table.append([f"`{'simulate(out=...)' if step == 'simulate' else 'fit_ramps(file)'}`", f"{w_wo:.2f}",
                      f"{w_with:.2f}", f"**{w_with / w_wo:.3f}**", f"{c_wo:.2f}", f"{c_with:.2f}",
                      f"{c_with / c_wo:.3f}"])
    md = "\n".join([f"### Metadata checksum cost (`benchmarks/metadata_checksum_cost.py`)", "",
                    f"{args.side}² detector, {args.ngroups} groups × 1 frame, medians of {args.repeat} alternated "
                    f"runs; {result['cpu']}, load {result['load']}, commit {result['commit']}.", "",
                    *markdown_table(["call", "wall without [s]", "wall with [s]", "ratio", "CPU without [s]",
                                     "CPU with [s]", "CPU ratio"], table), ""])
    write_results(args.out, "metadata_checksum_cost", result, md)
    print(md)


if __name__ == "__main__":
    main()
