"""Pictures of the instrument: both fields' cube and scene, PSF profiles, the slice map.

Like :mod:`slicersim.app.plotting` (which re-exports these functions): each returns the
matplotlib :class:`~matplotlib.figure.Figure`, writes it with ``savefile`` (and releases it
from pyplot), imports pyplot lazily and never calls ``plt.show``, so it works with Agg.
"""
from __future__ import annotations

import copy

import numpy as np

from slicersim import validation
from slicersim.errors import ParameterError
from slicersim.plotting import (check_region, check_savefile, colorbar, draw_slices, figure_writer,  # noqa: F401
                                finish, image_norm, save_figure, sky_extent)

__all__ = ["show_fields", "show_psf_profiles", "show_slice_map", "field_simulations", "save_figure", "figure_writer",
           "check_region", "check_wavelengths", "FIELDS"]

FIELDS = ("narrow", "wide")


def _simulation(obj):
    sim = getattr(obj, "simulation", obj)
    if not (hasattr(sim, "get_projected_scene") and hasattr(sim, "spectrograph")):
        raise ParameterError(f"expected a Target or a Simulation, got {type(obj).__name__}")
    return sim


def field_simulations(target_or_sim):
    """{"narrow": Simulation, "wide": Simulation} of the same scene and readout in both fields.

    A Target is copied and moved to the other field with ``update(field=...)``; a
    Simulation built by :func:`~slicersim.assembly.build_simulation` (``sim.config``,
    ``sim.field``) gets a twin in the other field with a copy of its scene and its readout;
    a mapping {field: Target or Simulation} is used as given."""
    if isinstance(target_or_sim, dict):
        unknown = set(target_or_sim) - set(FIELDS)
        if unknown or not target_or_sim:
            raise ParameterError(f"field mapping needs keys among {FIELDS}, got {sorted(target_or_sim)}")
        return {f: _simulation(target_or_sim[f]) for f in FIELDS if f in target_or_sim}
    sim = _simulation(target_or_sim)
    field = getattr(target_or_sim, "field", None) or getattr(sim, "field", None)
    if field not in FIELDS:
        raise ParameterError(f"cannot tell the Lazuli field of this object (field={field!r}); pass "
                             "{'narrow': ..., 'wide': ...}")
    other = FIELDS[1 - FIELDS.index(field)]
    if sim is not target_or_sim:                                   # a Target
        twin = copy.deepcopy(target_or_sim)
        twin.update(field=other)
        return {field: sim, other: twin.simulation}
    from slicersim.assembly import build_simulation
    twin = build_simulation(getattr(sim, "config", "cbe"), other, conventions=sim.conventions)
    twin.scene = copy.deepcopy(sim.scene)
    twin.update(nmd=tuple(sim.detector.nmd), nramps=sim.nramps)
    return {field: sim, other: twin}


def _band(lbda, lbda_range):
    if lbda_range is None:
        return np.ones(lbda.size, bool)
    lo, hi = (float(v) for v in lbda_range)
    sel = (lbda >= lo) & (lbda <= hi)
    if not (lo < hi) or not sel.any():
        raise ParameterError(f"lbda_range {lbda_range} [AA] selects no bin of the grid "
                             f"{lbda[0]:.0f}-{lbda[-1]:.0f} AA")
    return sel


def _has_compact_source(sim):
    """False for a field-filling illumination (a flat: no point source, no host)."""
    scene = getattr(sim, "scene", None)
    if scene is None:
        return True
    return getattr(scene, "pointsource", None) is not None or getattr(scene, "host", None) is not None


def _subject(target_or_sim, sims):
    """What the figure shows: the target's class (or Simulation), and for a flat what the spectra are."""
    if isinstance(target_or_sim, dict):
        target_or_sim = next(iter(target_or_sim.values()))
    name = type(target_or_sim).__name__
    if not _has_compact_source(next(iter(sims.values()))):
        name += " (field-filling illumination: mean spectra per cell)"
    return name


