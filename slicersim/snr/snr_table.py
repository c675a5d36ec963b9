"""Band SNR of many extraction models × many candidate readouts (OpenCL kernel or NumPy twin).

The single-ramp band SNR per bin of every candidate readout (n, m, d) is the
band-mean signal over √(band-mean optimal-extraction variance); the Rauscher07
cell variance is linear in the electron rate, V = A + B·Q, which the
``band_variance.cl`` kernel evaluates for all candidates at once.
"""
from __future__ import annotations

import numpy as np

from slicersim.backends.band_variance import band_variance_table
from slicersim.physics.psf import gaussian_psf_cells
from slicersim.physics.readout import VARIANCE_MODELS, cell_variance_coefficients, readout_times

__all__ = ["band_snr_table_for_models", "sim_band_indices", "readout_variance_coefficients", "template_psf",
           "extraction_weights", "WEIGHT_CUTOFF"]

#: extraction weights below this fraction of their bin's largest are skipped by the batch ETC
#: (:func:`extraction_weights`): each skipped term of the bin's inverse variance is below
#: WEIGHT_CUTOFF × (its largest term) × (A + B·Q_max) / (A + B·Q_min) of the bin's cells
WEIGHT_CUTOFF = 1e-16


def sim_band_indices(mask):
    """[i0, i1) of a contiguous boolean band mask."""
    idx = np.nonzero(mask)[0]
    return np.array([idx[0], idx[-1] + 1])


def readout_variance_coefficients(sim, n, m, d):
    """Cell variance V = A + B·Q [ADU²] per candidate readout and the saturation limit
    Qsat [e-/s/cell] of a simulation's detector (:func:`slicersim.physics.readout.cell_variance_coefficients`)."""
    det = sim.detector
    return cell_variance_coefficients((n, m, d), det.tframe, det.ron, sim.effective_dark(), det.gain,
                                      det.saturation, sim.detector_pixels_per_cell, sim.conventions)


def band_snr_table_for_models(sim, models, band, candidates, backend="auto", psf2=None, precision=None,
                              columns=None):
    """Single-ramp band SNR per bin, shape (N, K), for N extraction models and K readouts.

    Parameters
    ----------
    sim : Simulation  (instrument and detector)
    models : list of ExtractionModel, or a tuple (Q (N, nλ, nc), signal_rate (N, nλ))
    band : (N, 2) int  [i0, i1) bin ranges
    candidates : (n, m, d) arrays of length K
    precision : None (float64: the ETC) or the batch ETC's "auto" | "double" | "single"
        (:func:`slicersim.backends.band_variance.band_variance_table`)
    columns : None, or (N, J) int array
        Only the candidates ``columns[t]`` (indices into ``candidates``) of each target: the result
        is then (N, J), each value the same as in the full (N, K) table.
    """
    n, m, d = (np.asarray(c) for c in candidates)
    if isinstance(models, tuple):
        Q, signal_rate = models
    else:
        Q = np.stack([mod.cell_rate() for mod in models])
        signal_rate = np.stack([mod.signal_rate for mod in models])
    if psf2 is None:
        psf2 = sim.extraction_model.psf2 if sim.scene.pointsource is not None else _template_psf2(sim)
    tint = (n - 1) * (m + d) * sim.detector.tframe
    band = np.asarray(band, dtype=np.int64)
    if sim.detector.variance_model.lower().startswith("rauscher"):
        A, B, qsat = readout_variance_coefficients(sim, n, m, d)
        if columns is not None:
            columns = np.asarray(columns, dtype=np.intp)
            A, B, qsat, tint = (np.broadcast_to(x, n.shape)[columns] for x in (A, B, qsat, tint))
        var_sum, nvalid = band_variance_table(Q, psf2, A, B, qsat, band, backend=backend, precision=precision)
    else:  # non-linear variance model: NumPy evaluation per candidate
        var_sum, nvalid = _generic_band_variance(sim, Q, psf2, band, n, m, d)
        if columns is not None:
            columns = np.asarray(columns, dtype=np.intp)
            var_sum, nvalid, tint = (np.take_along_axis(var_sum, columns, axis=1),
                                     np.take_along_axis(nvalid, columns, axis=1), tint[columns])
    mean_signal = np.empty(Q.shape[0])
    for t, (i0, i1) in enumerate(band):
        mean_signal[t] = np.nanmean(signal_rate[t, i0:i1]) if i1 > i0 else np.nan
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_var = var_sum / nvalid
        return mean_signal[:, None] * (tint if tint.ndim == 2 else tint[None, :]) / np.sqrt(mean_var)


def _generic_band_variance(sim, Q, psf2, band, n, m, d):
    det, ppc = sim.detector, sim.detector_pixels_per_cell
    model = VARIANCE_MODELS[det.variance_model.lower()]
    dark = sim.effective_dark()
    var_sum = np.zeros((Q.shape[0], n.size))
    nvalid = np.zeros((Q.shape[0], n.size), dtype=np.int32)
    for k in range(n.size):
        nmd = (int(n[k]), int(m[k]), int(d[k]))
        tint = readout_times(nmd, det.tframe)["integration_time_per_ramp"]
        for t, (i0, i1) in enumerate(band):
            q = Q[t, i0:i1] / ppc
            var = ppc * model(q, nmd, det.tframe, det.ron, dark, det.gain, sim.conventions)
            var = np.where((q + dark) * tint * det.gain > det.saturation, np.inf, var)
            with np.errstate(divide="ignore", invalid="ignore"):
                v = 1.0 / np.sum(psf2[i0:i1] / var, axis=1)
            ok = ~np.isnan(v)
            var_sum[t, k], nvalid[t, k] = v[ok].sum(), ok.sum()
    return var_sum, nvalid


def template_psf(sim):
    """Gaussian PSF fractions of the aperture cells (nλ, ncell) of a point source at the
    simulation's position (the extraction weights of the batch ETC)."""
    sig_y, sig_x = sim.psf_sigmas
    return gaussian_psf_cells(sig_y, sig_x, sim.spectrograph.shape, sim.position, sim.aperture)


def extraction_weights(psf, rel_cutoff=WEIGHT_CUTOFF):
    """Squared PSF fractions with the negligible ones set to exactly 0 (skipped by the band-variance
    kernel, :func:`slicersim.backends.band_variance.nonzero_weights`).

    Parameters
    ----------
    psf : (nλ, ncell) float array
        PSF fractions of the aperture cells per bin (:func:`template_psf`).
    rel_cutoff : float
        Weights ``psf²`` below ``rel_cutoff`` × the largest of their bin are set to 0 (default
        :data:`WEIGHT_CUTOFF`, 1e-16: the dropped part of a bin's inverse variance is at most
        ncell × 1e-16 × the contrast (A + B·Q_max) / (A + B·Q_min) of its cells' variances).

    Returns
    -------
    (nλ, ncell) float64 array
        The extraction weights ``psf²``, 0 where negligible.
    """
    p2 = np.asarray(psf, dtype=np.float64) ** 2
    small = p2 < rel_cutoff * p2.max(axis=1, keepdims=True)
    p2[small] = 0.0
    return p2


def _template_psf2(sim):
    return template_psf(sim) ** 2
