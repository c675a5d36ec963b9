"""Pictures of the instrument: both fields' cube and scene, PSF profiles, the slice map.

Like :mod:`slicersim.app.plotting` (which re-exports these functions): each returns the
matplotlib :class:`~matplotlib.figure.Figure`, writes it with ``savefile`` (and releases it
from pyplot), imports pyplot lazily and never calls ``plt.show``, so it works with Agg.
"""
from __future__ import annotations

import copy
import os

import numpy as np

from slicersim import validation
from slicersim.errors import ParameterError

__all__ = ["show_fields", "show_psf_profiles", "show_slice_map", "field_simulations", "save_figure", "figure_writer",
           "check_region", "check_wavelengths", "FIELDS"]

FIELDS = ("narrow", "wide")


def figure_writer(fig, path, **options):
    """(path, writer) for :func:`slicersim.io.atomic.write_files`: ``writer(file)`` draws ``fig``
    (``savefig`` ``options``) in the format of the path's suffix (none: matplotlib's
    default, appended to the path as ``savefig`` does)."""
    import matplotlib
    path = os.fspath(path)
    fmt = os.path.splitext(path)[1][1:].lower()
    if not fmt:
        fmt = matplotlib.rcParams["savefig.format"]
        path = f"{path}.{fmt}"
    supported = fig.canvas.get_supported_filetypes()
    if fmt not in supported:
        raise ParameterError(f"unsupported figure format {fmt!r} ({path}); use {', '.join(sorted(supported))}")
    return path, lambda fh: fig.savefig(fh, format=fmt, **options)


def save_figure(fig, savefile, **options):
    """Write ``fig`` (``savefig`` ``options``) and release it from pyplot; returns the path.

    A path is written atomically (:func:`slicersim.io.atomic.write_files`: a temporary in its
    directory, renamed in when complete, replacing an existing file; on any error, e.g. a full
    disk, nothing is left; temporaries of killed writers there are removed), see
    :func:`figure_writer` for the format.  A binary file object is written directly."""
    import matplotlib.pyplot as plt
    from slicersim.errors import DatasetError
    from slicersim.io.atomic import write_files
    if hasattr(savefile, "write"):
        fig.savefig(savefile, **options)
        plt.close(fig)
        return savefile
    path, writer = figure_writer(fig, savefile, **options)
    write_files({path: writer}, overwrite=True, error_class=DatasetError)
    plt.close(fig)
    return path


def _finish(fig, savefile):
    if savefile is not None:
        save_figure(fig, savefile, dpi=120, bbox_inches="tight")
    return fig


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


def _extent(sim):
    """Field extent [arcsec] of the cube image (x along the slices, y across them): the
    simulation's cells are squares of side ``spatial_scale`` (Lazuli: 58 × 116 cells of
    0.04″ or 0.08″), so a round source is drawn round."""
    spec = sim.spectrograph
    ny, nx = spec.shape
    half_y = 0.5 * ny * spec.spatial_scale
    half_x = 0.5 * nx * spec.spatial_scale
    return (-half_x, half_x, -half_y, half_y)


def _image_norm(img):
    """Colour scale of an image: asinh (linear below 1 % of the peak) for a high contrast (a
    point source: min < 10 % of max); linear for a low contrast; ±0.5 % around the value
    for a uniform image (a flat), whose rounding noise would else fill the colour bar."""
    from matplotlib.colors import AsinhNorm, Normalize
    finite = np.asarray(img, float)[np.isfinite(img)]               # saturated cells are NaN
    if finite.size == 0:
        return Normalize(vmin=0.0, vmax=1.0)
    lo, hi = float(finite.min()), float(finite.max())
    peak = max(abs(lo), abs(hi))
    if peak == 0 or hi - lo <= 1e-6 * peak:
        mid = 0.5 * (lo + hi)
        half = 0.005 * abs(mid) or 1.0
        return Normalize(vmin=mid - half, vmax=mid + half)
    if lo >= 0.1 * hi:
        return Normalize(vmin=lo, vmax=hi)
    return AsinhNorm(linear_width=0.01 * peak, vmin=lo, vmax=hi)


