#!/usr/bin/env python
"""Raw-ramp HDF5 files: compression ratio and write speed of the supported filters.

The ramp: the Lazuli-like 2048² image of ``ramp_throughput.py``
(:func:`lazuli_rate_image`), MACC(16, 8, 0), one ramp, read noise 12 e-, simulated once in
memory (SCI uint16 + GROUPDQ uint8).  Each compression setting of
:func:`slicersim.io.rampfile.compression_options` — None, gzip levels 1 and 4 (+ byte shuffle),
``lz4`` (Blosc2/LZ4 + bit-shuffle), ``zstd`` (Blosc2/Zstd level 3 + bit-shuffle),
``bitshuffle-lz4`` (bitshuffle filter + LZ4) — writes the same arrays through
:class:`slicersim.io.rampfile.RampWriter` exactly as ``simulate(out=...)`` does (chunks of one group
× 256 rows); the time covers ``write_block`` and closing the file (median of ``--repeat``).
Reported: stored SCI and GROUPDQ bytes (HDF5 storage size), SCI compression ratio
(uncompressed / stored), write speed in MB/s of uncompressed SCI + GROUPDQ (1 MB = 1e6 B),
read-back time (median) and a lossless check.  The uncompressed SCI size is compared with
``Detector(shape=(ny, nx)).data_volume((n, m, d), nramps)`` [GB].

Two noise models, simulated with the same seed: ``white`` (Poisson, white read noise, kTC-free
bias: today's ramp) and ``lazuli`` (``effects="lazuli"``: cosmic rays, IPC, nonlinearity, NGHXRG
correlated noise, reference and bad pixels) — 1/f noise and cosmic rays make raw data less
compressible.

Writes ``<out>/ramp_compression.json``, ``.png`` and ``.md``.

    .venv/bin/python benchmarks/ramp_compression.py [--side 2048] [--repeat 3] [--out benchmarks/results]
        [--tmp DIR]
"""
import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))

from ramp_throughput import DETECTOR, lazuli_rate_image  # noqa: E402
from slicersim.instrument.detector import Detector  # noqa: E402
from slicersim.io.rampfile import RampWriter, read_ramps  # noqa: E402
from slicersim.products.ramps import simulate  # noqa: E402

SETTINGS = [None, "gzip:1", "gzip:4", "lz4", "zstd", "bitshuffle-lz4"]
NMD, NRAMPS = (16, 8, 0), 1


def write_once(path, sci, gdq, compression, row_block):
    """Seconds to write SCI + GROUPDQ (1 ramp) and close the file."""
    nramps, n, ny, nx = sci.shape
    t = time.perf_counter()
    with RampWriter(path, nramps, n, (ny, nx), attrs={"READPATT": "MACC(16,8,0)"}, row_block=row_block,
                    compression=compression, pixeldq=False, overwrite=True) as w:
        for y0 in range(0, ny, row_block):
            w.write_block(0, y0, sci[0, :, y0:y0 + row_block], gdq[0, :, y0:y0 + row_block])
    return time.perf_counter() - t


def measure(sci, gdq, compression, repeat, tmp, row_block=256):
    import h5py
    path = Path(tmp) / f"ramp_{str(compression).replace(':', '')}.h5"
    times = [write_once(path, sci, gdq, compression, row_block) for _ in range(repeat)]
    with h5py.File(path, "r") as fh:
        sci_stored = fh["SCI"].id.get_storage_size()
        gdq_stored = fh["GROUPDQ"].id.get_storage_size()
        filters = fh["SCI"]._filters if hasattr(fh["SCI"], "_filters") else {}
    reads = []
    for _ in range(repeat):
        t = time.perf_counter()
        back, back_dq, _, _ = read_ramps(path)
        reads.append(time.perf_counter() - t)
    t_read = float(np.median(reads))
    lossless = bool(np.array_equal(back, sci) and np.array_equal(back_dq, gdq))
    size = path.stat().st_size
    path.unlink()
    raw = sci.nbytes + gdq.nbytes
    w = float(np.median(times))
    return {"compression": compression or "none", "write_s": w, "write_s_all": times,
            "write_MB_per_s": raw / w / 1e6, "write_MB_per_s_best": raw / min(times) / 1e6, "read_s": t_read, "read_MB_per_s": raw / t_read / 1e6,
            "sci_stored_bytes": int(sci_stored), "gdq_stored_bytes": int(gdq_stored), "file_bytes": int(size),
            "sci_ratio": sci.nbytes / sci_stored, "gdq_ratio": gdq.nbytes / gdq_stored,
            "total_ratio": raw / (sci_stored + gdq_stored), "lossless": lossless,
            "hdf5_filters": {str(k): str(v) for k, v in dict(filters).items()}}


