"""Images: cube slices at a few wavelengths, the detector with its slice footprints, raw-ramp
groups and group differences.

Like :mod:`slicersim.plotting.spectra`: duck-typed models or arrays in, a matplotlib Figure
out (``savefile`` writes it atomically and releases it); pyplot is imported lazily.
"""
from __future__ import annotations

import numpy as np

from slicersim import validation
from slicersim.errors import ParameterError
from slicersim.plotting.figures import MAX_PANELS, check_axes, check_savefile, colorbar, finish, image_norm, new_axes

__all__ = ["plot_cube_slices", "draw_slices", "check_region", "plot_ramp_group", "source_zoom", "sky_extent"]


def sky_extent(spectrograph):
    """Field extent [arcsec] (x along the slices, y across them) of a cube image: cells are
    squares of side ``spatial_scale`` [arcsec], so a round source is drawn round.

    Parameters
    ----------
    spectrograph : Spectrograph
        Its ``shape`` (ny, nx) [cells] and ``spatial_scale`` [arcsec].

    Returns
    -------
    tuple of float
        (left, right, bottom, top) [arcsec], centred on 0 (matplotlib's ``extent``).
    """
    ny, nx = spectrograph.shape
    half_y, half_x = 0.5 * ny * spectrograph.spatial_scale, 0.5 * nx * spectrograph.spatial_scale
    return (-half_x, half_x, -half_y, half_y)


def _cube_wavelengths(lbda, wanted):
    """Indices of the bins nearest to ``wanted`` [Å] (default: four spread over the grid)."""
    if wanted is None:
        return np.unique(np.linspace(0, lbda.size - 1, 6).round().astype(int)[1:-1])
    wanted = np.atleast_1d(np.asarray(wanted, dtype=float))
    if wanted.ndim != 1 or wanted.size == 0 or not np.all(np.isfinite(wanted)):
        raise ParameterError(f"lbda must be one or more finite wavelengths [AA], got {wanted!r}")
    outside = wanted[(wanted < lbda[0]) | (wanted > lbda[-1])]
    if outside.size:
        raise ParameterError(f"lbda must lie within the cube's grid {lbda[0]:.0f}-{lbda[-1]:.0f} AA, got "
                             f"{', '.join(f'{v:g}' for v in outside)}")
    return np.abs(lbda[None, :] - wanted[:, None]).argmin(axis=1)


def plot_cube_slices(sim, cube=None, lbda=None, ax=None, savefile=None, unit="ADU"):
    """Images of a cube at a few wavelengths (one panel per λ, the nearest bin).

    Parameters
    ----------
    sim : Simulation
        Its ``lbda`` [Å] and ``spectrograph`` (shape, ``spatial_scale`` [arcsec]).
    cube : array_like of shape (nλ, ny, nx), optional
        Values [``unit``]; default: the simulation's signal cube (``sim.get_cube()[0]``, all
        ramps) [ADU].
    lbda : array_like, optional
        Wavelengths of the panels [Å] (default: four spread over the grid).
    ax : sequence of matplotlib.axes.Axes, optional
        None (new figure) or a sequence of Axes, one per wavelength.
    savefile : str, os.PathLike or file object, optional
        If given the figure is saved there.
    unit : str, optional
        Unit of the cube (colour bars).

    Returns
    -------
    matplotlib.figure.Figure
        The figure.
    """
    check_savefile(savefile)
    lbda_grid = np.asarray(sim.lbda, dtype=float)
    index = _cube_wavelengths(lbda_grid, lbda)            # checked before the cube is computed
    if index.size > MAX_PANELS:
        raise ParameterError(f"lbda: at most {MAX_PANELS} wavelengths (one panel each), got {index.size}")
    if ax is not None:
        check_axes(ax, index.size, "Axes, one per wavelength")
    if cube is None:
        cube = sim.get_cube()[0]
    cube = np.asarray(cube, dtype=float)
    if cube.ndim != 3 or cube.shape[0] != lbda_grid.size:
        raise ParameterError(f"cube must have shape ({lbda_grid.size}, ny, nx), got {cube.shape}")
    if ax is None:
        import matplotlib.pyplot as plt
        fig, axes = plt.subplots(1, index.size, figsize=(3.6 * index.size + 1, 3.0), squeeze=False,
                                 layout="constrained")
        axes = list(axes[0])
    else:
        axes = check_axes(ax, index.size, "Axes, one per wavelength")
        fig = axes[0].figure
    extent = sky_extent(sim.spectrograph)
    for a, k in zip(axes, index):
        img = cube[k]
        im = a.imshow(img, origin="lower", extent=extent, interpolation="nearest", aspect="equal",
                      cmap="cividis", norm=image_norm(img))
        colorbar(fig, im, a, f"signal [{unit}]")
        a.set_title(f"λ = {lbda_grid[k]:.0f} Å", fontsize="medium")
        a.set_xlabel("x along the slices [arcsec]")
        a.set_ylabel("y across the slices [arcsec]")
    if ax is None:
        fig.suptitle(f"cube slices ({cube.shape[1]} × {cube.shape[2]} cells of "
                     f"{sim.spectrograph.spatial_scale:g}″)", fontsize="medium")
    return finish(fig, savefile)


