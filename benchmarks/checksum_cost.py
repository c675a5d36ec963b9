#!/usr/bin/env python
"""Cost of the Fletcher-32 checksums of raw-ramp HDF5 files (issue 26: keep it ≤ 10 %).

A full-detector ramp (``--side`` 4096, ``--ngroups`` groups, one ramp; SCI uint16 + GROUPDQ uint8,
noise-like values: 1000 + Poisson(100) + 12 e- read noise, drawn once) is written through
:class:`slicersim.io.rampfile.RampWriter` exactly as ``simulate(out=...)`` does (chunks of one group
× ``--row-block`` rows), once with the checksums (the package's default) and once with the same
writer minus ``fletcher32`` — alternately, ``--repeat`` times each, the median kept.  Then the
file is read back (``read_ramps``: the checksums verified) against the same read without them.
Each row: the compression (``--compression``, default none and lz4), write and read seconds with
and without, and their ratios.  The end-to-end row (``--e2e``, default on): ``simulate(rate, (ngroups,
1, 0), out=...)`` of a full-detector rate image (the default backend, as a user gets it; one frame
per group: the least computation per byte written, so the largest relative cost) and ``fit_ramps`` of
the file, with and without the checksums (``h5py`` ``create_dataset`` stripped of ``fletcher32`` for
the baseline), alternated.  As the end-to-end difference is small against its run-to-run scatter on a
shared machine, the checksum's own cost is also given as the writer rows' added seconds over the
end-to-end time (``added_fraction``).

Writes ``<out>/checksum_cost.json`` and ``.md``.

    .venv/bin/python benchmarks/checksum_cost.py [--side 4096] [--ngroups 16] [--repeat 3]
        [--compression none lz4] [--e2e-repeat 1] [--out benchmarks/results] [--tmp DIR]
"""
import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))

from _common import cpu_model, write_json  # noqa: E402
from slicersim.io.rampfile import RampWriter, read_ramps  # noqa: E402


