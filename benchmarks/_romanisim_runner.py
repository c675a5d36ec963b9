"""Runner of ``benchmarks/ramp_vs_romanisim.py`` in romanisim's own venv (``benchmarks/.venv-romanisim``).

    python _romanisim_runner.py IN.json OUT.json

IN.json: ``rate_npy`` (rate image [e-/s], float64 (ny, nx)), ``nmd`` (n, m, d), ``tframe`` [s],
``ron`` [e-], ``gain``, ``seed``, ``cr_flux`` [cm⁻² s⁻¹], ``pixel_pitch`` / ``pixel_depth`` [µm],
``repeat``.  It simulates the ramp with ``romanisim.l1.make_l1`` (read pattern of the MACC: the m
reads of group g are reads g(m+d)+1 … g(m+d)+m; cosmic rays on with the same flux, pixel size,
depth and an area equal to the image's; IPC on, romanisim's default kernel), after drawing the
total counts as romanisim's image step does (one Poisson per pixel of rate × time of the last
read).  OUT.json: versions, process CPU seconds (all threads) and wall seconds of each repeat,
split into the counts draw and ``make_l1``, and the mean of the last resultant."""
import json
import sys
import time

import galsim
import numpy as np
import romanisim
from romanisim import l1


def main(spec_path, out_path):
    spec = json.loads(open(spec_path).read())
    rate = np.load(spec["rate_npy"])
    n, m, d = spec["nmd"]
    pattern = [list(range(g * (m + d) + 1, g * (m + d) + m + 1)) for g in range(n)]
    l1.parameters.read_time = float(spec["tframe"])        # read_pattern_to_tij and the CR time step
    t_last = pattern[-1][-1] * spec["tframe"]
    pitch_cm = spec["pixel_pitch"] * 1e-4
    crparam = {"flux": spec["cr_flux"], "area": rate.size * pitch_cm**2, "pixel_size": spec["pixel_pitch"],
               "pixel_depth": spec["pixel_depth"]}
    runs = []
    for r in range(spec["repeat"]):
        gen = np.random.default_rng(spec["seed"] + r)
        c0, w0 = time.process_time(), time.perf_counter()
        counts = galsim.Image(gen.poisson(rate * t_last).astype("f8"))
        c1, w1 = time.process_time(), time.perf_counter()
        res, dq = l1.make_l1(counts, pattern, read_noise=spec["ron"] / spec["gain"], gain=spec["gain"],
                             rng=galsim.UniformDeviate(spec["seed"] + r), crparam=crparam, saturation=65535)
        c2, w2 = time.process_time(), time.perf_counter()
        runs.append({"counts_cpu_s": c1 - c0, "make_l1_cpu_s": c2 - c1, "cpu_s": c2 - c0, "wall_s": w2 - w0,
                     "last_resultant_mean": float(np.mean(res[-1])), "cr_flagged": int(np.count_nonzero(dq))})
    out = {"romanisim": romanisim.__version__, "galsim": galsim.__version__, "numpy": np.__version__,
           "shape": list(rate.shape), "reads": n * (m + d) - d, "resultants": n, "runs": runs,
           "ipc_kernel": l1.ipc.ipc_kernel.tolist()}
    open(out_path, "w").write(json.dumps(out, indent=1))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
