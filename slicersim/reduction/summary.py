"""Per-target summary of a campaign against its truth: band flux / input, pulls, χ², SNR against the ETC.

Each target's reduced spectrum (``spectra/<field>/FLUX``, VAR and, from the forward extraction,
COVARIANCE [e-/s per bin] on LBDA_EDGES) is compared with its truth (``truth/target``:
:mod:`slicersim.io.target_truth`), the simulation's expected rate [e-/s per native bin], both
taken as piecewise-constant densities in λ:

* band flux F = Σ_b w_b F̂_b with w_b the fraction of bin b inside the band [lo, hi] (observer
  frame: the campaign's ``observation.lbda_range`` × (1 + z) when its frame is "rest", default
  4000–6800 Å rest); σ_F² = wᵀ C w (C the covariance, else diag VAR); the input's T the same
  integral of the truth rate; ``band_flux_ratio`` = F / T, its error σ_F / T, ``pull`` = (F − T) / σ_F;
* ``chi2`` = rᵀ C⁻¹ r / N over the N bins touching the band, r = F̂_b − T_b (T_b the truth in bin b):
  the spectrum against its input, per degree of freedom (1 for errors that are right);
* ``snr_reported`` = F / σ_F; ``snr_measured`` = F / (σ_F √chi2): the band SNR with the noise the
  residuals show; ``snr_etc`` = T / √(Σ_j w_j² V_j), V_j the ETC variance of the truth's native bins
  for the readout used: all three band-integrated SNRs, comparable whatever the binning.

A campaign that was not reduced is summarised from its simulated extracted spectra
(``spectrum.h5``: noisy vs signal [ADU], flag ``simulated``) when it has them.
"""
from __future__ import annotations

import json
import os

import numpy as np

from slicersim.errors import DatasetError, RampFileError

__all__ = ["band_overlap", "rebin", "compare_band", "summarize", "redshift_bins", "COLUMN_UNITS",
           "DEFAULT_BAND", "CHI2_FLAG", "PULL_FLAG"]

#: the default ETC band [Å, rest frame]
DEFAULT_BAND = (4000.0, 6800.0, "rest")
#: χ²/dof above which a row is flagged
CHI2_FLAG = 3.0
#: |pull| above which a row is flagged
PULL_FLAG = 5.0
#: units and descriptions of the summary's columns
COLUMN_UNITS = {
    "target_id": ("", "target"), "status": ("", "reduction status (or the campaign's)"),
    "redshift": ("", "redshift"), "phase": ("d", "rest-frame days from B-band peak"),
    "peak_absmag": ("mag", "peak absolute magnitude in the population's band"),
    "field": ("", "field observed"), "band_lo": ("Angstrom", "band start, observer frame"),
    "band_hi": ("Angstrom", "band end, observer frame"),
    "band_flux_ratio": ("", "reduced band flux / input band flux"),
    "band_flux_ratio_error": ("", "1-sigma error of band_flux_ratio"),
    "pull": ("", "(band_flux_ratio - 1) / band_flux_ratio_error"),
    "chi2": ("", "chi2 per bin of the spectrum against the input, in the band"),
    "chi2_fit": ("", "chi2 per dof of the forward fit on the pixels"),
    "noise_scale": ("", "noise level of the fitted pixels in units of the ramp fit's variance (1: as the fit says)"),
    "snr_reported": ("", "band flux / its reported error"),
    "snr_measured": ("", "band flux / (reported error x sqrt(chi2))"),
    "snr_etc": ("", "the ETC's band SNR for the readout used"),
    "position_error": ("arcsec", "fitted minus true position"),
    "flags": ("", "comma-separated warnings (not-reduced, rates-only, no-truth, no-spectrum, simulated, unreadable, "
                  "partial-band, chi2, pull, fit-not-converged, failed)"),
    "t_simulate": ("s", "wall time of the target's simulation task"),
    "t_reduce": ("s", "wall time of the target's reduction task"),
}