def check_region(region, shape):
    """A zoom, checked to lie within a detector of ``shape``.

    Parameters
    ----------
    region : sequence of int
        (row0, row1, col0, col1) [px].
    shape : tuple of int
        (rows, cols) of the detector [px].

    Returns
    -------
    tuple of int
        (row0, row1, col0, col1) [px].

    Raises
    ------
    slicersim.errors.ParameterError
        Not four integers with 0 ≤ row0 < row1 ≤ rows and 0 ≤ col0 < col1 ≤ cols.
    """
    if isinstance(region, (str, bytes)) or not hasattr(region, "__len__") or len(region) != 4:
        raise ParameterError(f"region must be (row0, row1, col0, col1) [px], got {validation.short_repr(region)}")
    r0, r1, c0, c1 = (validation.integer(f"region[{i}] ({what}) [px]", v)
                      for i, (v, what) in enumerate(zip(region, ("row0", "row1", "col0", "col1"))))
    if not (0 <= r0 < r1 <= shape[0] and 0 <= c0 < c1 <= shape[1]):
        raise ParameterError(f"region (row0, row1, col0, col1) must satisfy 0 <= row0 < row1 <= {shape[0]} "
                             f"and 0 <= col0 < col1 <= {shape[1]} (the detector) [px], got {tuple(region)}")
    return r0, r1, c0, c1


def _slice_background(ax, fig, image, label_image, view, image_label):
    """Detector image (log scale) or label image behind the outlines; returns the outline colour."""
    from matplotlib.colors import LogNorm
    if image is not None:
        pos = image[image > 0]
        norm = LogNorm(vmin=max(pos.min(), pos.max() * 1e-6), vmax=pos.max()) if pos.size else None
        im = ax.imshow(np.where(image > 0, image, np.nan), norm=norm, cmap="magma", **view)
        fig.colorbar(im, ax=ax, fraction=0.046, label=image_label)
        edge = "cyan"
    else:
        im = ax.imshow(np.ma.masked_equal(label_image, -1), cmap="tab20", **view)
        fig.colorbar(im, ax=ax, fraction=0.046, label="slice id (label image)")
        edge = "k"
    im.set_gid("background")
    return edge


