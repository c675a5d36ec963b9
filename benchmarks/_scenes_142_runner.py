"""Run inside benchmarks/.refvenv142 (slicersim==1.4.2): the host / galaxy cases of scenes_vs_142.py.

Usage: python _scenes_142_runner.py INPUT.json OUTPUT.json OUTPUT.npz
INPUT: {"redshifts": [...], "host": "sersic:bb-5000", "band": "bessellr", "powerlaw": [alpha, mag],
        "apertures": [...], "snr": 5, "snr_band": [lo, hi], "nmd": [n, m, d],
        "blur_modes": ["native", "physical"], "ngc": {"name": "ngc0628", "redshift": 0.05,
        "apertures": ["1-arcsec"]}, "image_lbda": 8000, "etc_blur_modes": ["native"]}

Per redshift z and blur mode (``_blur_reference_runner.py``; "physical" is our σ_x = 0.568 cells):

* host: ``LazuliPowerLaw(alpha, mag, band, redshift=z, host={"refmodel": host, "band": band})``
  (1.4.2's defaults r_kpc=5, n=2, ellip=0.3, theta=−30, magabs=−21), narrow field, readout
  ``nmd`` × 1; per bin: the host light in the 1″ aperture (``get_spectrum(of_host=True)``,
  flambda and ADU), the host cube summed over the field (``get_scene_cubes``, flambda and ADU),
  the host's total spectrum, the host cube before the PSF summed over the field, the host image
  (fraction of its flux per spaxel) at ``image_lbda``, the sum of the PSF kernel, and the point
  source by ``get_spectrum(method="aperture")`` with the default aperture;
* galaxy: ``LazuliGalaxy(z, model=host, aperture=a, band=band)`` per aperture ``a``:
  ``get_spectrum`` in flambda and ADU at ``nmd`` × 1, then ``setup_to_snr(snr, lbda_range=
  snr_band, frame="rest")`` (readout, exposure time, reached SNR per resolution element);
* NGC (native blur only): ``GalaxySpatialModel.project_to`` on the narrow grid and
  ``LazuliGalaxy(z, model=name, aperture=a)`` as the galaxies above.

The ETC walk runs for the blur modes of ``etc_blur_modes`` only (spectra and the SNR at ``nmd``
for every mode).

band="bessellr": 1.4.2's default "sdssr" needs a download.  Per-bin arrays go to OUTPUT.npz.
"""
import json
import sys
import time
import warnings

import numpy as np

warnings.filterwarnings("ignore")


def _narrow(target, mode, blur):
    target.change_spectrograph("narrow")
    sim = target.simulation
    sigma = blur["sigma"](mode, float(sim.spectrograph.dispersion_resolution))
    if sigma is not None:
        blur["override"](sim.spectrograph, sigma)
    return sim


def host_case(slicersim, spec, z, mode, blur, arrays):
    alpha, mag = spec["powerlaw"]
    target = slicersim.LazuliPowerLaw(alpha=alpha, mag=mag, band=spec["band"], redshift=z,
                                      host={"refmodel": spec["host"], "band": spec["band"]})
    sim = _narrow(target, mode, blur)
    sim.update(nmd=tuple(spec["nmd"]), nramps=1)
    lbda = np.asarray(sim.spectrograph.lbda, float)
    key = f"host_{mode}_z{z}"
    arrays[key + "_lbda"] = lbda
    _, s, _ = target.get_spectrum(unit="adu", incl_error=False, of_host=True)
    to_flambda = np.asarray(sim.convert_units(units_in="adu", units_out="flambda"), float)
    arrays[key + "_aperture_adu"], arrays[key + "_aperture_flambda"] = np.asarray(s, float), s * to_flambda
    # the point source by aperture photometry with the target's default aperture (1.4.2: "1-arcsec")
    _, s, v = target.get_spectrum(unit="adu", incl_error=False, method="aperture")
    arrays[key + "_ps_aperture_adu"], arrays[key + "_ps_aperture_var"] = np.asarray(s, float), np.asarray(v, float)
    for unit in ("flambda", "adu"):
        cubes = sim.get_scene_cubes(unit=unit)
        arrays[f"{key}_cube_{unit}"] = np.asarray(cubes["host_cube"], float).sum(axis=(1, 2))
    host = sim.scene.host
    total = np.asarray(host.get_spectrum(lbda)[1], float)
    grid = np.asarray(sim._get_host_cube_(lbda), float)
    arrays[key + "_total"], arrays[key + "_grid"] = total, grid.sum(axis=(1, 2))
    i = int(np.argmin(np.abs(lbda - spec["image_lbda"])))
    arrays[key + "_image"] = grid[i] / total[i]            # fraction of the host flux per spaxel
    arrays[key + "_psf_sum"] = np.asarray(sim.spectrograph.get_spatial_psf(position=(-0.5, -0.5)), float).sum(axis=(1, 2))
    pos, radius, optimal = sim.get_aperture()
    return {"z": z, "blur_mode": mode, "host_redshift": float(host.meta["redshift"]),
            "aperture": sim.extraction.get("aperture"), "aperture_radius_spx": float(radius),
            "aperture_position": [float(v) for v in pos],
            "exposure_time": float(target.get_exposure_time()),
            "shape": list(sim.spectrograph.spx_shape), "spatial_scale": float(sim.spectrograph.spx_spatial_scale),
            "instrumental_blur_cells": blur_in_effect(sim)}


