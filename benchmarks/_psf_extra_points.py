"""Extra points of ``psf_speed_accuracy.py``: convolution of an extended host with the PSF.

A Sersic host (n = 1, r_eff = 0.3″, q = 0.6, PA 30°) of unit flux per plane is
convolved with the per-λ Airy PSF kernels (jitter and slice blur included,
odd kernel of ±8σ_max cells) by direct and FFT convolution, on OpenCL and with
SciPy, over all 525 λ planes of the Lazuli narrow field.  Errors are against a
float64 ``scipy.ndimage.convolve`` oracle (zero outside the field): max over λ
of max|out − oracle| / peak(oracle), and the flux error relative to the host flux.
"""
import numpy as np


def points(ctx):
    from scipy import ndimage

    from slicersim.backends.convolution import convolve_cube
    from slicersim.backends.psf import psf_cube
    from slicersim.sources.extended import SersicProfile

    lbda, shape, kw, repeat = ctx["lbda"], ctx["shape"], dict(ctx["kwargs"]), ctx["repeat"]
    timed = ctx["timed"]
    host = SersicProfile(1.0, 0.3, 0.6, 30.0).cell_fractions(shape, kw["spatial_scale"])
    cube = np.broadcast_to(host, (lbda.size,) + host.shape).copy()
    out = []
    for k in (11, 21, 31):
        kw_k = {key: val for key, val in kw.items() if key != "oversampling"}
        kernels = psf_cube(lbda, (k, k), (0.0, 0.0), "airy", oversampling="auto", **kw_k)
        oracle = np.stack([ndimage.convolve(cube[i], kernels[i][::-1, ::-1], mode="constant")
                           for i in range(lbda.size)])
        peak = oracle.reshape(lbda.size, -1).max(axis=1)
        for method in ("direct", "fft"):
            for backend in ("opencl", "numpy"):
                try:
                    res, wall, _, cpu = timed(lambda: convolve_cube(cube, kernels, method=method,
                                                                    backend=backend), repeat)
                except Exception as exc:  # e.g. no OpenCL device
                    print(f"host {method}/{backend} k={k}: skipped ({exc})")
                    continue
                err = np.max(np.abs(res - oracle).reshape(lbda.size, -1).max(axis=1) / peak)
                flux = np.max(np.abs(res.sum(axis=(1, 2)) - oracle.sum(axis=(1, 2))) / host.sum())
                out.append({"method": f"host-conv-{method}-{backend}", "setting": f"k={k}",
                            "seconds": wall, "cpu_seconds": cpu, "max_err_rel_peak": float(err),
                            "flux_err": float(flux)})
    return out