def draw_slices(footprints, image=None, label_image=None, *, region=None, labels=True, ax=None, savefile=None,
                image_label="detector image [e-/s/px]"):
    """The detector with every slice's footprint outlined and labelled.

    Parameters
    ----------
    footprints : list of FieldFootprints
        The field footprints (iterables of slices with ``contour`` [px], ``slice_id``,
        ``trace_x``/``trace_y`` [px]; ``field``, ``detector_shape``, ``lbda_edges`` [Å],
        ``truncate``, ``overlaps()``).
    image : array_like of shape (rows, cols), optional
        Detector image (log scale, colour bar ``image_label`` with its unit).
    label_image : array_like of shape (rows, cols), optional
        Instead of ``image``: slice id per pixel (−1 outside).
    region : tuple of int, optional
        (row0, row1, col0, col1) [px] zoom, already checked; default the whole detector.
    labels : bool, optional
        Write each slice id at the blue end of its trace.
    ax : matplotlib.axes.Axes, optional
        None (new figure) or an Axes.
    savefile : str, os.PathLike or file object, optional
        If given the figure is saved there.
    image_label : str, optional
        Label of the colour bar of ``image``, with its unit.

    Returns
    -------
    matplotlib.figure.Figure
        The figure.
    """
    check_savefile(savefile)
    from matplotlib.patches import Polygon
    shape = tuple(footprints[0].detector_shape)
    fig, ax = new_axes(ax, figsize=(9, 8.5))
    r0, r1, c0, c1 = (0, shape[0], 0, shape[1]) if region is None else region
    view = dict(origin="lower", interpolation="nearest", interpolation_stage="data", extent=(c0, c1, r0, r1))
    if image is not None:
        image = np.asarray(image, np.float64)
        if image.shape != shape:
            raise ParameterError(f"image must have the detector shape {shape}, got {image.shape}")
        image = image[r0:r1, c0:c1]
    elif label_image is not None:
        label_image = np.asarray(label_image)[r0:r1, c0:c1]
    else:
        raise ParameterError("draw_slices needs an image or a label_image")
    edge = _slice_background(ax, fig, image, label_image, view, image_label)
    nslices = 0
    for fp in footprints:
        for s in fp:
            ax.add_patch(Polygon(s.contour, closed=True, fill=False, ec=edge, lw=0.6, gid=f"slice {s.slice_id}"))
            if labels:
                ax.text(s.trace_x[0], s.trace_y[0] + 6, str(s.slice_id), fontsize=5 if region is None else 8,
                        ha="center", va="bottom", color=edge, gid=f"label {s.slice_id}", clip_on=True)
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
    return finish(fig, savefile)