# --------------------------------------------------------------------------- #
#  both fields                                                                 #
# --------------------------------------------------------------------------- #
def show_fields(target_or_sim, lbda_range=None, seed=None, savefile=None):
    """Scene and cube of the narrow and wide fields side by side (one column per field).

    Rows: the projected scene C summed over ``lbda_range`` [Å, observed; default all bins]
    [ph/s per cell]; the signal cube (all ramps, noisy when ``seed`` is given) summed the
    same way [ADU] (asinh colour scales, linear below 1 % of the peak; linear for images of
    low contrast such as flats); the spectra summed over the extraction aperture's cells
    (``sim.aperture``): cube [ADU] (left axis) and scene [ph/s] (right axis) — without a
    point source (flats, lamps) the mean spectra per cell over the whole field instead.
    Images in arcsec on the sky (x along the slices, square cells: equal scales on both
    axes).  See :func:`field_simulations` for what ``target_or_sim`` may be.
    """
    check_savefile(savefile)
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    sims = field_simulations(target_or_sim)
    fields = [f for f in FIELDS if f in sims]
    fig, axes = plt.subplots(3, len(fields), figsize=(6.4 * len(fields), 9.5), squeeze=False,
                             gridspec_kw={"height_ratios": [1, 1, 1.2]}, layout="constrained")
    for k, field in enumerate(fields):
        sim = sims[field]
        lbda = sim.lbda
        sel = _band(lbda, lbda_range)
        scene = sim.get_projected_scene()
        signal, _, *noisy = sim.get_cube(seed=seed)
        cube = noisy[0] if noisy else signal
        extent = sky_extent(sim.spectrograph)
        lo, hi = lbda[sel][0], lbda[sel][-1]
        for row, (data, unit, what) in enumerate(((scene, "ph/s/cell", "projected scene"),
                                                  (cube, "ADU", "noisy cube" if noisy else "signal cube"))):
            ax = axes[row, k]
            img = data[sel].sum(axis=0)                                # NaN where a bin saturates
            saturated = int(np.count_nonzero(~np.isfinite(img)))
            im = ax.imshow(img, origin="lower", extent=extent, interpolation="nearest", aspect="equal",
                           cmap=plt.get_cmap("cividis").with_extremes(bad="crimson"), norm=image_norm(img))
            im.set_gid(f"{field}:{'scene' if row == 0 else 'cube'}")
            colorbar(fig, im, ax, f"Σλ [{unit}]")
            note = f", {saturated} cells saturated (red)" if saturated else ""
            ax.set_title(f"{field} field ({sim.spectrograph.spatial_scale:g}″ cells): {what}{note}\n"
                         f"{lo:.0f}–{hi:.0f} Å", fontsize="medium")
            ax.set_xlabel("x along the slices [arcsec]")
            ax.set_ylabel("y across the slices [arcsec]")
        ax = axes[2, k]
        if _has_compact_source(sim):
            iy, ix = sim.aperture
            spec_cube, spec_scene = cube[:, iy, ix].sum(axis=1), scene[:, iy, ix].sum(axis=1)
            where, unit = f"in the aperture ({iy.size} cells)", ""
        else:                                   # a flat: no aperture, the mean cell of the field
            spec_cube, spec_scene = cube.mean(axis=(1, 2)), scene.mean(axis=(1, 2))
            where, unit = f"field mean ({cube.shape[1]}×{cube.shape[2]} cells)", "/cell"
        ax.plot(lbda, spec_cube, color="tab:blue", lw=1.2, ds="steps-mid", gid=f"{field}:cube")
        ax.set_ylabel(f"cube, {where} [ADU{unit}]", color="tab:blue")
        ax.set_xlabel("observed wavelength [Å]")
        twin = ax.twinx()
        twin.plot(lbda, spec_scene, color="tab:orange", lw=1.0, ds="steps-mid", gid=f"{field}:scene")
        twin.set_ylabel(f"scene, {where.split(' (')[0]} [ph/s{unit}]", color="tab:orange")
        if lbda_range is not None:
            ax.axvspan(lo, hi, color="gold", alpha=0.25, lw=0, zorder=0)
        ax.xaxis.set_major_locator(MaxNLocator(5))
        ax.set_xlim(lbda[0], lbda[-1])
        ax.grid(alpha=0.3)
    t = sims[fields[0]].get_times()
    which = "narrow and wide fields" if len(fields) == 2 else f"{fields[0]} field"
    fig.suptitle(f"{_subject(target_or_sim, sims)}: Lazuli {which}, readout "
                 f"{tuple(int(v) for v in t['nmd'])} × {int(t['nramps'])} ramp(s), "
                 f"{float(t['exposure_time']):.0f} s", fontsize="medium")
    return finish(fig, savefile)


