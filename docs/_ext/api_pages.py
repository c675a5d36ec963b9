"""Sphinx extension: the API reference pages, generated from ``slicersim.__all__``.

Writes ``docs/_generated/api/*.rst`` when the documentation is built: one page for the names
exported by ``import slicersim`` (grouped by the subpackage that defines them, so a name added to
``__all__`` appears without editing the docs), and one per main entry point of the subpackages.
The text of every entry is the object's own docstring (``sphinx.ext.autodoc`` with napoleon's
numpy style).  Also runnable as a script.
"""
import importlib
import inspect
from pathlib import Path

from _write import write_if_changed

#: entry points of the subpackages: (page, title, intro, [(directive, dotted name)])
ENTRY_POINTS = [
    ("etc", "Exposure-time calculator", "The batch ETC; the single-target ETC is a method of every target "
     "(`setup_to_snr`, see the top-level page).",
     [("autofunction", "slicersim.etc.solve_many"),
      ("autoclass", "slicersim.etc.solve.SolveOptions")]),
    ("ramps", "Raw ramps", "Raw MACC ramps of a rate image, with or without detector effects.",
     [("autofunction", "slicersim.products.ramps.simulate"),
      ("autoclass", "slicersim.products.ramps.RampParameters"),
      ("autoclass", "slicersim.products.ramps.RampIO"),
      ("autoclass", "slicersim.products.ramps.RunOptions"),
      ("autoclass", "slicersim.products.ramps.DetectorMaps"),
      ("autoclass", "slicersim.products.ramps.RampResult"),
      ("autofunction", "slicersim.io.rampfile.read_ramps")]),
    ("campaign", "Survey plans and campaigns", "Survey planning (batch ETC of a population) and campaigns on Dask.",
     [("autofunction", "slicersim.campaign.plan.plan_survey"),
      ("autoclass", "slicersim.campaign.plan.SurveyOptions"),
      ("autoclass", "slicersim.campaign.plan.SurveyPlan"),
      ("autofunction", "slicersim.campaign.plan.plot_time_and_volume"),
      ("autoclass", "slicersim.campaign.spec.CampaignSpec"),
      ("autofunction", "slicersim.campaign.runner.run_campaign"),
      ("autofunction", "slicersim.campaign.runner.campaign_status")]),
    ("reduction", "Reduction", "Raw ramps back to rates, cubes and spectra.",
     [("autofunction", "slicersim.reduction.pipeline.reduce_exposure"),
      ("autoclass", "slicersim.reduction.options.ReduceOptions"),
      ("autofunction", "slicersim.reduction.ramp_fit.fit_ramps"),
      ("autoclass", "slicersim.reduction.ramp_fit.FitOptions"),
      ("autoclass", "slicersim.reduction.ramp_fit.RateProduct")]),
    ("plotting", "Figures", "The figures of the `show_*` methods and of the demo, from arrays and models "
     "(matplotlib; colour bars and axes carry units).",
     [("automodule", "slicersim.plotting.figures"),
      ("automodule", "slicersim.plotting.spectra"),
      ("automodule", "slicersim.plotting.images")]),
    ("validation", "Validation", "`slicersim.validation` is the one module that checks user input: "
     "every checker raises a `slicersim.errors.SlicersimError` subclass whose message names the parameter.",
     [("automodule", "slicersim.validation")]),
    ("errors", "Errors", "Every error a user can cause is a subclass of `SlicersimError`; the subclasses "
     "also derive from `ValueError`, `OSError` or `RuntimeError`, so `except ValueError` keeps working.",
     [("automodule", "slicersim.errors")]),
]

#: objects whose docstring autodoc cannot render cleanly: {dotted name: hand-written reST}
HANDWRITTEN = {}


def _exists(dotted):
    module, _, name = dotted.rpartition(".")
    try:
        return hasattr(importlib.import_module(module), name)
    except ImportError:
        try:
            importlib.import_module(dotted)
            return True
        except ImportError:
            return False


def _entry(directive, dotted, options=()):
    if dotted in HANDWRITTEN:
        return HANDWRITTEN[dotted].rstrip() + "\n\n"
    lines = [f".. {directive}:: {dotted}"]
    lines += [f"   :{o}" if ": " in o else f"   :{o}:" for o in options]      # "name" or "name: value"
    return "\n".join(lines) + "\n\n"


def _inherited(cls, exported):
    """``inherited-members`` option of an exported class: the members it inherits from bases that
    have no entry of their own (a mixin such as ``DetectorProducts``: ``Target.get_ramps``), not
    those of exported bases (documented there), of ``Versioned`` (caching) or of ``object``."""
    skip = [base.__name__ for base in cls.__mro__[1:] if base in exported]
    return "inherited-members: " + ", ".join(dict.fromkeys([*skip, "Versioned", "object"]))


def _title(text, char="="):
    return f"{text}\n{char * len(text)}\n\n"


def top_level_page():
    """reST of the names of ``slicersim.__all__``, grouped by defining subpackage."""
    import slicersim
    groups = {}
    exported = {getattr(slicersim, n) for n in slicersim.__all__ if inspect.isclass(getattr(slicersim, n))}
    for name in slicersim.__all__:
        if name.startswith("__"):
            continue
        obj = getattr(slicersim, name)
        module = getattr(obj, "__module__", "slicersim") or "slicersim"
        part = module.split(".")[1] if module.count(".") else "slicersim"
        groups.setdefault(part, []).append((name, obj))
    text = _title("Top-level API (``import slicersim``)")
    text += ("The names exported by ``slicersim`` (``slicersim.__all__``), grouped by the subpackage that "
             "defines them.  Units are given in each docstring; see also :doc:`../../units` and "
             ":doc:`../../api_conventions`.\n\n.. currentmodule:: slicersim\n\n")
    for part in sorted(groups):
        text += _title(f"slicersim.{part}" if part != "slicersim" else "slicersim", "-")
        for name, obj in groups[part]:
            if inspect.isclass(obj):
                text += _entry("autoclass", f"slicersim.{name}", ("members", _inherited(obj, exported)))
            elif callable(obj):
                text += _entry("autofunction", f"slicersim.{name}")
            else:
                text += _entry("autodata", f"slicersim.{name}")
    return text


def entry_page(title, intro, entries):
    text = _title(title) + intro + "\n\n"
    for directive, dotted in entries:
        if not _exists(dotted):
            continue                       # renamed by a refactoring: the page keeps building
        options = ("members",) if directive in ("autoclass", "automodule") else ()
        text += _entry(directive, dotted, options)
    return text


def generate(outdir):
    outdir = Path(outdir)
    write_if_changed(outdir / "slicersim.rst", top_level_page())
    for page, title, intro, entries in ENTRY_POINTS:
        write_if_changed(outdir / f"{page}.rst", entry_page(title, intro, entries))
    index = (_title("API reference") + "Generated from the docstrings (numpy style).\n\n"
             ".. toctree::\n   :maxdepth: 1\n\n   slicersim\n"
             + "".join(f"   {page}\n" for page, *_ in ENTRY_POINTS))
    write_if_changed(outdir / "index.rst", index)
    return outdir / "index.rst"


def _on_builder_inited(app):
    generate(Path(app.srcdir) / "_generated" / "api")


def setup(app):
    app.connect("builder-inited", _on_builder_inited)
    return {"parallel_read_safe": True, "parallel_write_safe": True}


if __name__ == "__main__":
    print(generate(Path(__file__).resolve().parents[1] / "_generated" / "api"))