class _NoChecksumWriter(RampWriter):
    """RampWriter without Fletcher-32 (the baseline)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.compression.pop("fletcher32", None)


def _ramp(side, ngroups, seed=1):
    rng = np.random.default_rng(seed)
    charge = np.cumsum(rng.poisson(100.0, (ngroups, side, side)).astype(np.float32), axis=0)
    sci = np.clip(1000.0 + charge + rng.normal(0.0, 12.0, charge.shape), 0, 65535).astype(np.uint16)
    return sci[None], np.zeros(sci[None].shape, np.uint8)


def _write(cls, path, sci, gdq, compression, row_block):
    _, n, ny, nx = sci.shape
    t = time.perf_counter()
    with cls(path, 1, n, (ny, nx), attrs={"NFRAMES": 1, "GROUPGAP": 0, "TFRAME": 2.83}, row_block=row_block,
             compression=compression, pixeldq=False, overwrite=True) as w:
        for y0 in range(0, ny, row_block):
            w.write_block(0, y0, sci[0, :, y0:y0 + row_block], gdq[0, :, y0:y0 + row_block])
    return time.perf_counter() - t


def _read(path):
    t = time.perf_counter()
    read_ramps(path)
    return time.perf_counter() - t


def measure(tmp, sci, gdq, compression, row_block, repeat):
    """{write/read seconds with and without checksums (medians), ratios, file sizes}."""
    comp = None if compression == "none" else compression
    paths = {"with": os.path.join(tmp, "with.h5"), "without": os.path.join(tmp, "without.h5")}
    times = {"write_with": [], "write_without": [], "read_with": [], "read_without": []}
    _write(RampWriter, paths["with"], sci[..., :64, :], gdq[..., :64, :], comp, min(row_block, 64))   # warm-up
    for _ in range(repeat):
        times["write_without"].append(_write(_NoChecksumWriter, paths["without"], sci, gdq, comp, row_block))
        times["write_with"].append(_write(RampWriter, paths["with"], sci, gdq, comp, row_block))
        times["read_without"].append(_read(paths["without"]))
        times["read_with"].append(_read(paths["with"]))
    med = {k: float(np.median(v)) for k, v in times.items()}
    return {"compression": compression, **med,
            "write_ratio": med["write_with"] / med["write_without"],
            "read_ratio": med["read_with"] / med["read_without"],
            "bytes_with": os.path.getsize(paths["with"]), "bytes_without": os.path.getsize(paths["without"]),
            "samples": times}


class _without_fletcher32:
    """Context: every h5py create_dataset without fletcher32 (the baseline of the end-to-end row)."""

    def __enter__(self):
        import h5py
        self._orig = h5py.Group.create_dataset

        def create(group, *args, **kwargs):
            kwargs.pop("fletcher32", None)
            return self._orig(group, *args, **kwargs)
        h5py.Group.create_dataset = create
        return self

    def __exit__(self, *exc):
        import h5py
        h5py.Group.create_dataset = self._orig


def measure_e2e(tmp, side, ngroups, repeat):
    """simulate(out=...) and fit_ramps(file) seconds with and without checksums (medians), ratios."""
    import contextlib

    from slicersim.products.ramps import simulate
    from slicersim.reduction.ramp_fit import fit_ramps
    rate = np.random.default_rng(2).uniform(0.0, 50.0, (side, side))
    warm = os.path.join(tmp, "warm.h5")                     # imports, kernels, caches: not timed
    fit_ramps(simulate(rate[:64, :64], (ngroups, 1, 0), seed=3, out=warm, progress=False, overwrite=True),
              progress=False)
    times = {"simulate_with": [], "simulate_without": [], "fit_with": [], "fit_without": []}
    for _ in range(repeat):
        for label, ctx in (("without", _without_fletcher32), ("with", contextlib.nullcontext)):
            path = os.path.join(tmp, f"e2e_{label}.h5")
            with ctx():
                t = time.perf_counter()
                simulate(rate, (ngroups, 1, 0), seed=3, out=path, progress=False, overwrite=True)
                times[f"simulate_{label}"].append(time.perf_counter() - t)
            t = time.perf_counter()
            fit_ramps(path, progress=False)
            times[f"fit_{label}"].append(time.perf_counter() - t)
    med = {k: float(np.median(v)) for k, v in times.items()}
    return {"compression": "end-to-end (simulate + fit_ramps, none)", **med,
            "write_with": med["simulate_with"], "write_without": med["simulate_without"],
            "read_with": med["fit_with"], "read_without": med["fit_without"],
            "write_ratio": med["simulate_with"] / med["simulate_without"],
            "read_ratio": med["fit_with"] / med["fit_without"], "samples": times}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--side", type=int, default=4096)
    ap.add_argument("--ngroups", type=int, default=16)
    ap.add_argument("--row-block", type=int, default=256)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--compression", nargs="+", default=["none", "lz4"])
    ap.add_argument("--out", default=str(HERE / "results"))
    ap.add_argument("--tmp", default=None)
    ap.add_argument("--no-e2e", dest="e2e", action="store_false", help="skip the end-to-end row")
    ap.add_argument("--e2e-repeat", type=int, default=1, help="repeats of the (slow) end-to-end row")
    args = ap.parse_args(argv)
    sci, gdq = _ramp(args.side, args.ngroups)
    rows = []
    with tempfile.TemporaryDirectory(dir=args.tmp) as tmp:
        for comp in args.compression:
            row = measure(tmp, sci, gdq, comp, args.row_block, args.repeat)
            rows.append(row)
            print(f"{comp:>8}: write {row['write_without']:.2f} s → {row['write_with']:.2f} s with Fletcher-32 "
                  f"(×{row['write_ratio']:.3f}); read {row['read_without']:.2f} s → {row['read_with']:.2f} s "
                  f"(×{row['read_ratio']:.3f})", flush=True)
        if args.e2e:
            row = measure_e2e(tmp, args.side, args.ngroups, args.e2e_repeat)
            plain = next((r for r in rows if r["compression"] == "none"), None)
            if plain is not None:                   # the writer's added seconds over the whole job
                row["added_fraction"] = {
                    "write": (plain["write_with"] - plain["write_without"]) / row["write_with"],
                    "read": (plain["read_with"] - plain["read_without"]) / row["read_with"]}
                print(f"checksum cost over the end-to-end job: write {100 * row['added_fraction']['write']:+.1f} %, "
                      f"read {100 * row['added_fraction']['read']:+.1f} %", flush=True)
            rows.append(row)
            print(f"end-to-end: simulate {row['write_without']:.2f} s → {row['write_with']:.2f} s "
                  f"(×{row['write_ratio']:.3f}); fit_ramps {row['read_without']:.2f} s → {row['read_with']:.2f} s "
                  f"(×{row['read_ratio']:.3f})", flush=True)
    result = {"side": args.side, "ngroups": args.ngroups, "row_block": args.row_block, "repeat": args.repeat,
              "e2e_repeat": args.e2e_repeat, "loadavg": os.getloadavg(),
              "uncompressed_bytes": int(sci.nbytes + gdq.nbytes), "cpu": cpu_model(), "rows": rows,
              "command": " ".join(["benchmarks/checksum_cost.py"] + (argv if argv is not None else sys.argv[1:]))}
    write_json(os.path.join(args.out, "checksum_cost.json"), result)
    lines = ["# Fletcher-32 checksum cost of raw-ramp files", "",
             f"{args.side}² pixels, {args.ngroups} groups, 1 ramp ({result['uncompressed_bytes'] / 1e9:.2f} GB "
             f"uncompressed SCI + GROUPDQ), median of {args.repeat}; CPU {result['cpu']}.", "",
             "Rows 'none'/'lz4': RampWriter alone (write) and read_ramps (read); the end-to-end row: "
             "simulate(out=...) (write) and fit_ramps (read).", "",
             "| compression | write without [s] | write with [s] | ratio | read without [s] | read with [s] | ratio |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {r['compression']} | {r['write_without']:.2f} | {r['write_with']:.2f} | {r['write_ratio']:.3f} | "
              f"{r['read_without']:.2f} | {r['read_with']:.2f} | {r['read_ratio']:.3f} |" for r in rows]
    lines += [f"\nThe writer's added seconds ('none' row) over the end-to-end job: write "
              f"{100 * r['added_fraction']['write']:+.1f} %, read {100 * r['added_fraction']['read']:+.1f} % "
              f"(load average {result['loadavg'][0]:.2f})." for r in rows if "added_fraction" in r]
    with open(os.path.join(args.out, "checksum_cost.md"), "w") as fh:
        fh.write("\n".join(lines) + "\n")
    _plot(rows, result, os.path.join(args.out, "checksum_cost.png"))
    return 0


def _plot(rows, result, path):
    """Bar chart of the with/without ratios (write and read) per row."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    labels = [r["compression"].split(" (")[0] for r in rows]
    x = np.arange(len(rows))
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.bar(x - 0.2, [r["write_ratio"] for r in rows], 0.4, label="write")
    ax.bar(x + 0.2, [r["read_ratio"] for r in rows], 0.4, label="read")
    ax.axhline(1.0, color="k", lw=0.8)
    ax.axhline(1.1, color="r", ls="--", lw=0.8, label="+10 %")
    ax.set_xticks(x, labels)
    ax.set_ylabel("time with / without Fletcher-32")
    ax.set_title(f"{result['side']}² × {result['ngroups']} groups; {result['cpu']}, load {result['loadavg'][0]:.1f}",
                 fontsize=8)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
