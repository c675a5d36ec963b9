"""Figure plumbing shared by every plot: axes, colour bars, colour scales, atomic saving.

Only NumPy and matplotlib (imported lazily, inside the functions) and the layers below
(``errors``, ``io.atomic``); ``plt.show`` is never called, so everything works with Agg.
"""
from __future__ import annotations

import os

import numpy as np

from slicersim.errors import ParameterError

__all__ = ["figure_writer", "save_figure", "finish", "new_axes", "colorbar", "image_norm", "check_axes",
           "check_savefile", "MAX_PANELS"]

#: the most panels one figure draws (one per wavelength of ``show_cube``): more is unreadable and slow
MAX_PANELS = 12


def check_savefile(savefile):
    """``savefile`` checked before anything is drawn.

    Parameters
    ----------
    savefile : str, os.PathLike, file object or None
        None, a path naming a file (str or os.PathLike, its folder existing) or a binary file
        object.

    Returns
    -------
    str, os.PathLike, file object or None
        ``savefile`` unchanged.

    Raises
    ------
    slicersim.errors.ParameterError
        Naming it otherwise (``savefile=3``, or ``"."`` that wrote ``..png``).
    """
    if savefile is None or hasattr(savefile, "write"):
        return savefile
    if isinstance(savefile, bool) or not isinstance(savefile, (str, os.PathLike)):
        raise ParameterError(f"savefile must be a file path (str or os.PathLike) or a binary file object, got "
                             f"{_short(savefile)}")
    path = os.fspath(savefile)
    name = os.path.basename(path)
    if not name or name in (".", "..") or os.path.isdir(path):
        raise ParameterError(f"savefile {path!r} names a folder, not a file: give a file name such as "
                             f"{os.path.join(path, 'figure.png')!r}")
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise ParameterError(f"savefile {path!r}: the folder {folder!r} does not exist")
    return savefile


def check_axes(ax, count=None, what="Axes"):
    """``ax`` as a list of matplotlib Axes.

    Parameters
    ----------
    ax : matplotlib.axes.Axes or sequence of matplotlib.axes.Axes
        One Axes, or a sequence of ``count`` of them.
    count : int, optional
        The number of Axes required (any count when None).
    what : str, optional
        What the Axes are, in the error message.

    Returns
    -------
    list of matplotlib.axes.Axes
        The Axes.

    Raises
    ------
    slicersim.errors.ParameterError
        Naming the argument otherwise (``ax='foo'`` was an AttributeError).
    """
    from matplotlib.axes import Axes
    axes = [ax] if isinstance(ax, Axes) else None
    if axes is None:
        if isinstance(ax, (str, bytes)) or not hasattr(ax, "__len__"):
            raise ParameterError(f"ax must be a matplotlib Axes or a sequence of them, got {_short(ax)}")
        axes = list(np.ravel(np.asarray(ax, dtype=object)))
        bad = [a for a in axes if not isinstance(a, Axes)]
        if bad or not axes:
            raise ParameterError(f"ax must be a matplotlib Axes or a sequence of them, got "
                                 f"{_short(bad[0]) if bad else 'an empty sequence'} in it")
    if count is not None and len(axes) != count:
        raise ParameterError(f"ax must hold {count} {what}, got {len(axes)}")
    return axes


def _short(value):
    from slicersim.validation import short_repr
    return short_repr(value)


def figure_writer(fig, path, **options):
    """(path, writer) for ``slicersim.io.file_set.write_files``.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure.
    path : str or os.PathLike
        Where it goes; its suffix gives the format (none: matplotlib's default, appended to
        the path as ``savefig`` does).
    **options
        ``savefig`` options.

    Returns
    -------
    path : str
        The path, with the suffix of the format.
    writer : callable
        ``writer(file)`` draws ``fig`` in that format to a binary file.
    """
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
    """Write ``fig`` and release it from pyplot.

    A path is written atomically (``slicersim.io.file_set.write_files``: a temporary in its
    directory, renamed in when complete, replacing an existing file; on any error, e.g. a full
    disk, nothing is left; temporaries of killed writers there are removed), see
    :func:`figure_writer` for the format.  A binary file object is written directly.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure.
    savefile : str, os.PathLike or file object
        A path or a binary file object.
    **options
        ``savefig`` options.

    Returns
    -------
    str or file object
        The path written (with the format's suffix), or the file object.
    """
    import matplotlib.pyplot as plt
    from slicersim.errors import DatasetError
    from slicersim.io.file_set import write_files
    if hasattr(savefile, "write"):
        fig.savefig(savefile, **options)
        plt.close(fig)
        return savefile
    path, writer = figure_writer(fig, savefile, **options)
    write_files({path: writer}, overwrite=True, error_class=DatasetError)
    plt.close(fig)
    return path


def finish(fig, savefile, dpi=120):
    """Save ``fig`` to ``savefile`` when given (:func:`save_figure`, tight box).

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure.
    savefile : str, os.PathLike, file object or None
        Where to save it (checked by :func:`check_savefile`); None: not saved.
    dpi : float, optional
        Resolution [dots per inch].

    Returns
    -------
    matplotlib.figure.Figure
        ``fig``.
    """
    check_savefile(savefile)
    if savefile is not None:
        save_figure(fig, savefile, dpi=dpi, bbox_inches="tight")
    return fig


def new_axes(ax=None, **subplots):
    """The figure and axes to draw on.

    Parameters
    ----------
    ax : matplotlib.axes.Axes, optional
        Draw there (one Axes).
    **subplots
        Without ``ax``: options of ``plt.subplots`` (constrained layout by default).

    Returns
    -------
    fig : matplotlib.figure.Figure
        ``ax``'s figure, else a new figure.
    axes : matplotlib.axes.Axes or numpy.ndarray
        ``ax``, else the new axes.
    """
    if ax is not None:
        ax = check_axes(ax, 1)[0]
        return ax.figure, ax
    import matplotlib.pyplot as plt
    subplots.setdefault("layout", "constrained")
    return plt.subplots(**subplots)


def image_norm(img):
    """Colour scale of an image: asinh (linear below 1 % of the peak) for a high contrast (a
    point source: min < 10 % of max); linear for a low contrast; ±0.5 % around the value
    for a uniform image (a flat), whose rounding noise would else fill the colour bar.

    Parameters
    ----------
    img : array_like
        The image (non-finite values, e.g. saturated cells, are ignored).

    Returns
    -------
    matplotlib.colors.Normalize
        ``AsinhNorm`` or ``Normalize`` (0–1 when nothing is finite).
    """
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


def colorbar(fig, im, ax, label, min_gap=0.09):
    """Colour bar labelled ``label`` (with its unit) whose tick labels do not overlap: ticks
    closer than ``min_gap`` (fraction of the bar) to a kept one are dropped (asinh scales
    crowd ticks around 0).

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure.
    im : matplotlib.cm.ScalarMappable
        The image (or other mappable) the bar describes.
    ax : matplotlib.axes.Axes
        The axes the bar is taken from.
    label : str
        Label of the bar, with its unit.
    min_gap : float, optional
        Least distance between two ticks [fraction of the bar].

    Returns
    -------
    matplotlib.colorbar.Colorbar
        The colour bar.
    """
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