def band_overlap(edges, lo, hi):
    """Fraction of each bin inside [lo, hi].

    Parameters
    ----------
    edges : (n + 1,) array
        Increasing bin edges [Å].
    lo, hi : float
        Band [Å].

    Returns
    -------
    (n,) array in [0, 1].
    """
    edges = np.asarray(edges, float)
    inside = np.clip(np.minimum(edges[1:], hi) - np.maximum(edges[:-1], lo), 0.0, None)
    return inside / np.diff(edges)


def rebin(src_edges, values, dst_edges):
    """Integrate ``values`` per bin of ``src_edges`` (a piecewise-constant density) into the bins
    ``dst_edges``: (m,) per destination bin; NaN values count as 0.

    Parameters
    ----------
    src_edges : (n + 1,) array [Å];  values : (n,) array (per source bin, e.g. e-/s)
    dst_edges : (m + 1,) array [Å]

    Returns
    -------
    (m,) array, in the unit of ``values`` per destination bin.
    """
    src_edges, dst_edges = np.asarray(src_edges, float), np.asarray(dst_edges, float)
    v = np.nan_to_num(np.asarray(values, float))
    cum = np.concatenate([[0.0], np.cumsum(v)])
    at = np.interp(dst_edges, src_edges, cum)           # integral up to each destination edge
    return np.diff(at)


def compare_band(edges, flux, variance, truth, band, covariance=None):
    """The band comparison of one spectrum with its truth (module docstring).

    Parameters
    ----------
    edges : (n + 1,) array [Å];  flux, variance : (n,) arrays [e-/s per bin, (e-/s)²]
    truth : TargetTruth (native bins, ``rate`` [e-/s per bin], ``etc_variance``)
    band : (lo, hi) [Å, observer frame]
    covariance : (n, n) array or None

    Returns
    -------
    dict: band_flux_ratio, band_flux_ratio_error, pull, chi2, snr_reported, snr_measured, snr_etc,
    partial (the band not entirely covered by finite bins).
    """
    lo, hi = band
    edges, flux, variance = (np.asarray(a, float) for a in (edges, flux, variance))
    w = band_overlap(edges, lo, hi)
    use = (w > 0) & np.isfinite(flux) & np.isfinite(variance) & (variance > 0)
    covered = float(np.sum(w[use] * np.diff(edges)[use]))
    partial = covered < (1 - 1e-6) * (hi - lo)
    tb = rebin(truth.edges(), truth.rate, edges)
    wu = w[use]
    t_band = float(np.sum(wu * tb[use]))
    f_band = float(np.sum(wu * flux[use]))
    if covariance is not None and np.shape(covariance) == (edges.size - 1,) * 2:
        c = np.asarray(covariance, float)[np.ix_(use, use)]
    else:
        c = np.diag(variance[use])
    var_band = float(wu @ c @ wu)
    out = dict.fromkeys(("band_flux_ratio", "band_flux_ratio_error", "pull", "chi2", "snr_reported",
                         "snr_measured", "snr_etc"), np.nan)
    out["partial"] = bool(partial)
    tw = band_overlap(truth.edges(), lo, hi)
    etc_var = float(np.nansum(tw**2 * truth.etc_variance))
    t_native = float(np.nansum(tw * np.nan_to_num(truth.rate)))
    if etc_var > 0:
        out["snr_etc"] = t_native / np.sqrt(etc_var)
    if not (use.any() and t_band > 0 and var_band > 0):
        return out
    sigma = np.sqrt(var_band)
    r = flux[use] - tb[use]
    try:
        chi2 = float(r @ np.linalg.solve(c, r)) / r.size
    except np.linalg.LinAlgError:
        chi2 = float(np.sum(r**2 / variance[use])) / r.size
    out.update(band_flux_ratio=f_band / t_band, band_flux_ratio_error=sigma / t_band,
               pull=(f_band - t_band) / sigma, chi2=chi2, snr_reported=f_band / sigma,
               snr_measured=f_band / (sigma * np.sqrt(chi2)) if chi2 > 0 else np.nan)
    return out


