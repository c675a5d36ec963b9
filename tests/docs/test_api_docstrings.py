"""The API pages (docs/_ext/api_pages.py) render numpydoc docstrings: every name of
``slicersim.__all__`` and every entry point documents its parameters and what it returns."""
import importlib
import inspect
import re
import sys
from pathlib import Path

import pytest

import slicersim

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "docs" / "_ext"))

import api_pages  # noqa: E402  (docs/_ext is not a package)

ENTRY = re.compile(r"^(\*{0,2}\w+(?:\s*,\s*\*{0,2}\w+)*)\s*(?::.*)?$")


def sections(doc):
    """{title: [lines]} of the numpydoc sections of ``doc`` (a title underlined with dashes)."""
    lines = inspect.cleandoc(doc or "").splitlines()
    out, current = {}, None
    for i, line in enumerate(lines):
        nxt = lines[i + 1] if i + 1 < len(lines) else ""
        if line.strip() and nxt.strip() and set(nxt.strip()) == {"-"} and len(nxt.strip()) >= len(line.strip()):
            current = line.strip()
            out[current] = []
        elif current is not None and not (line.strip() and set(line.strip()) == {"-"}):
            out[current].append(line)
    return out


def documented_names(lines):
    """Parameter names of a Parameters section: its unindented ``name : type`` lines."""
    names = set()
    for line in lines:
        if line and not line[0].isspace():
            match = ENTRY.match(line)
            assert match, f"not a numpydoc parameter line: {line!r}"
            names.update(n.strip().lstrip("*") for n in match.group(1).split(","))
    return names


def public_api():
    """(dotted name, object) of slicersim.__all__ and of the entry points of the API pages."""
    objects = [(f"slicersim.{name}", getattr(slicersim, name)) for name in slicersim.__all__
               if not name.startswith("__")]
    for _, _, _, entries in api_pages.ENTRY_POINTS:
        for directive, dotted in entries:
            if directive == "automodule":
                module = importlib.import_module(dotted)
                objects += [(f"{dotted}.{name}", getattr(module, name)) for name in module.__all__]
            else:
                module, _, name = dotted.rpartition(".")
                objects.append((dotted, getattr(importlib.import_module(module), name)))
    return [(name, obj) for name, obj in objects
            if callable(obj) and not (inspect.isclass(obj) and issubclass(obj, BaseException))]


def parameters(obj):
    """Names of the parameters to document; ``**kwargs`` may instead be documented by the keywords
    it takes (then the section lists names that are not in the signature)."""
    params = inspect.signature(obj).parameters
    return [name for name in params if name not in ("self", "cls")]


def undocumented(obj, documented):
    params = inspect.signature(obj).parameters
    missing = set(parameters(obj)) - documented
    keywords = [n for n, p in params.items() if p.kind is inspect.Parameter.VAR_KEYWORD]
    if keywords and documented - set(params):
        missing -= set(keywords)
    return missing


def check_numpydoc(name, obj):
    """Functions and methods have Parameters (when they take any) and Returns; classes document
    their constructor in a Parameters section; every parameter of the signature is listed and
    every entry has an indented description."""
    found = sections(obj.__doc__)
    if parameters(obj):
        assert "Parameters" in found, f"{name}: no numpydoc Parameters section"
        missing = undocumented(obj, documented_names(found["Parameters"]))
        assert not missing, f"{name}: parameters not documented: {sorted(missing)}"
    for title in ("Parameters", "Returns"):
        lines = found.get(title, [])
        for i, line in enumerate(lines):
            if line and not line[0].isspace():
                assert i + 1 < len(lines) and lines[i + 1][:1].isspace(), \
                    f"{name}: {title} entry without an indented description: {line!r}"
    if not inspect.isclass(obj):
        assert "Returns" in found or "Yields" in found, f"{name}: no numpydoc Returns section"


@pytest.mark.parametrize("name, obj", public_api(), ids=lambda v: v if isinstance(v, str) else "")
def test_public_api_has_numpydoc_sections(name, obj):
    """Every name of ``slicersim.__all__`` and every entry point of the API pages."""
    check_numpydoc(name, obj)


def test_the_walk_sees_the_api():
    """The walk covers every exported name and the entry points (so the test above can fail)."""
    names = {name for name, _ in public_api()}
    assert {"slicersim.Simulation", "slicersim.Target", "slicersim.lazuli_etc",
            "slicersim.products.ramps.simulate", "slicersim.reduction.pipeline.reduce_exposure",
            "slicersim.validation.number"} <= names
    assert len(names) > 100
    assert sections("Doc.\n\nParameters\n----------\nx : int\n    X.\n") == {"Parameters": ["x : int", "    X."]}
    assert documented_names(["a, *args : int", "    Both.", "**kw", "    More."]) == {"a", "args", "kw"}


def public_methods():
    """(qualified name, function) of the documented public methods of the exported classes (the
    API pages render them), each once."""
    seen, out = set(), []
    for name in slicersim.__all__:
        cls = getattr(slicersim, name)
        if not inspect.isclass(cls) or issubclass(cls, BaseException):
            continue
        for attr, value in inspect.getmembers(cls):
            func = getattr(value, "__func__", value)
            if attr.startswith("_") or not inspect.isfunction(func) or not func.__doc__:
                continue
            if func.__qualname__ not in seen:
                seen.add(func.__qualname__)
                out.append((func.__qualname__, getattr(cls, attr)))
    return out


@pytest.mark.parametrize("name, method", public_methods(), ids=lambda v: v if isinstance(v, str) else "")
def test_public_methods_have_numpydoc_sections(name, method):
    """The methods on the API pages (``get_*``, ``setup_to_snr``, ``update``, ``show_*``, ...)."""
    check_numpydoc(name, method)


def test_the_method_walk_sees_the_pages():
    names = {name for name, _ in public_methods()}
    assert {"ObservationMixin.setup_to_snr", "ObservationMixin.get_spectrum", "Simulation.get_cube",
            "Simulation.update", "SpectrumSNRMixin.get_band_snr", "DetectorProducts.get_ramps",
            "DetectorProducts.show_spectrum"} <= names         # mixins' methods: by their own class
