"""Sphinx extension (and script): the layer table of ``docs/layout.md``, generated from
:data:`slicersim.layers.LAYERS`.

The table between the markers :data:`BEGIN` and :data:`END` of ``docs/layout.md`` is rewritten from
the layer list (lowest first, with each layer's path in the package), so the documented layers are
the ones ``tests/test_layers.py`` enforces.  ``tests/docs/test_layout_doc.py`` fails when the page
and the list disagree; ``python docs/_ext/layer_page.py`` rewrites the table.  As an extension
(``"layer_page"`` in ``conf.py``'s ``extensions``) it does the same when the documentation is built.
"""
from pathlib import Path

from _write import write_if_changed

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "layout.md"
BEGIN = "<!-- layers: generated from slicersim/layers.py by docs/_ext/layer_page.py; do not edit -->"
END = "<!-- end of the generated layers -->"


def _path(name):
    """The layer's place in the package: ``slicersim/name/`` or ``slicersim/name.py``."""
    package = ROOT / "slicersim"
    if (package / name).is_dir():
        return f"`slicersim/{name}/`"
    return f"`slicersim/{name}.py`"


def render():
    """The Markdown table of the layers, lowest first."""
    from slicersim.layers import LAYERS
    rows = ["| # | layer | content |", "|---|---|---|"]
    rows += [f"| {i} | {_path(name)} | {content} |" for i, (name, content) in enumerate(LAYERS)]
    return "\n".join(rows)


def page_text(text):
    """``text`` (the page) with the block between the markers replaced by :func:`render`."""
    head, sep, rest = text.partition(BEGIN)
    if not sep or END not in rest:
        raise ValueError(f"{PAGE}: the markers of the generated layer table are missing")  # internal: docs page
    tail = rest.partition(END)[2]
    return f"{head}{BEGIN}\n{render()}\n{END}{tail}"


def generate(path=PAGE):
    """Rewrite the layer table of ``path`` when it changed; returns the path."""
    write_if_changed(path, page_text(Path(path).read_text(encoding="utf-8")))
    return path


def setup(app):
    app.connect("builder-inited", lambda app: generate())
    return {"parallel_read_safe": True, "parallel_write_safe": True}


if __name__ == "__main__":
    import sys
    sys.path.insert(0, str(ROOT))
    print(generate())