# --------------------------------------------------------------------------- #
#  PSF                                                                         #
# --------------------------------------------------------------------------- #
def check_wavelengths(sim, lbda, what="lbda"):
    """Refuse (ParameterError naming ``what``) wavelengths [Å] that are not numbers or lie outside the
    simulation's spectral range; returns them as a 1-D float array."""
    lbdas = validation.array(f"{what} [AA]", np.atleast_1d(lbda), ndim=1)
    if lbdas.size == 0:
        raise ParameterError(f"{what} must be one or more wavelengths [AA], got none")
    edges = sim.spectrograph.lbda_edges
    lo, hi = float(edges[0]), float(edges[-1])
    bad = [float(v) for v in lbdas if not lo <= v <= hi]
    if bad:
        raise ParameterError(f"{what} must lie within the instrument's range {lo:.0f}-{hi:.0f} AA, got "
                             f"{', '.join(f'{v:g}' for v in bad)}")
    return lbdas


def psf_profile_curves(sim, lbda, radius):
    """Normalised radial profiles and encircled energies at λ [Å] and r [arcsec].

    Returns {"airy", "gauss_y", "gauss_x", "ee_airy", "ee_gauss"}: the Airy intensity of the
    annular pupil I(r)/I(0) (diffraction only); the simulation's Gaussian PSF exp(−r²/2σ²)
    across (σ_y: Airy-equivalent σ with guiding jitter) and along the slices (σ_x, plus the
    instrumental blur); the Airy encircled energy and the Gaussian's 1 − exp(−r²/2σ_y²)."""
    from slicersim.physics.psf import (airy_amplitude, airy_encircled_energy, airy_wavenumber,
                                       gaussian_psf_sigmas)
    tel, spec = sim.telescope, sim.spectrograph
    r = np.asarray(radius, np.float64)
    sig_y, sig_x = (float(v) * spec.spatial_scale for v in gaussian_psf_sigmas(
        lbda, tel.psf_sigma_ref, spec.spatial_scale, tel.guiding_sigma, sim.instrumental_sigma))
    k = float(airy_wavenumber(lbda, tel.diameter_ext, 1.0))
    return {"airy": airy_amplitude(k * r, tel.obscuration) ** 2,
            "gauss_y": np.exp(-0.5 * (r / sig_y) ** 2), "gauss_x": np.exp(-0.5 * (r / sig_x) ** 2),
            "ee_airy": airy_encircled_energy(r, lbda, tel.diameter_ext, tel.obscuration),
            "ee_gauss": 1.0 - np.exp(-0.5 * (r / sig_y) ** 2), "sigma": (sig_y, sig_x)}


def show_psf_profiles(target_or_sim, lbda=(5000.0, 10000.0, 15000.0), rmax=None, npoints=400, savefile=None):
    """PSF radial profiles (left, log scale) and encircled energy (right) at wavelengths ``lbda`` [Å].

    Per λ: the Airy pattern of the telescope's annular pupil (solid) and the simulation's
    Gaussian model across (dashed) and along (dotted) the slices, from
    :func:`psf_profile_curves`; ``lbda`` must lie within the instrument's spectral range;
    ``rmax`` [arcsec] defaults to 3 Airy radii at the largest λ.
    The cell sizes of both fields (0.04″, 0.08″ for Lazuli) are marked.
    """
    check_savefile(savefile)
    import matplotlib.pyplot as plt

    sim = _simulation(target_or_sim)
    lbdas = check_wavelengths(sim, lbda)
    if rmax is None:
        rmax = 3.0 * float(sim.telescope.airy_radius(lbdas.max()))
    rmax = validation.number("rmax", rmax, low=0.0, low_open=True, unit="arcsec")
    npoints = validation.integer("npoints", npoints, low=2, high=1 << 20)
    r = np.linspace(0.0, rmax, npoints)
    fig, (ax_p, ax_e) = plt.subplots(1, 2, figsize=(11, 4.6), layout="constrained")
    colours = plt.get_cmap("plasma")(np.linspace(0.1, 0.85, lbdas.size))
    for lam, col in zip(lbdas, colours):
        c = psf_profile_curves(sim, lam, r)
        ax_p.plot(r, c["airy"], color=col, lw=1.4, label=f"{lam:.0f} Å Airy", gid=f"airy:{lam:g}")
        ax_p.plot(r, c["gauss_y"], color=col, lw=1.0, ls="--", gid=f"gauss_y:{lam:g}",
                  label=f"Gaussian σ_y = {c['sigma'][0]:.3f}″")
        ax_p.plot(r, c["gauss_x"], color=col, lw=1.0, ls=":", gid=f"gauss_x:{lam:g}",
                  label=f"Gaussian σ_x = {c['sigma'][1]:.3f}″")
        ax_e.plot(r, c["ee_airy"], color=col, lw=1.4, label=f"{lam:.0f} Å Airy", gid=f"ee_airy:{lam:g}")
        ax_e.plot(r, c["ee_gauss"], color=col, lw=1.0, ls="--", label="Gaussian", gid=f"ee_gauss:{lam:g}")
    from slicersim.assembly import LAZULI_FIELDS
    for ax in (ax_p, ax_e):
        for name, par in LAZULI_FIELDS.items():
            ax.axvline(par["spatial_scale"], color="0.5", lw=0.8, ls="-.", gid=f"cell:{name}")
        ax.set_xlabel("radius [arcsec]")
        ax.grid(alpha=0.3)
        ax.set_xlim(0, r[-1])
    ax_p.set_yscale("log")
    ax_p.set_ylim(1e-5, 1.5)
    ax_p.set_ylabel("intensity / peak")
    ax_e.set_ylabel("encircled energy")
    ax_e.set_ylim(0, 1.02)
    ax_p.legend(fontsize="x-small", ncol=1, loc="upper right")
    tel = sim.telescope
    fig.suptitle(f"PSF: D = {tel.diameter_ext:g} m, obscuration {tel.obscuration:.2f}, guiding σ "
                 f"{tel.guiding_sigma:g}″; cells 0.04″ / 0.08″ (dash-dot)", fontsize="medium")
    return finish(fig, savefile)