def _colorbar(fig, im, ax, label, min_gap=0.09):
    """Colour bar whose tick labels do not overlap: ticks closer than ``min_gap`` (fraction
    of the bar) to a kept one are dropped (asinh scales crowd ticks around 0)."""
    cb = fig.colorbar(im, ax=ax, fraction=0.046, label=label)
    norm = im.norm
    ticks = [t for t in cb.get_ticks() if norm.vmin <= t <= norm.vmax]
    if len(ticks) > 2:
        pos = np.asarray(norm(ticks), float)
        kept = []
        for i in np.argsort(-np.abs(np.asarray(ticks))):         # the largest |value| first
            if all(abs(pos[i] - pos[j]) >= min_gap for j in kept):
                kept.append(i)
        cb.set_ticks(sorted(ticks[i] for i in kept))
    return cb


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
        extent = _extent(sim)
        lo, hi = lbda[sel][0], lbda[sel][-1]
        for row, (data, unit, what) in enumerate(((scene, "ph/s/cell", "projected scene"),
                                                  (cube, "ADU", "noisy cube" if noisy else "signal cube"))):
            ax = axes[row, k]
            img = data[sel].sum(axis=0)                                # NaN where a bin saturates
            saturated = int(np.count_nonzero(~np.isfinite(img)))
            im = ax.imshow(img, origin="lower", extent=extent, interpolation="nearest", aspect="equal",
                           cmap=plt.get_cmap("cividis").with_extremes(bad="crimson"), norm=_image_norm(img))
            im.set_gid(f"{field}:{'scene' if row == 0 else 'cube'}")
            _colorbar(fig, im, ax, f"Σλ [{unit}]")
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
    return _finish(fig, savefile)


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
    return _finish(fig, savefile)


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


def check_region(region, shape):
    """(row0, row1, col0, col1) [px] of a zoom, checked to lie within a detector of ``shape``."""
    if isinstance(region, (str, bytes)) or not hasattr(region, "__len__") or len(region) != 4:
        raise ParameterError(f"region must be (row0, row1, col0, col1) [px], got {validation.short_repr(region)}")
    r0, r1, c0, c1 = (validation.integer(f"region[{i}] ({what}) [px]", v)
                      for i, (v, what) in enumerate(zip(region, ("row0", "row1", "col0", "col1"))))
    if not (0 <= r0 < r1 <= shape[0] and 0 <= c0 < c1 <= shape[1]):
        raise ParameterError(f"region (row0, row1, col0, col1) must satisfy 0 <= row0 < row1 <= {shape[0]} "
                             f"and 0 <= col0 < col1 <= {shape[1]} (the detector) [px], got {tuple(region)}")
    return r0, r1, c0, c1


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
    [px], within the detector, zooms in.
    """
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm
    from matplotlib.patches import Polygon

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
    if ax is None:
        fig, ax = plt.subplots(figsize=(9, 8.5), layout="constrained")
    else:
        fig = ax.figure
    r0, r1, c0, c1 = (0, shape[0], 0, shape[1]) if region is None else check_region(region, shape)
    view = dict(origin="lower", interpolation="nearest", interpolation_stage="data", extent=(c0, c1, r0, r1))
    if image is not None:
        data = np.asarray(image, np.float64)
        if data.shape != shape:
            raise ParameterError(f"image must have the detector shape {shape}, got {data.shape}")
        data = data[r0:r1, c0:c1]
        pos = data[data > 0]
        norm = LogNorm(vmin=max(pos.min(), pos.max() * 1e-6), vmax=pos.max()) if pos.size else None
        im = ax.imshow(np.where(data > 0, data, np.nan), norm=norm, cmap="magma", **view)
        fig.colorbar(im, ax=ax, fraction=0.046, label="detector image")
        edge = "cyan"
    else:
        label = detector_label_image(*footprints)[r0:r1, c0:c1]
        im = ax.imshow(np.ma.masked_equal(label, -1), cmap="tab20", **view)
        fig.colorbar(im, ax=ax, fraction=0.046, label="slice id (label image)")
        edge = "k"
    im.set_gid("background")
    nslices = 0
    for fp in footprints:
        for s in fp:
            ax.add_patch(Polygon(s.contour, closed=True, fill=False, ec=edge, lw=0.6, gid=f"slice {s.slice_id}"))
            if labels:
                x, y = s.trace_x[0], s.trace_y[0]
                ax.text(x, y + 6, str(s.slice_id), fontsize=5 if region is None else 8, ha="center",
                        va="bottom", color=edge, gid=f"label {s.slice_id}", clip_on=True)
            nslices += 1
    ax.set_xlim(c0, c1)
    ax.set_ylim(r0, r1)
    ax.set_aspect("equal")
    ax.set_xlabel("detector column x [px]")
    ax.set_ylabel("detector row y [px]")
    shared = sum(n for f in footprints for *_, n in f.overlaps())
    fp0 = footprints[0]
    ax.set_title(f"slice footprints: {nslices} slices ({', '.join(f.field for f in footprints)}), "
                 f"{fp0.lbda_edges[0]:.0f}–{fp0.lbda_edges[-1]:.0f} Å, windows ±{fp0.truncate:g} σ; "
                 f"{shared} px shared by neighbours", fontsize="medium")
    return _finish(fig, savefile)