def redshift_bins(z, values, errors=None, nbins=None):
    """Mean ± error of ``values`` in bins of redshift (finite values only).

    Parameters
    ----------
    z, values : (N,) arrays;  errors : (N,) per-value errors (None: the scatter is the error)
    nbins : number of bins (default: about one per 4 values, 1 to 6)

    Returns
    -------
    dict of (k,) arrays: z_lo, z_hi, z_mid, n, mean, error (the larger of the scatter / √n and,
    with ``errors``, the propagated √Σσ² / n; NaN for an empty bin).
    """
    z, v = np.asarray(z, float), np.asarray(values, float)
    ok = np.isfinite(z) & np.isfinite(v)
    e = None if errors is None else np.asarray(errors, float)
    if e is not None:
        ok &= np.isfinite(e)
    n_ok = int(ok.sum())
    k = int(nbins) if nbins else int(np.clip(round(n_ok / 4), 1, 6))
    if n_ok == 0:
        return {key: np.array([]) for key in ("z_lo", "z_hi", "z_mid", "n", "mean", "error")}
    lo, hi = float(z[ok].min()), float(z[ok].max())
    edges = np.linspace(lo, hi if hi > lo else lo + 1e-6, k + 1)
    idx = np.clip(np.searchsorted(edges, z[ok], side="right") - 1, 0, k - 1)
    out = {"z_lo": edges[:-1], "z_hi": edges[1:], "z_mid": 0.5 * (edges[1:] + edges[:-1]),
           "n": np.bincount(idx, minlength=k), "mean": np.full(k, np.nan), "error": np.full(k, np.nan)}
    vv = v[ok]
    for i in range(k):
        sel = vv[idx == i]
        if sel.size == 0:
            continue
        out["mean"][i] = sel.mean()
        scatter = sel.std(ddof=1) / np.sqrt(sel.size) if sel.size > 1 else np.nan
        prop = np.sqrt(np.sum(e[ok][idx == i] ** 2)) / sel.size if e is not None else np.nan
        out["error"][i] = np.nanmax([scatter, prop]) if np.isfinite([scatter, prop]).any() else np.nan
    return out


# ----------------------------------------------------------------------------- reading the products
def _band_of(spec, redshift):
    """(lo, hi) [Å, observer frame] of the campaign's band for a target at ``redshift``."""
    obs = (spec or {}).get("observation") or {}
    lo, hi = obs.get("lbda_range") or DEFAULT_BAND[:2]
    frame = obs.get("frame") or DEFAULT_BAND[2]
    scale = 1.0 + redshift if frame == "rest" and np.isfinite(redshift) else 1.0
    return float(lo) * scale, float(hi) * scale


def _reduced_spectrum(path, field):
    """(edges, flux, variance, covariance or None, fit attrs dict, field) of a reduced file, or None."""
    import h5py
    try:
        with h5py.File(path, "r") as fh:
            if "spectra" not in fh or not len(fh["spectra"]):
                return None
            name = field if field in fh["spectra"] else sorted(fh["spectra"])[0]
            g = fh["spectra"][name]
            cov = g["COVARIANCE"][...] if "COVARIANCE" in g else None
            raw = fh.attrs.get(f"SPECTRUM_{name.upper()}")
            fit = json.loads(raw.decode() if isinstance(raw, bytes) else raw) if raw is not None else {}
            return g["LBDA_EDGES"][...], g["FLUX"][...], g["VAR"][...], cov, fit, name
    except (OSError, KeyError, ValueError) as exc:
        raise RampFileError(f"cannot read the spectrum of {path} ({' '.join(str(exc).split())})") from None


def _simulated_spectrum(path):
    """(edges, noisy, variance, TargetTruth-like of the signal) of a campaign's spectrum.h5 [ADU]."""
    import h5py

    from slicersim.io.target_truth import TargetTruth
    with h5py.File(path, "r") as fh:
        lbda, signal, var, noisy = (fh[k][...] for k in ("lbda", "signal", "variance", "noisy"))
        flambda = fh["flambda"][...] if "flambda" in fh else np.full(lbda.size, np.nan)
    mids = 0.5 * (lbda[1:] + lbda[:-1])
    edges = np.concatenate([[lbda[0] - (mids[0] - lbda[0])], mids, [lbda[-1] + (lbda[-1] - mids[-1])]])
    truth = TargetTruth({}, lbda, np.diff(edges), flambda, signal, etc_variance=var)
    return edges, noisy, var, truth