# --------------------------------------------------------------------------- #
#  raw ramps                                                                   #
# --------------------------------------------------------------------------- #
def source_zoom(rate, half=(300, 250)):
    """A box of half-sizes ``half`` (rows, cols) around the brightest pixel of ``rate`` once
    each row's median (the slices' smooth light: background, thermal) is removed, i.e. around
    the source's trace; clipped to the image.

    Parameters
    ----------
    rate : array_like of shape (rows, cols)
        A rate image (NaN counted as 0).
    half : tuple of int, optional
        Half-sizes (rows, cols) of the box [px].

    Returns
    -------
    tuple of int
        (row0, row1, col0, col1) [px].
    """
    rate = np.nan_to_num(np.asarray(rate, dtype=float))
    excess = rate - np.median(rate, axis=1, keepdims=True)
    r, c = np.unravel_index(np.argmax(excess), rate.shape)
    hr, hc = min(half[0], rate.shape[0] // 2), min(half[1], rate.shape[1] // 2)
    r0 = int(np.clip(r - hr, 0, rate.shape[0] - 2 * hr))
    c0 = int(np.clip(c - hc, 0, rate.shape[1] - 2 * hc))
    return r0, r0 + 2 * hr, c0, c0 + 2 * hc


def _read_groups(path, ramp, first, group):
    """(first group, chosen group [ADU, float], their indices, time between them [s], attributes)."""
    from slicersim.io.rampfile import open_hdf5_input
    with open_hdf5_input(path, "an HDF5 ramp file", ("SCI", "truth/rate")) as fh:
        ngroups = fh["SCI"].shape[1]
        g0, g1 = first % ngroups, group % ngroups
        a = fh["SCI"][ramp, g0].astype(float)
        b = fh["SCI"][ramp, g1].astype(float)
        attrs = {k: fh.attrs[k] for k in ("READPATT", "TGROUP", "NGROUPS", "NFRAMES", "GROUPGAP", "NINTS")
                 if k in fh.attrs}
    dt = (g1 - g0) * float(attrs.get("TGROUP", np.nan))
    return a, b, (g0, g1), dt, attrs


def _block_mean(img, factor):
    """``img`` averaged over ``factor`` × ``factor`` blocks (a light full-detector view)."""
    ny, nx = (s // factor * factor for s in img.shape)
    return img[:ny, :nx].reshape(ny // factor, factor, nx // factor, factor).mean(axis=(1, 3))


def _ramp_panel(fig, ax, img, extent, title, label, cmap="magma"):
    lo, hi = np.nanpercentile(img, (1, 99.8))
    im = ax.imshow(img, origin="lower", extent=extent, cmap=cmap, interpolation="nearest", aspect="auto",
                   vmin=lo, vmax=hi if hi > lo else lo + 1)
    ax.set_title(title, fontsize="medium")
    fig.colorbar(im, ax=ax, fraction=0.046, label=label)
    ax.set_xlabel("detector column x [px]")
    ax.set_ylabel("detector row y [px]")


def plot_ramp_group(path, group=-1, ramp=0, savefile=None, zoom=None, *, first=0, title=None, origin=(0, 0)):
    """A raw ramp's source: the group difference as a slope next to a raw group.

    Panels: the slope (group ``group`` − group ``first``) / Δt [ADU/s] of the whole file
    (block means above 1024 px) with the zoom outlined, when the zoom is smaller than the file;
    the same slope in the zoom; the raw group ``group`` [ADU] (bias pedestal + charge, under
    the read noise) in the zoom.  ``zoom`` (row0, row1, col0, col1) [px of the file] defaults
    to :func:`source_zoom` of the file's input rate (``truth/rate``), else of the slope.
    ``origin`` (row, col) [px]: the file's first pixel on the detector (a window's ramp), so
    that axes read detector pixels.  ``title``: first line(s) of the title (e.g. the target and
    the readout the ETC chose); the file's readout pattern follows.

    Parameters
    ----------
    path : str or path-like
        The HDF5 ramp file.
    group : int, optional
        The group shown (negative: from the end).
    ramp : int, optional
        The ramp (integration) read.
    savefile : str, os.PathLike or file object, optional
        If given the figure is saved there.
    zoom : tuple of int, optional
        (row0, row1, col0, col1) [px of the file] around the source.
    first : int, optional
        The group subtracted from ``group``.
    title : str, optional
        First line(s) of the title.
    origin : tuple of int, optional
        (row, col) of the file's first pixel on the detector [px].

    Returns
    -------
    matplotlib.figure.Figure
        The figure.
    """
    check_savefile(savefile)
    import matplotlib.pyplot as plt

    from slicersim.io.rampfile import open_hdf5_input
    a, b, (g0, g1), dt, attrs = _read_groups(path, ramp, first, group)
    if g1 == g0:
        raise ParameterError(f"group and first must name different groups, got group {g1} twice")
    timed = bool(np.isfinite(dt) and dt > 0)
    slope, unit = ((b - a) / dt, "ADU/s") if timed else (b - a, "ADU")
    if zoom is None:
        with open_hdf5_input(path, "an HDF5 ramp file", ("SCI", "truth/rate")) as fh:
            rate = fh["truth/rate"][...] if "truth/rate" in fh else None
        zoom = source_zoom(slope if rate is None else rate)
    r0, r1, c0, c1 = check_region(zoom, slope.shape)
    oy, ox = (int(v) for v in origin)
    overview = (r1 - r0, c1 - c0) != slope.shape
    fig, axes = plt.subplots(1, 2 + overview, figsize=(6 * (2 + overview), 5.6), layout="constrained",
                             squeeze=False)
    axes = list(axes[0])
    box = (c0 + ox, c1 + ox, r0 + oy, r1 + oy)
    if overview:
        factor = max(1, -(-max(slope.shape) // 1024))
        ax0 = axes.pop(0)
        _ramp_panel(fig, ax0, _block_mean(slope, factor), (ox, ox + slope.shape[1], oy, oy + slope.shape[0]),
                    f"slope (group {g1} − group {g0}) / {dt:.0f} s, whole file", f"slope [{unit}]", "viridis")
        ax0.set_aspect("equal")
        ax0.add_patch(plt.Rectangle((box[0], box[2]), c1 - c0, r1 - r0, fill=False, color="r", lw=1.2, gid="zoom"))
    _ramp_panel(fig, axes[0], slope[r0:r1, c0:c1], box,
                f"slope (group {g1} − group {g0}) / {dt:.0f} s around the source", f"slope [{unit}]", "viridis")
    _ramp_panel(fig, axes[1], b[r0:r1, c0:c1], box, f"raw group {g1} around the source", "raw group [ADU]")
    patt = attrs.get("READPATT", "")
    patt = patt.decode() if isinstance(patt, bytes) else str(patt)
    readout = (f"file: {patt}, ramp {ramp} of {int(attrs.get('NINTS', 1))}, "
               f"{int(attrs.get('NGROUPS', 0))} groups of {int(attrs.get('NFRAMES', 0))} frames, "
               f"gap {int(attrs.get('GROUPGAP', 0))}; {slope.shape[0]} × {slope.shape[1]} px")
    fig.suptitle((f"{title}\n" if title else "") + readout, fontsize="medium")
    return finish(fig, savefile, dpi=100)
