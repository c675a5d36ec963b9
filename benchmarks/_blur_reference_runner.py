"""Run a public ``slicersim`` release (1.0.0 or 1.4.2) on a batch of ETC targets.

Research helper for the instrumental-blur / gain study (see ``blur_*`` notes).
It is executed with the interpreter of an isolated virtual environment that
holds *one* public release, never our own package::

    benchmarks/.refvenv/bin/python    benchmarks/_blur_reference_runner.py < targets.json > out_100.json
    benchmarks/.refvenv142/bin/python benchmarks/_blur_reference_runner.py < targets.json > out_142.json

(venvs: ``python3 -m venv benchmarks/.refvenv && benchmarks/.refvenv/bin/pip
install slicersim==1.0.0``, same with ``.refvenv142`` and ``==1.4.2``.)
With ``--example`` it prints the default input JSON and exits; an empty stdin
also means "use the default input".

Input JSON (stdin), every key optional::

    {
      "snr": 20, "per_resolution": true,           # requested SNR per resolution element
      "z_switch": 0.8,                             # field "auto": narrow if z < z_switch else wide
      "lbda_in": [3000, 20000, 10],                # np.arange(*lbda_in) input grid [Å]
      "blur_modes": ["native"],                    # see BLUR_MODES below
      "gain_check": true,                          # SNR(gain=2)/SNR(gain=1) at the solved readout
      "instrument": null,                          # null: the release's packaged lazuli_cbe.toml,
                                                   # or a path given as LazuliTarget(instrument=...)
      "targets": [
        {"id": "snia_z0.5", "kind": "snia", "z": 0.5,
         "sncosmo_source": "hsiao-subsampled", "peak_absmag": -19.3,
         "absmag_band": "bessellb", "magsys": "ab", "cosmology": "Planck18", "phase": 0.0,
         "lbda_range": [4000, 6800], "frame": "rest", "field": "auto"},
        {"id": "flat_B22", "kind": "flat", "mag": 22, "band": "bessellb",
         "lbda_range": [4000, 6800], "frame": "obs", "field": "both"}
      ]
    }

``field`` is "narrow", "wide", "auto" or "both" (one row per field; the row of
the "auto" choice has ``policy_field = true``).  Rest-frame ranges are turned
into observer-frame ranges here (``lbda_range * (1 + z)``) and always passed
with ``frame="obs"``: the point source built from arrays has no redshift.

Both releases are driven through the API they share::

    target = slicersim.LazuliTarget(lbda, flux, mag=mag, band=band[, instrument=...])
    target.change_spectrograph(field)             # always, also for "narrow"
    target.setup_to_snr(snr, per_resolution=True, lbda_range=[lo, hi], frame="obs")

API differences handled here:

* ``setup_to_snr`` returns the reached SNR per wavelength bin in 1.0.0 and per
  resolution element in 1.4.2 (``target.py:294``); we therefore recompute the
  band SNR at the solved readout with ``simulation.get_band_snr`` (per bin in
  both) and multiply by sqrt(dispersion_resolution) ourselves.
* 1.4.2 no longer selects the narrow field in ``VirtualLazuliTarget.__init__``
  (it infers the throughput column from the spaxel config when the TOML has
  ``name = "lazuli"``); calling ``change_spectrograph`` always makes both
  releases use the same field settings (spaxel scale, IFU optics count,
  throughput column).
* ``iotools.PACKAGE_PATH`` is ``slicersim/config`` in 1.0.0 and ``slicersim``
  in 1.4.2; the packaged config is located from ``slicersim.__file__``.

BLUR_MODES.  A mode sets the instrumental blur sigma along the slice (in cells; the release's
``Spectrograph.get_instrumental_psf`` is replaced on the instance) and, optionally, the detector
pixels per cell:

* ``native``        - the release's own blur formula (nothing replaced), 2 px per cell;
* ``none``          - no instrumental blur;
* ``v100``          - sqrt(dr**2 - 2**2)            (1.0.0 formula, 1.136 for dr = 2.3);
* ``v142``          - sqrt(dr**2 - 2**2) / 2 / 2    (1.4.2 formula, 0.284);
* ``physical_blur`` - sqrt(dr**2 - 2**2) / 2        (0.568, our blur), the release's 2 px per cell;
* ``physical``      - our physical conventions: the blur of ``physical_blur`` AND 1 detector
  pixel per cell (= ``physical_blur+1px``);
* a number          - that sigma in cells;
* ``<mode>+1px``    - any of the above with 1 detector pixel per cell (e.g. ``native+1px``).

Pixels per cell.  Both releases count read noise, dark and full well of 2 detector pixels per
cell (spaxel x native bin): ``Simulation._get_slicer_cube_`` calls
``detector.estimate_pixel_signal(cube, ..., npix_per_spaxel=self.spectrograph._ANAMORPHOSE)``
(= 2), which spreads the flux over that many pixels, computes signal, variance (read noise, dark,
Poisson) and the saturation test per pixel, then multiplies back.  Our physical default counts 1
(``slicersim.physics.conventions.detector_pixels_per_cell``).  The ``+1px`` modes patch exactly
that argument: ``Detector.estimate_pixel_signal`` is wrapped (class level, only while that row is
solved) so that an explicitly passed ``npix_per_spaxel`` becomes 1.  ``_ANAMORPHOSE`` itself is
not touched (1.4.2's blur, ``extra_pixels /= self._ANAMORPHOSE``, keeps its value), nor are the
spectrograph shape or calls that use the default ``npix_per_spaxel=1``.  In every mode the
wrapper records the values passed (``npix_per_spaxel_passed``) and used; without ``+1px`` it
passes the arguments through unchanged.

``_blur_sigma`` and ``_override_blur`` are also used by ``_sources_142_runner.py`` and
``_scenes_142_runner.py``, which apply the blur only: there ``"physical"`` means the blur part.

Output (stdout): one JSON document with the release, versions, config
provenance and one row per (target, field, blur mode): readout (n, m, d),
nramps, total exposure time, per-ramp times, SNR per bin and per resolution
element, the blur actually in effect, saturation count, wall time.  Everything
the library prints goes to stderr.
"""