# --------------------------------------------------------------------------- #
#  slice map                                                                   #
# --------------------------------------------------------------------------- #
def _field_footprints(mapper, fields, config, lbda_edges, ncol, truncate):
    from slicersim.instrument.footprints import field_footprints
    out = []
    for field in fields:
        if lbda_edges is None:
            from slicersim.assembly import build_simulation
            spec = build_simulation(config, field).spectrograph
            out.append(field_footprints(mapper, field, spectrograph=spec, truncate=truncate))
        else:
            out.append(field_footprints(mapper, field, lbda_edges, ncol, truncate=truncate))
    return out


def show_slice_map(mapper=None, fields=FIELDS, image=None, *, footprints=None, config="cbe", lbda_edges=None,
                   ncol=116, truncate=4.0, labels=True, region=None, ax=None, savefile=None):
    """The detector with every slice's footprint outlined and labelled.

    Background: ``image`` (e.g. ``target.get_detector_image()`` [e-/s/px], log scale), else
    the label image (slice id per pixel, :func:`~slicersim.instrument.footprints.detector_label_image`).
    Outlines: each slice's outer contour (one closed polygon per slice, ``gid`` "slice N"),
    labelled with its id at the blue end of its trace.  Footprints come from ``footprints``
    (:class:`~slicersim.instrument.footprints.FieldFootprints`, one or a list), else from
    ``mapper`` (default: the built-in Lazuli layout) for ``fields`` on the grid of
    ``config`` (or ``lbda_edges`` [Å] and ``ncol``).  ``region`` (row0, row1, col0, col1)
    [px], within the detector, zooms in.  The colour bar reads "detector image
    [e-/s/px]".  Drawn by :func:`slicersim.plotting.draw_slices`.
    """
    check_savefile(savefile)
    from slicersim.instrument.footprints import FieldFootprints, detector_label_image
    if footprints is None:
        if mapper is None:
            from slicersim.assembly import default_mapper
            mapper = default_mapper()
        fields = (fields,) if isinstance(fields, str) else tuple(fields)
        if not fields or not set(fields) <= set(FIELDS):
            raise ParameterError(f"fields must be among {FIELDS}, got {fields!r}")
        footprints = _field_footprints(mapper, fields, config, lbda_edges, ncol, truncate)
    footprints = [footprints] if isinstance(footprints, FieldFootprints) else list(footprints)
    if not footprints or not all(isinstance(f, FieldFootprints) for f in footprints):
        raise ParameterError("footprints must be FieldFootprints (one or a list)")
    shape = footprints[0].detector_shape
    region = None if region is None else check_region(region, shape)
    label_image = detector_label_image(*footprints) if image is None else None
    return draw_slices(footprints, image, label_image, region=region, labels=labels, ax=ax, savefile=savefile)
