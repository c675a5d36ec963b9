"""The layers of the package are true (issue 24): every import of every module, those inside
functions included, read with ``ast`` and grouped by subpackage (a top-level module is its own
group), against :data:`slicersim.layers.LAYERS`: no cycle between groups, no import of a later
layer, no private name imported from another group, no import of the package root from inside,
and the layer chain of the package docstring is the list."""
import ast
from pathlib import Path

import pytest

import slicersim
from slicersim import layers

PKG = Path(slicersim.__file__).resolve().parent
NAME = PKG.name


def _modules():
    """{dotted module name: path} of every Python file of the package."""
    out = {}
    for path in sorted(PKG.rglob("*.py")):
        parts = list(path.relative_to(PKG.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


MODULES = _modules()


def _group(module):
    """Layer of a dotted module name: its subpackage or top-level module (None: the root)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None


def _imports(module, path):
    """(line, imported module, imported name or None) of every import of ``module`` inside the
    package; ``from slicersim.x import y`` names module ``slicersim.x.y`` when that is a module."""
    is_pkg = path.name == "__init__.py"
    here = module.split(".") if is_pkg else module.split(".")[:-1]
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == NAME:
                    yield node.lineno, alias.name, None
        elif isinstance(node, ast.ImportFrom):
            base = here[:len(here) - node.level + 1] if node.level else []
            target = base + (node.module.split(".") if node.module else [])
            if not target or target[0] != NAME:
                continue
            for alias in node.names:
                sub = ".".join(target + [alias.name])
                if sub in MODULES:
                    yield node.lineno, sub, None
                else:
                    yield node.lineno, ".".join(target), alias.name


def _edges():
    """[(source group, target group, where, what)] of every import between two groups."""
    out = []
    for module, path in MODULES.items():
        for line, target, name in _imports(module, path):
            source, dest = _group(module), _group(target)
            if source != dest:
                out.append((source, dest, f"{path.relative_to(PKG.parent)}:{line}",
                            target + (f".{name}" if name else "")))
    return out


EDGES = _edges()


def _cycles(graph):
    """Strongly connected components with more than one node (Tarjan)."""
    index, low, stack, on, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_every_group_is_a_layer():
    groups = {_group(m) for m in MODULES} - {None}
    assert sorted(groups - set(layers.names())) == [], "modules or subpackages missing from LAYERS"
    assert sorted(set(layers.names()) - groups) == [], "LAYERS names that are not in the package"
    assert len(set(layers.names())) == len(layers.LAYERS)


def test_no_cycle_between_subpackages():
    graph = {}
    for source, dest, _, _ in EDGES:
        graph.setdefault(str(source), set()).add(str(dest))
    assert _cycles(graph) == []


def test_no_cycle_between_modules():
    """Module level too (function-level imports counted): the mapper's figure method importing the
    footprints module, which imported the mapper, was such a cycle."""
    graph = {}
    for module, path in MODULES.items():
        for _, target, _ in _imports(module, path):
            owner = target
            while owner not in MODULES and "." in owner:
                owner = owner.rpartition(".")[0]
            if owner in MODULES and owner != module and not module.startswith(owner + ".") and owner != NAME:
                graph.setdefault(module, set()).add(owner)
    assert _cycles(graph) == []


def test_no_upward_import():
    upward = [f"{where}: {source} imports {what} ({dest})" for source, dest, where, what in EDGES
              if source is not None and dest is not None and layers.rank(dest) >= layers.rank(source)]
    assert upward == []


def test_nothing_inside_imports_the_root():
    root = [f"{where}: {what}" for source, dest, where, what in EDGES if source is not None and dest is None]
    assert root == []


def _private(name):
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def test_no_private_name_imported_across_subpackages():
    private = [f"{where}: {what}" for source, dest, where, what in EDGES
               if dest is not None and any(_private(part) for part in what.split(".")[1:])]
    assert private == []


def test_docstring_lists_the_layers():
    doc = " ".join(slicersim.__doc__.split())
    assert " ".join(layers.chain().split()) in doc


def test_rank_refuses_an_unknown_layer():
    assert layers.rank("physics") < layers.rank("backends") < layers.rank("simulation")
    with pytest.raises(KeyError, match="not a layer"):
        layers.rank("nowhere")


def test_the_scan_sees_function_level_imports(tmp_path):
    """The scan counts an import inside a function (the cycles of issue 24 hid there)."""
    path = tmp_path / "m.py"
    path.write_text("def f():\n    from slicersim.etc.search import solve_readout\n", encoding="utf-8")
    assert list(_imports("slicersim.simulation", path)) == [(2, "slicersim.etc.search", "solve_readout")]