def plot(result, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for c, case in enumerate(result["cases"]):
        for k, r in enumerate(case["rows"]):
            ax.scatter(r["write_MB_per_s"], r["sci_ratio"], s=60, color=f"C{k}", marker="os"[c % 2],
                       label=f"{r['compression']} ({case['noise']})")
            ax.annotate(r["compression"], (r["write_MB_per_s"], r["sci_ratio"]), textcoords="offset points",
                        xytext=(6, 4), fontsize=7)
    ax.legend(fontsize=6, ncol=2)
    ax.set_xscale("log")
    ax.set_xlabel("write speed [MB/s of uncompressed SCI + GROUPDQ]")
    ax.set_ylabel("SCI compression ratio")
    ax.set_title(f"{result['shape'][0]}² × {result['nmd'][0]} groups, raw ramps: o white, s lazuli effects (load "
                 f"{result['machine']['loadavg_before'][0]:.1f})", fontsize=10)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def markdown(result):
    ny, nx = result["shape"]
    lines = ["### Raw-ramp file compression (`benchmarks/ramp_compression.py`)", "",
             f"Lazuli-like {ny}×{nx} image, MACC{tuple(result['nmd'])}, 1 ramp, read noise 12 e- "
             f"(SCI {result['sci_bytes'] / 1e6:.0f} MB + GROUPDQ {result['gdq_bytes'] / 1e6:.0f} MB); "
             "chunks of 1 group × 256 rows; median of "
             f"{result['repeat']} writes on the shared 2-core VM (load {result['machine']['loadavg_before'][0]:.1f}).",
             "", "| noise | compression | SCI ratio | GROUPDQ ratio | file [MB] | write [MB/s] median (best) | read [MB/s] | lossless |",
             "|---|---|---:|---:|---:|---:|---:|---|"]
    for case in result["cases"]:
        for r in case["rows"]:
            lines.append(f"| {case['noise']} | {r['compression']} | {r['sci_ratio']:.2f} | {r['gdq_ratio']:.0f} | "
                         f"{r['file_bytes'] / 1e6:.0f} | {r['write_MB_per_s']:.0f} ({r['write_MB_per_s_best']:.0f}) | "
                         f"{r['read_MB_per_s']:.0f} | {r['lossless']} |")
    dv = result["data_volume_check"]
    lines += ["", f"Uncompressed SCI dataset: {dv['sci_stored_bytes']} B = {dv['sci_stored_GB']:.6f} GB; "
              f"`Detector(shape=({ny}, {nx})).data_volume({tuple(result['nmd'])}, 1)` = {dv['data_volume_GB']:.6f} GB "
              f"({'equal' if dv['equal'] else 'DIFFERENT'})."]
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--side", type=int, default=2048)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    ap.add_argument("--tmp", default=None)
    args = ap.parse_args()
    load0 = os.getloadavg()
    rate = lazuli_rate_image(args.side, args.side)
    cases = []
    for noise, effects in (("white", None), ("lazuli", "lazuli")):
        sci, gdq = simulate(rate, NMD, nramps=NRAMPS, seed=5, return_dq=True, progress=False, effects=effects,
                            **DETECTOR)
        print(f"{noise} ramp {sci.shape}: SCI {sci.nbytes / 1e6:.0f} MB, GROUPDQ {gdq.nbytes / 1e6:.0f} MB", flush=True)
        rows = []
        with tempfile.TemporaryDirectory(dir=args.tmp) as tmp:
            for comp in SETTINGS:
                r = measure(sci, gdq, comp, args.repeat, tmp)
                rows.append(r)
                print(f"{noise:7s} {r['compression']:15s} SCI ratio {r['sci_ratio']:5.2f}  GDQ ratio "
                      f"{r['gdq_ratio']:7.1f}  write {r['write_MB_per_s']:6.0f} MB/s  read {r['read_MB_per_s']:6.0f} MB/s  "
                      f"lossless {r['lossless']}", flush=True)
        cases.append({"noise": noise, "effects": effects, "rows": rows})
        del sci, gdq
    rows = cases[0]["rows"]
    plain = rows[0]
    vol = Detector(shape=(args.side, args.side)).data_volume(NMD, NRAMPS)
    check = {"sci_stored_bytes": plain["sci_stored_bytes"], "sci_stored_GB": plain["sci_stored_bytes"] / 1e9,
             "data_volume_GB": vol, "equal": bool(plain["sci_stored_bytes"] == round(vol * 1e9))}
    print(f"uncompressed SCI {check['sci_stored_GB']:.6f} GB vs data_volume {vol:.6f} GB: equal {check['equal']}")
    from slicersim.backends import opencl
    dev = opencl.get_device() if opencl.is_available() else None
    result = {"benchmark": "ramp_compression", "shape": [args.side, args.side], "nmd": list(NMD), "nramps": NRAMPS,
              "sci_bytes": plain["sci_stored_bytes"], "gdq_bytes": plain["gdq_stored_bytes"], "repeat": args.repeat,
              "rows": rows, "cases": cases,
              "data_volume_check": check,
              "machine": {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
                          "opencl_device": f"{dev.name.strip()} [{dev.platform.name.strip()}]" if dev else None,
                          "loadavg_before": load0, "loadavg_after": os.getloadavg()}}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "ramp_compression.json").write_text(json.dumps(result, indent=1))
    plot(result, out / "ramp_compression.png")
    (out / "ramp_compression.md").write_text(markdown(result))
    print(f"wrote {out / 'ramp_compression.json'}, .png, .md")


if __name__ == "__main__":
    main()