def _position_error(truth, fit):
    """|fitted − true position| [arcsec] (forward fits: native cells × the truth's cell scale), or NaN."""
    pos = fit.get("position_native_cells")
    a = truth.attrs if truth is not None else {}
    if pos is None or not {"position_x", "position_y", "cell_scale"} <= set(a):
        return np.nan
    return float(np.hypot(pos[0] - a["position_x"], pos[1] - a["position_y"]) * a["cell_scale"])


def _row_value(row, name):
    if row is None or name not in row.colnames:
        return np.nan
    v = row[name]
    try:
        return float(v)
    except (TypeError, ValueError):
        return np.nan


def summarize(dataset, reduced=None):
    """The per-target summary (astropy Table, units in the column metadata; :data:`COLUMN_UNITS`) of
    campaign ``dataset``, from the reduction directory ``reduced`` (``slicersim reduce DATASET --out
    RED --spectra``) when given, else from the campaign's own simulated spectra.

    Parameters
    ----------
    dataset : path of a campaign dataset directory
    reduced : path of its reduction directory, or None

    Returns
    -------
    astropy.table.Table, one row per target of the campaign's catalog.
    """
    from astropy.table import Table

    from slicersim.io.dataset import CATALOG, Dataset, not_a_dataset_directory
    from slicersim.io.target_truth import read_target_truth
    src = Dataset(dataset)
    if not os.path.isdir(src.path):
        raise not_a_dataset_directory(src.path, "run the campaign first: `slicersim campaign run SPEC --out DIR`")
    stored = src.stored_spec()
    if stored is None:
        raise DatasetError(f"{src.path} is not a slicersim campaign dataset (no spec.json)")
    spec = stored[0]
    if isinstance(spec, dict) and spec.get("kind") == "slicersim reduction":
        raise DatasetError(f"{src.path} is a reduction directory: give the campaign dataset, and this with --reduced")
    try:
        catalog = Table.read(src.file(CATALOG), format="ascii.ecsv")
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{src.file(CATALOG)} is missing or unreadable ({' '.join(str(exc).split())[:200]})") \
            from None
    red = red_catalog = None
    if reduced is not None:
        red = Dataset(reduced)
        rstored = red.stored_spec() if os.path.isdir(red.path) else None
        if rstored is None or rstored[0].get("kind") != "slicersim reduction":
            raise DatasetError(f"{red.path} is not a reduction directory (made by `slicersim reduce DATASET --out "
                               "DIR`)")
        try:
            red_catalog = Table.read(red.file(CATALOG), format="ascii.ecsv")
        except (OSError, ValueError) as exc:
            raise DatasetError(f"{red.file(CATALOG)} is missing or unreadable "
                               f"({' '.join(str(exc).split())[:200]})") from None
    red_rows = {int(r["target_id"]): r for r in red_catalog} if red_catalog is not None else {}
    rows = [_target_row(src, spec, row, red, red_rows.get(int(row["target_id"])), read_target_truth)
            for row in catalog]
    return _table(rows)