import argparse
import contextlib
import hashlib
import json
import math
import platform
import sys
import time
import traceback
import warnings
from pathlib import Path

DEFAULT_INPUT = {
    "snr": 20.0,
    "per_resolution": True,
    "z_switch": 0.8,
    "lbda_in": [3000.0, 20000.0, 10.0],
    "blur_modes": ["native"],
    "gain_check": True,
    "instrument": None,
    "targets": (
        [{"id": f"snia_z{z}", "kind": "snia", "z": z, "sncosmo_source": "hsiao-subsampled",
          "peak_absmag": -19.3, "absmag_band": "bessellb", "magsys": "ab",
          "cosmology": "Planck18", "phase": 0.0,
          "lbda_range": [4000.0, 6800.0], "frame": "rest", "field": "both"}
         for z in (0.2, 0.5, 1.0, 1.5)]
        + [{"id": "flat_B22", "kind": "flat", "mag": 22.0, "band": "bessellb",
            "lbda_range": [4000.0, 6800.0], "frame": "obs", "field": "both"}]
    ),
}

EXPECTED_SIZE_PX = 2.0  # geometric slice-width image on the detector [px] (both releases)


def _log(*args):
    print("[blur-runner]", *args, file=sys.stderr, flush=True)


def _sha256(path):
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:
        return None


def _normalised_toml(path):
    """TOML text without trailing blanks, blank lines and the 1.4.2-only ``name`` key."""
    try:
        lines = Path(path).read_text().splitlines()
    except OSError:
        return None
    keep = []
    for line in lines:
        code = line.split("#", 1)[0].strip()
        if not code or code.replace(" ", "").startswith('name="'):
            continue
        keep.append(" ".join(code.split()))
    return keep