def blur_in_effect(sim):
    try:
        v = sim.spectrograph.get_instrumental_psf(in_spaxels=True)
        return None if v is None else float(np.ravel(v)[0])
    except Exception:  # noqa: BLE001
        return None


def galaxy_case(slicersim, spec, z, aperture, mode, blur, arrays, model=None, etc=True):
    model = model or spec["host"]
    target = slicersim.LazuliGalaxy(z, model=model, aperture=aperture, band=spec["band"])
    sim = _narrow(target, mode, blur)
    sim.update(nmd=tuple(spec["nmd"]), nramps=1)
    key = f"gal_{mode}_{model}_z{z}_{aperture}"
    row = {"z": z, "aperture": aperture, "blur_mode": mode, "model": model}
    try:
        pos, radius, optimal = sim.get_aperture()
        row.update(aperture_radius_spx=float(radius), optimal=bool(optimal))
        arrays[key + "_lbda"] = np.asarray(sim.spectrograph.lbda, float)
        _, s, v = target.get_spectrum(unit="adu", incl_error=False)
        to_flambda = np.asarray(sim.convert_units(units_in="adu", units_out="flambda"), float)
        arrays[key + "_adu"], arrays[key + "_adu_var"] = np.asarray(s, float), np.asarray(v, float)
        arrays[key + "_flambda"] = s * to_flambda
        arrays[key + "_total"] = np.asarray(sim.scene.host.get_spectrum(sim.spectrograph.lbda)[1], float)
        row["snr_at_nmd"] = float(target.get_band_snr(spec["snr_band"], frame="rest", per_resolution=True))
        if etc:
            t0 = time.perf_counter()
            config, reached = target.setup_to_snr(spec["snr"], lbda_range=spec["snr_band"], frame="rest")
            row.update(etc_s=time.perf_counter() - t0, nmd=[int(v) for v in config["nmd"]],
                       nramps=int(config["nramps"]), snr=float(reached),
                       exposure_time=float(target.get_exposure_time()))
    except Exception as exc:  # noqa: BLE001
        row["error"] = f"{type(exc).__name__}: {str(exc).splitlines()[0][:200] if str(exc) else ''}"
    return row


def ngc_case(slicersim, spec, blur, arrays):
    from slicersim.scene.sources.galaxy import GalaxySpatialModel
    from astropy.cosmology import Planck18
    ngc = spec["ngc"]
    name, z = ngc["name"], ngc["redshift"]
    gal = GalaxySpatialModel.from_name(name)
    shape, scale = (116, 58), 0.04
    arrays["ngc_image"] = gal.project_to(z, shape=shape, pixel_scale=scale)
    ratio = gal.get_pixel_scale(z, Planck18) / scale
    out = {"name": name, "redshift": z, "galaxy_redshift": float(gal.redshift),
           "image_pixel_scale": float(gal.pixel_scale), "pixel_scale_at_z": float(gal.get_pixel_scale(z, Planck18)),
           "image_shape": list(gal.image.shape), "center": [float(v) for v in gal.center],
           "subsamples_per_axis": int(np.ceil(8 * ratio)), "galaxies": []}
    for aperture in ngc.get("apertures", ["1-arcsec"]):
        out["galaxies"].append(galaxy_case(slicersim, spec, z, aperture, "native", blur, arrays, model=name))
    return out


def main():
    inp, out_json, out_npz = sys.argv[1:4]
    with open(inp) as fh:
        spec = json.load(fh)
    import slicersim
    from _blur_reference_runner import _blur_sigma, _override_blur     # same folder (sys.path[0])
    blur = {"sigma": _blur_sigma, "override": _override_blur}
    res = {"version": slicersim.__version__, "host": [], "galaxy": [], "timings": {}}
    arrays = {}
    t0 = time.perf_counter()
    for mode in spec["blur_modes"]:
        for z in spec["redshifts"]:
            res["host"].append(host_case(slicersim, spec, z, mode, blur, arrays))
    res["timings"]["host_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    for mode in spec["blur_modes"]:
        for z in spec["redshifts"]:
            for aperture in spec["apertures"]:
                res["galaxy"].append(galaxy_case(slicersim, spec, z, aperture, mode, blur, arrays,
                                                 etc=mode in spec.get("etc_blur_modes", ["native"])))
    res["timings"]["galaxy_s"] = time.perf_counter() - t0
    if spec.get("ngc"):
        t0 = time.perf_counter()
        try:
            res["ngc"] = ngc_case(slicersim, spec, blur, arrays)
        except Exception as exc:  # noqa: BLE001
            res["ngc"] = {"error": f"{type(exc).__name__}: {exc}"}
        res["timings"]["ngc_s"] = time.perf_counter() - t0
    np.savez(out_npz, **arrays)
    with open(out_json, "w") as fh:
        json.dump(res, fh, default=lambda o: o.item() if hasattr(o, "item") else str(o))


if __name__ == "__main__":
    main()