def _target_row(src, spec, row, red, red_row, read_truth):
    """One summary row (dict)."""
    tid = int(row["target_id"])
    z = _row_value(row, "redshift")
    out = {"target_id": tid, "status": str(row["status"]) if "status" in row.colnames else "",
           "redshift": z, "phase": _row_value(row, "phase"), "peak_absmag": _row_value(row, "peak_absmag"),
           "field": str(row["field"]) if "field" in row.colnames else ""}
    lo, hi = _band_of(spec, z)
    out.update(band_lo=lo, band_hi=hi, chi2_fit=np.nan, noise_scale=np.nan, position_error=np.nan,
               t_simulate=src.read_timing(tid), t_reduce=red.read_timing(tid) if red is not None else np.nan)
    flags = []

    def truth_of(path):
        try:
            return read_truth(path)
        except RampFileError:                    # damaged: that target is flagged, the report goes on
            flags.append("unreadable")
            return None
    truth = None
    ramps = str(row["ramps_product"]) if "ramps_product" in row.colnames else ""
    result = None
    if red is not None:
        status = str(red_row["status"]) if red_row is not None else "missing"
        out["status"] = status
        product = str(red_row["product"]) if red_row is not None and "product" in red_row.colnames else ""
        if status != "done" or not product or product == "--":
            flags.append("not-reduced")
        else:
            truth, result = _reduced_result(os.path.join(red.path, product), src, ramps, out, flags, truth_of)
    elif out["status"] == "done" and _product(row, "reduced_product"):    # a streaming campaign's own reduction
        truth, result = _reduced_result(os.path.join(src.path, _product(row, "reduced_product")), src, ramps, out,
                                        flags, truth_of)
    else:
        if ramps and ramps != "--" and out["status"] == "done":
            truth = truth_of(os.path.join(src.path, ramps))
        sp = str(row["spectrum_product"]) if "spectrum_product" in row.colnames else ""
        if out["status"] == "done" and sp and sp != "--":
            try:
                edges, noisy, var, sim_truth = _simulated_spectrum(os.path.join(src.path, sp))
                result = compare_band(edges, noisy, var, sim_truth, (lo, hi))
                flags.append("simulated")
            except (OSError, KeyError):
                flags.append("unreadable")
        else:
            flags.append("no-spectrum")
    if truth is not None:
        for key in ("phase", "peak_absmag"):
            if not np.isfinite(out[key]) and key in truth.attrs:
                out[key] = float(truth.attrs[key])
    if result is not None:
        if result.pop("partial"):
            flags.append("partial-band")
        out.update(result)
        if np.isfinite(out["chi2"]) and out["chi2"] > CHI2_FLAG:
            flags.append("chi2")
        if np.isfinite(out["pull"]) and abs(out["pull"]) > PULL_FLAG:
            flags.append("pull")
    if out["status"] == "failed":
        flags.append("failed")
    out["flags"] = ",".join(dict.fromkeys(flags))
    return out


def _product(row, column):
    """The catalog's product path in ``column`` ("" when absent or empty)."""
    value = str(row[column]) if column in row.colnames else ""
    return "" if value in ("", "--") else value


def _reduced_result(path, src, ramps, out, flags, truth_of):
    """(truth, band comparison or None) of the reduced file ``path``; ``out`` gets the fit's χ² and position
    error, ``flags`` what went wrong (unreadable, rates-only, no-truth, fit-not-converged)."""
    lo, hi = out["band_lo"], out["band_hi"]
    truth = truth_of(path)
    if truth is None and ramps and ramps != "--":          # reduced before files carried it
        truth = truth_of(os.path.join(src.path, ramps))
    try:
        spectrum = _reduced_spectrum(path, out["field"])
    except RampFileError:
        flags.append("unreadable")
        return truth, None
    if spectrum is None:
        flags.append("rates-only")
        return truth, None
    if truth is None:
        flags.append("no-truth")
        return truth, None
    edges, flux, var, cov, fit, _ = spectrum
    result = compare_band(edges, flux, var, truth, (lo, hi), covariance=cov)
    out["chi2_fit"] = float(fit.get("chi2_dof_pixels", np.nan))
    out["noise_scale"] = float(fit.get("noise_scale") or np.nan)
    out["position_error"] = _position_error(truth, fit)
    if fit.get("converged") is False:
        flags.append("fit-not-converged")
    return truth, result


def _table(rows):
    from astropy.table import Table
    names = list(COLUMN_UNITS)
    cols = {n: [r.get(n, np.nan) for r in rows] for n in names}
    table = Table()
    for n in names:
        values = cols[n]
        if n in ("status", "field", "flags"):
            table[n] = np.array([str(v) for v in values], dtype=str) if values else np.array([], dtype=str)
        elif n == "target_id":
            table[n] = np.array(values, dtype=np.int64)
        else:
            table[n] = np.array(values, dtype=float)
        unit, description = COLUMN_UNITS[n]
        if unit:
            table[n].unit = unit
        table[n].description = description
    return table