def _num(value):
    """JSON-friendly numbers (numpy scalars, non-finite -> None)."""
    try:
        import numpy as np
        if isinstance(value, np.ndarray):
            return [_num(v) for v in value.tolist()]
        if isinstance(value, np.generic):
            value = value.item()
    except ImportError:  # pragma: no cover
        pass
    if isinstance(value, (list, tuple)):
        return [_num(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _num(v) for k, v in value.items()}
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _versions():
    out = {"python": platform.python_version()}
    for name in ("slicersim", "numpy", "scipy", "astropy", "sncosmo", "pandas"):
        try:
            mod = __import__(name)
            out[name] = getattr(mod, "__version__", "unknown")
        except Exception as exc:  # pragma: no cover
            out[name] = f"unavailable ({exc.__class__.__name__})"
    return out


def _config_info(slicersim, instrument):
    packaged = Path(slicersim.__file__).resolve().parent / "config" / "lazuli_cbe.toml"
    shared = Path(__file__).resolve().parents[2] / "shared" / "reference" / "config" / "lazuli_cbe.toml"
    info = {"packaged_cbe": str(packaged), "packaged_cbe_sha256": _sha256(packaged),
            "instrument_kwarg": instrument}
    if shared.is_file():
        info["shared_cbe"] = str(shared)
        info["shared_cbe_sha256"] = _sha256(shared)
        info["packaged_equals_shared_bytes"] = info["packaged_cbe_sha256"] == info["shared_cbe_sha256"]
        info["packaged_equals_shared_ignoring_whitespace_and_name"] = (
            _normalised_toml(packaged) == _normalised_toml(shared))
    return info


# --------------------------------------------------------------------------- #
#  inputs                                                                     #
# --------------------------------------------------------------------------- #
def _target_flux(spec, lbda):
    import numpy as np
    kind = spec.get("kind", "flat")
    if kind == "snia":
        import sncosmo
        from astropy import cosmology as astro_cosmo
        cosmo = getattr(astro_cosmo, spec.get("cosmology", "Planck18"))
        model = sncosmo.Model(spec.get("sncosmo_source", "hsiao-subsampled"))
        model.set(z=float(spec["z"]), t0=0.0)
        model.set_source_peakabsmag(float(spec.get("peak_absmag", -19.3)),
                                    spec.get("absmag_band", "bessellb"),
                                    spec.get("magsys", "ab"), cosmo=cosmo)
        flux = np.asarray(model.flux(float(spec.get("phase", 0.0)), lbda), dtype=float)
        return flux, None, spec.get("absmag_band", "bessellb")  # absolute f_lambda, mag=None
    if kind == "flat":
        return np.ones_like(lbda), float(spec.get("mag", 22.0)), spec.get("band", "bessellb")
    raise ValueError(f"unknown target kind {kind!r} (snia or flat)")


def _fields(spec, z_switch):
    field = spec.get("field", "auto")
    z = spec.get("z")
    auto = "narrow" if (z is None or float(z) < z_switch) else "wide"
    if field == "both":
        return [("narrow", auto == "narrow"), ("wide", auto == "wide")]
    if field == "auto":
        return [(auto, True)]
    return [(field, field == auto)]


def _obs_range(spec):
    lo, hi = (float(v) for v in spec.get("lbda_range", [4000.0, 6800.0]))
    if spec.get("frame", "obs") == "rest" and spec.get("z") is not None:
        zp1 = 1.0 + float(spec["z"])
        return [lo * zp1, hi * zp1]
    return [lo, hi]


# --------------------------------------------------------------------------- #
#  blur                                                                       #
# --------------------------------------------------------------------------- #
def _blur_sigma(mode, dr):
    """Sigma [cells, along the slice] for a blur mode; None = leave the release alone."""
    width = math.sqrt(dr ** 2 - EXPECTED_SIZE_PX ** 2) if dr > EXPECTED_SIZE_PX else 0.0
    if mode == "native":
        return None
    if mode == "none":
        return 0.0
    if mode == "v100":
        return width
    if mode == "v142":
        return width / 2.0 / 2.0
    if mode in ("physical", "physical_blur"):
        return width / 2.0
    return float(mode)


def _parse_mode(mode):
    """(blur mode, detector pixels per cell or None = the release's own count)."""
    if mode == "physical":
        return "physical_blur", 1
    if isinstance(mode, str) and mode.endswith("+1px"):
        return mode[:-len("+1px")], 1
    return mode, None


def _override_blur(spectrograph, sigma_cells):
    """Replace ``get_instrumental_psf`` on this instance by a fixed sigma (cells)."""
    def get_instrumental_psf(spotsize=None, expected_size=2, in_spaxels=True):
        if sigma_cells is None or sigma_cells <= 0:
            return None
        return sigma_cells if in_spaxels else sigma_cells * spectrograph.spx_spatial_scale
    spectrograph.get_instrumental_psf = get_instrumental_psf


# --------------------------------------------------------------------------- #
#  detector pixels per cell                                                   #
# --------------------------------------------------------------------------- #
@contextlib.contextmanager
def _pixels_per_cell(slicersim, npix):
    """Wrap ``Detector.estimate_pixel_signal`` while the block runs.

    Records every explicitly passed ``npix_per_spaxel`` (the slicer cube passes
    ``spectrograph._ANAMORPHOSE``); with ``npix`` not None it is replaced by ``npix``.
    Nothing else changes.  Yields the record: {"passed": [...], "used": [...]}.
    """
    import inspect
    from slicersim import detector as detmod
    cls = detmod.Detector
    original = cls.__dict__["estimate_pixel_signal"]
    sig = inspect.signature(original)
    record = {"passed": [], "used": []}

    def estimate_pixel_signal(self, *args, **kwargs):
        bound = sig.bind(self, *args, **kwargs)
        if "npix_per_spaxel" in bound.arguments:
            passed = bound.arguments["npix_per_spaxel"]
            used = passed if npix is None else npix
            bound.arguments["npix_per_spaxel"] = used
            if passed not in record["passed"]:
                record["passed"].append(passed)
            if used not in record["used"]:
                record["used"].append(used)
        return original(*bound.args, **bound.kwargs)

    cls.estimate_pixel_signal = estimate_pixel_signal
    try:
        yield record
    finally:
        cls.estimate_pixel_signal = original


# --------------------------------------------------------------------------- #
#  solve                                                                      #
# --------------------------------------------------------------------------- #
def _solve_one(slicersim, lbda, flux, mag, band, field, obs_range, cfg, blur_mode, gain_check):
    import numpy as np
    kwargs = {"instrument": cfg["instrument"]} if cfg.get("instrument") else {}
    t0 = time.perf_counter()
    target = slicersim.LazuliTarget(lbda, flux, mag=mag, band=band, **kwargs)
    target.change_spectrograph(field)
    sim = target.simulation
    sp = sim.spectrograph
    dr = float(sp.dispersion_resolution)
    native_sigma = sp.get_instrumental_psf(in_spaxels=True)
    blur_part, _ = _parse_mode(blur_mode)
    sigma = _blur_sigma(blur_part, dr)
    if sigma is not None:
        _override_blur(sp, sigma)
    t1 = time.perf_counter()
    _, reached_raw = target.setup_to_snr(cfg["snr"], per_resolution=cfg["per_resolution"],
                                         lbda_range=list(obs_range), frame="obs")
    t2 = time.perf_counter()

    readout = target.get_readout_config()
    times = sim.get_times()
    snr_bin = float(sim.get_band_snr(list(obs_range), frame="obs"))
    sp_after = sim.spectrograph
    row = {
        "nmd": [int(v) for v in readout["nmd"]],
        "nramps": int(readout["nramps"]),
        "exposure_time": float(target.get_exposure_time()),
        "exposure_time_per_ramp": float(times["exposure_time"]),
        "integration_time_per_ramp": float(times["integration_time"]),
        "snr_per_bin": snr_bin,
        "snr_per_resolution": snr_bin * math.sqrt(dr),
        "setup_to_snr_returned": _num(reached_raw),
        "setup_to_snr_returned_is": ("per_bin" if slicersim.__version__.startswith("1.0")
                                     else "per_resolution"),
        "dispersion_resolution": dr,
        "blur_mode": blur_mode,
        "native_inst_sigma_cells": _num(native_sigma),
        "inst_sigma_cells_used": _num(sp_after.get_instrumental_psf(in_spaxels=True)),
        "effective_scatter_cells_axes(-2,-1)": _num(sp_after.get_additonal_spatial_scatter(in_spaxels=True)),
        "spectrograph_replaced_during_solve": sp_after is not sp,
        "spectrograph_anamorphose": _num(getattr(sp_after, "_ANAMORPHOSE", None)),
        "spx_shape": [int(v) for v in sp_after.spx_shape],
        "spx_scale_arcsec": _num(np.atleast_1d(sp_after.spx_spatial_scale)[0]),
        "nsaturated_detpx": _num(getattr(sim.detector, "nsaturated_detpx", None)),
        "pointsource_position": _num(getattr(sim.scene.pointsource, "position", None)),
        "construct_s": t1 - t0,
        "setup_to_snr_s": t2 - t1,
    }
    if gain_check:
        g0 = float(sim.detector.gain)
        sim.update(gain=2.0 * g0)
        snr_g2 = float(sim.get_band_snr(list(obs_range), frame="obs"))
        sim.update(gain=g0)
        row["gain_check"] = {"gain0": g0, "snr_bin_gain0": snr_bin, "snr_bin_2gain0": snr_g2,
                             "ratio": snr_g2 / snr_bin if snr_bin else None}
    return row


def run(cfg):
    import numpy as np
    with contextlib.redirect_stdout(sys.stderr):
        import slicersim
    lbda = np.arange(*[float(v) for v in cfg["lbda_in"]])
    rows = []
    for spec in cfg["targets"]:
        try:
            flux, mag, band = _target_flux(spec, lbda)
        except Exception as exc:
            rows.append({"id": spec.get("id"), "ok": False,
                         "error": f"input: {exc.__class__.__name__}: {exc}"})
            continue
        obs_range = _obs_range(spec)
        flux_sha = hashlib.sha256(np.ascontiguousarray(flux, dtype="<f8").tobytes()).hexdigest()[:16]
        for field, policy in _fields(spec, float(cfg["z_switch"])):
            for blur_mode in cfg["blur_modes"]:
                row = {"id": spec.get("id"), "kind": spec.get("kind"), "z": spec.get("z"),
                       "mag": mag, "band": band, "field": field, "policy_field": policy,
                       "lbda_range": spec.get("lbda_range"), "frame": spec.get("frame", "obs"),
                       "lbda_range_obs": obs_range, "input_flux_sha256_16": flux_sha}
                try:
                    with contextlib.redirect_stdout(sys.stderr), \
                            warnings.catch_warnings(record=True) as wlist:
                        warnings.simplefilter("always")
                        warnings.simplefilter("ignore", ResourceWarning)
                        _, npix = _parse_mode(blur_mode)
                        with _pixels_per_cell(slicersim, npix) as npix_record:
                            row.update(_solve_one(slicersim, lbda, flux, mag, band, field, obs_range,
                                                  cfg, blur_mode, cfg["gain_check"]))
                        row["pixels_per_cell_override"] = npix
                        row["npix_per_spaxel_passed"] = npix_record["passed"]
                        row["npix_per_spaxel_used"] = npix_record["used"]
                    row["ok"] = True
                    row["warnings"] = sorted({f"{w.category.__name__}: {w.message}"[:160]
                                              for w in wlist})
                except Exception as exc:
                    row.update({"ok": False, "error": f"{exc.__class__.__name__}: {exc}",
                                "traceback": traceback.format_exc(limit=6)})
                rows.append(_num(row))
                _log(f"{slicersim.__version__} {row['id']:>10s} {field:6s} blur={str(blur_mode):8s}",
                     (f"{tuple(row['nmd'])}x{row['nramps']} T={row['exposure_time']:.1f}s "
                      f"SNR/res={row['snr_per_resolution']:.2f}" if row.get("ok") else row["error"]))
    return {
        "runner": "benchmarks/_blur_reference_runner.py",
        "slicersim_version": slicersim.__version__,
        "module_file": str(Path(slicersim.__file__).resolve()),
        "versions": _versions(),
        "config": _config_info(slicersim, cfg.get("instrument")),
        "input": {k: v for k, v in cfg.items() if k != "targets"},
        "targets_input": cfg["targets"],
        "api": ("LazuliTarget(lbda, flux, mag, band) ; change_spectrograph(field) ; "
                "setup_to_snr(snr, per_resolution=True, lbda_range=obs_range, frame='obs')"),
        "rows": rows,
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--example", action="store_true", help="print the default input JSON and exit")
    args = parser.parse_args(argv)
    if args.example:
        print(json.dumps(DEFAULT_INPUT, indent=1))
        return 0
    text = "" if sys.stdin is None or sys.stdin.isatty() else sys.stdin.read()
    cfg = dict(DEFAULT_INPUT)
    if text.strip():
        cfg.update(json.loads(text))
    out = run(cfg)
    json.dump(out, sys.stdout, indent=1)
    sys.stdout.write("\n")
    return 0 if all(r.get("ok") for r in out["rows"]) else 1


if __name__ == "__main__":
    sys.exit(main())
