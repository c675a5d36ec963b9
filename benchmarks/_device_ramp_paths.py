"""Ramp kernel vs NumPy twin, path by path, on the selected OpenCL device (device_suite.sh step
``ramp_paths``; run 7 on the H200).  Prints, in this order (each part flushed, so a run cut short still
tells something):

1. the extended device self-check's verdict (random streams + ramp blocks, selfcheck.py);
2. per rate class (dark 0.005, 0.1, 1, 30, 1e3, 1e4, 1e5 e-/s; the last two saturate), one 4096-px
   detector row at rows 0 and 4000 of a 4096² detector, MACC(64,8,0), the benchmark's detector
   (ramp_throughput.DETECTOR): differing SCI values / pixels, max |diff| [ADU], GROUPDQ differences,
   the first differing (group, column) with both values; then the same with gauss_min_mean = 1e3
   (the Gaussian path) at row 4000;
3. the benchmark's own call (reduce_speed.py: Lazuli-like 4096² image, simulate → HDF5) and a few of
   its rows (0, the bright spots', 2047, 4000, 4095) against the twin of those rows.

Run with SLICERSIM_TRUST_DEVICE=1 (the comparisons must run on the device even if it fails the check).
"""
import os
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from slicersim.backends import opencl, selfcheck  # noqa: E402
from slicersim.backends import ramp as rb  # noqa: E402
from slicersim.physics.ramp import RampParameters, frame_mean_charge  # noqa: E402

T0 = time.time()
DETECTOR = dict(dark=2.8e-3, thermal_dark=1.2e-3, roic_glow=3e-3, tframe=2.83, ron=12.0, gain=1.0)  # ramp_throughput's
NX, NMD, SEED = 4096, (64, 8, 0), 11
CLASSES = (0.005, 0.1, 1.0, 30.0, 1e3, 1e4, 1e5)
only = set(sys.argv[1:])            # parts to run (default all): selfcheck classes file


def say(*a):
    print(f"[{time.time() - T0:6.1f} s]", *a, flush=True)


def params(**kw):
    det = {k: DETECTOR[k] for k in ("tframe", "ron", "gain")}
    return RampParameters(nmd=NMD, dark=DETECTOR["dark"], thermal_dark=DETECTOR["thermal_dark"],
                          roic_glow=DETECTOR["roic_glow"], **det, **kw)


def mu_of(rate):
    return frame_mean_charge(rate, DETECTOR["dark"], DETECTOR["thermal_dark"], DETECTOR["roic_glow"],
                             DETECTOR["tframe"])


def compare(label, got, want, cols_of=None):
    """Print differences of (SCI, GROUPDQ) (n, npix) blocks, per class of columns if given."""
    (sc, qc), (sn, qn) = got, want
    groups = cols_of or {"all": np.arange(sn.shape[1])}
    for name, cols in groups.items():
        a, b = sc[:, cols].astype(np.int64), sn[:, cols].astype(np.int64)
        diff = a != b
        dq = int(np.count_nonzero(qc[:, cols] != qn[:, cols]))
        line = (f"{label} {name:>8}: SCI differ {int(diff.sum())}/{diff.size} values, "
                f"{int(diff.any(axis=0).sum())}/{diff.shape[1]} px, max|diff| "
                f"{int(np.abs(a - b).max()) if diff.any() else 0} ADU; GROUPDQ differ {dq}")
        if diff.any():
            g, c = np.argwhere(diff)[0]
            first_groups = np.flatnonzero(diff.any(axis=1))[:4].tolist()
            line += (f"; first (group {g}, col {int(cols[c])}): gpu {int(a[g, c])} twin {int(b[g, c])}"
                     f" (twin g0 {int(b[0, c])}, g-1 {int(b[-1, c])}); groups with diffs {first_groups}…")
        print("   ", line, flush=True)


if not only or "selfcheck" in only:
    t = time.time()
    ok, msg = selfcheck.device_selfcheck()
    say(f"extended self-check ({time.time() - t:.2f} s): {'PASS' if ok else 'FAIL'}: {msg}")
    rc, rn = selfcheck._ramp_blocks(rb.simulate_block_opencl), selfcheck._ramp_blocks(rb.simulate_block_numpy)
    for name, (mu, *_), got, want in zip("AB", selfcheck._ramp_cases(), rc, rn):
        compare(f"self-check block {name} mu/frame", got, want,
                {f"{c:g}": np.flatnonzero(mu == c) for c in np.unique(mu)})

if not only or "classes" in only:
    say("device:", opencl.get_device().name.strip(), "| rate classes [e-/s]", CLASSES, "| MACC", NMD)
    ncls = len(CLASSES)
    rate = np.array(CLASSES)[np.arange(NX) % ncls]
    cols_of = {f"{c:g}": np.flatnonzero(rate == c) for c in CLASSES}
    mu, dead = mu_of(rate), np.zeros(NX, bool)
    for label, row, kw in (("row 0   ", 0, {}), ("row 4000", 4000, {}),
                           ("row 4000 gauss>=1e3/frame", 4000, {"gauss_min_mean": 1e3})):
        p = params(**kw)
        t = time.time()
        got = rb.simulate_block_opencl(mu, dead, row * NX, 0, SEED, p)
        t1 = time.time()
        want = rb.simulate_block_numpy(mu, dead, row * NX, 0, SEED, p)
        say(f"{label}: kernel {t1 - t:.2f} s, twin {time.time() - t1:.2f} s")
        compare(label, got, want, cols_of)
    # one block of many rows at once (the product's block size): rows 3968-4095, column classes as above
    rows = 128
    p = params()
    big = np.tile(mu, rows)
    got = rb.simulate_block_opencl(big, np.zeros(big.size, bool), (4096 - rows) * NX, 0, SEED, p)
    for r in (0, rows - 1):
        want = rb.simulate_block_numpy(mu, dead, (4096 - rows + r) * NX, 0, SEED, p)
        compare(f"block of {rows} rows, row {4096 - rows + r}", (got[0][:, r * NX:(r + 1) * NX],
                got[1][:, r * NX:(r + 1) * NX]), want, cols_of)
    say("classes done")

if not only or "file" in only:
    import h5py
    from ramp_throughput import DETECTOR as DET, lazuli_rate_image
    assert DET == DETECTOR, DET
    from slicersim.products.ramps import simulate
    side = int(os.environ.get("RAMP_PATHS_SIDE", 4096))     # smaller only for a local dry run
    rate = lazuli_rate_image(side, side)
    bright_rows = sorted(set(np.nonzero(rate >= 1e3)[0].tolist()))[:2]
    path = os.path.join(tempfile.mkdtemp(), "ramp.h5")
    t = time.time()
    simulate(rate, NMD, seed=SEED, out=path, progress=False, **DETECTOR)
    ys = [0, *bright_rows, side // 2 - 1, side * 4000 // 4096, side - 1]
    say(f"benchmark simulate {side}² → HDF5 {time.time() - t:.1f} s; rows compared: {ys} (bright: {bright_rows})")
    p = params()
    mu = mu_of(rate)
    with h5py.File(path, "r") as fh:
        for y in ys:
            got = (fh["SCI"][0, :, y, :], fh["GROUPDQ"][0, :, y, :])
            want = rb.simulate_block_numpy(mu[y], np.zeros(side, bool), y * side, 0, SEED, p)
            lit = {"dark(<1)": np.flatnonzero(rate[y] < 1.0), "lit(>=1)": np.flatnonzero(rate[y] >= 1.0)}
            compare(f"file row {y:4d}", got, want, {k: v for k, v in lit.items() if v.size})
    os.remove(path)
    say("file done")
