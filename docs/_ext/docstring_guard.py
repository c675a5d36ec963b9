"""Sphinx extension: show a docstring as preformatted text when it is not valid reStructuredText.

The package's docstrings are written for ``help()`` (aligned "name : description [unit]" lines,
``|x|`` for absolute values, ...).  Most render through napoleon; those that docutils cannot
parse would make ``sphinx-build -W`` fail.  After napoleon (priority 600 > 500), each docstring is
parsed once by docutils on the side; if that reports a warning or an error, the object's original
docstring is shown verbatim in a literal block instead, so nothing is lost and the build stays
clean.  The objects concerned are listed in ``docs/_generated/docstring_fallbacks.txt`` (fix their
docstrings in the package to get them rendered).
"""
import inspect
import io
import re
from pathlib import Path

from docutils.core import publish_doctree
from docutils.utils import Reporter

ROLE = re.compile(r":(?:[\w.-]+:)+`([^`]*)`")          # :func:`x`, :py:meth:`~a.b` -> ``x``
DIRECTIVE = re.compile(r"^(\s*)\.\. [\w:-]+::.*$", re.M)
FALLBACKS = []
#: docstrings that Sphinx warns about although the side parse above accepts them (Sphinx's own
#: parsing context differs): shown verbatim too
FORCE_VERBATIM = {
    "slicersim.Simulation": "napoleon reads its closing paragraph as a field list",
    "slicersim.SersicProfile.cell_fractions": "``oversampling``² (an inline literal followed by ²)",
}


def _problems(lines):
    """Messages (level ≥ warning) that docutils reports for the reST ``lines``."""
    text = ROLE.sub(lambda m: "``" + m.group(1).replace("`", "") + "``", "\n".join(lines))
    text = DIRECTIVE.sub(lambda m: m.group(1) + "..", text)        # Sphinx-only directives: comments
    stream = io.StringIO()
    publish_doctree(text, settings_overrides={"report_level": Reporter.WARNING_LEVEL, "halt_level": 5,
                                              "warning_stream": stream, "file_insertion_enabled": False,
                                              "raw_enabled": False})
    return [line for line in stream.getvalue().splitlines() if line.strip()]


def _guard(app, what, name, obj, options, lines):
    if not lines:
        return
    problems = [f"forced: {FORCE_VERBATIM[name]}"] if name in FORCE_VERBATIM else _problems(lines)
    if not problems:
        return
    doc = inspect.getdoc(obj) or "\n".join(lines)
    where = ""
    try:
        where = f"{inspect.getsourcefile(obj)}:{inspect.getsourcelines(obj)[1]}"
    except (TypeError, OSError):
        pass
    FALLBACKS.append(f"{name}  ({where})  {problems[0]}")
    lines[:] = ["::", ""] + ["    " + line for line in doc.splitlines()] + [""]


def _write_report(app, exception):
    if not FALLBACKS:                     # an incremental build read no docstring: keep the last list
        return
    path = Path(app.srcdir) / "_generated" / "docstring_fallbacks.txt"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(sorted(set(FALLBACKS))) + ("\n" if FALLBACKS else ""), encoding="utf-8")


def setup(app):
    app.connect("autodoc-process-docstring", _guard, priority=600)
    app.connect("build-finished", _write_report)
    return {"parallel_read_safe": False, "parallel_write_safe": True}
