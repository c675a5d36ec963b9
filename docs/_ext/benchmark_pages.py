"""Sphinx extension: one documentation page per benchmark family, from ``benchmarks/results``.

A family is a benchmark script (``benchmarks/NAME.py``) and every result file whose name starts
with its name (``closed_loop_defaults_ipc.json`` belongs to ``closed_loop_defaults.py``: the longest
script name that prefixes it); a result with no script (``gpu_h200.md``) is a family of its own.
Each page holds the script's description from ``benchmarks/README.md``, every Markdown table of
the family (headings shifted below the page title), every figure (copied next to the page) and,
for a JSON file without a Markdown twin, a short summary of its top-level content.  Pages are
written to ``docs/_generated/benchmarks/`` when the documentation is built (``make docs``), so
they always show the results that are committed.  Also runnable as a script.
"""
import ast
import json
import re
import shutil
from pathlib import Path

from _write import write_if_changed

ROOT = Path(__file__).resolve().parents[2]
BENCH = ROOT / "benchmarks"
RESULTS = BENCH / "results"
SUFFIXES = (".md", ".png", ".json")
HEADING = re.compile(r"^(#{1,6})\s+(.*)$")
IMAGE = re.compile(r"\]\(([^)\s]*/)?([^/)\s]+\.png)\)")


def scripts():
    """Names of the benchmark scripts (``benchmarks/*.py`` without a leading underscore)."""
    return sorted(p.stem for p in BENCH.glob("*.py") if not p.name.startswith("_"))


def families():
    """{family name: [result paths]} of ``benchmarks/results`` (only .md, .png, .json)."""
    names = sorted(scripts(), key=len, reverse=True)
    out = {}
    for path in sorted(RESULTS.iterdir()):
        if not path.is_file() or path.suffix not in SUFFIXES:
            continue
        stem = path.stem
        family = next((n for n in names if stem == n or stem.startswith(n + "_")), stem)
        out.setdefault(family, []).append(path)
    return out


def descriptions():
    """{script name: one-line description} from the tables and sections of benchmarks/README.md."""
    text = (BENCH / "README.md").read_text(encoding="utf-8") if (BENCH / "README.md").is_file() else ""
    out = {}
    for m in re.finditer(r"^\|\s*`([\w]+)\.py`\s*\|\s*(.+?)\s*\|\s*$", text, re.M):
        out[m.group(1)] = m.group(2)
    for m in re.finditer(r"^##\s+`([\w]+)\.py`\s*[—-]\s*(.+)$", text, re.M):
        out[m.group(1)] = m.group(2).strip()
    for name in scripts():                       # else the first sentence of the script's docstring
        if name not in out:
            try:
                doc = ast.get_docstring(ast.parse((BENCH / f"{name}.py").read_text(encoding="utf-8"))) or ""
            except (SyntaxError, UnicodeDecodeError):
                doc = ""
            first = " ".join(doc.strip().split("\n\n")[0].split())
            if first:
                out[name] = first if len(first) <= 200 else first[:197] + "..."
    return out


def registry():
    """{name: registry entry} of ``benchmarks/registry.py`` (question, baseline, acceptance), or {}."""
    import importlib.util
    path = BENCH / "registry.py"
    if not path.is_file():
        return {}
    spec = importlib.util.spec_from_file_location("_benchmark_registry", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return dict(module.BY_NAME)


def shift_headings(text, top=2):
    """Shift the Markdown headings of ``text`` so that its highest one is at level ``top``."""
    levels = [len(m.group(1)) for line in text.splitlines() if (m := HEADING.match(line))]
    if not levels:
        return text
    delta = top - min(levels)
    lines = []
    fence = False
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            fence = not fence
        m = None if fence else HEADING.match(line)
        lines.append(f"{'#' * min(6, len(m.group(1)) + delta)} {m.group(2)}" if m else line)
    return "\n".join(lines)


def json_summary(path, max_lines=40):
    """The top-level content of a JSON result, compactly (long lists shortened)."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except ValueError as exc:
        return f"(not readable as JSON: {exc})"

    def shorten(v, depth=0):
        if isinstance(v, dict):
            return {k: shorten(x, depth + 1) for k, x in v.items()} if depth < 2 else f"{{{len(v)} keys}}"
        if isinstance(v, list):
            return [shorten(x, depth + 1) for x in v[:3]] + ([f"... {len(v) - 3} more"] if len(v) > 3 else [])
        if isinstance(v, str) and len(v) > 80:
            return v[:77] + "..."
        return v

    lines = json.dumps(shorten(data), indent=1, ensure_ascii=False, default=str).splitlines()
    if len(lines) > max_lines:
        lines = lines[:max_lines] + [f"... ({len(lines) - max_lines} more lines)"]
    return "\n".join(lines)


def page(family, paths, outdir, about):
    """Markdown text of one family's page; copies its figures into ``outdir``."""
    script = BENCH / f"{family}.py"
    title = f"`{family}.py`" if script.is_file() else f"`{family}`"
    parts = [f"# {title}", ""]
    if family in about:
        parts += [about[family], ""]
    entry = registry().get(family)
    if entry is not None:
        parts += [f"- Question: {entry.question}", f"- Baseline: {entry.baseline}",
                  f"- Acceptance: {entry.acceptance}", ""]
    if script.is_file():
        parts += [f"Script: `benchmarks/{family}.py`; results: `benchmarks/results/{family}*`.", ""]
    stems = {p.stem for p in paths if p.suffix == ".md"}
    for path in paths:
        if path.suffix == ".md":
            text = path.read_text(encoding="utf-8")
            text = IMAGE.sub(lambda m: f"]({m.group(2)})" if (RESULTS / m.group(2)).is_file() else m.group(0), text)
            if not HEADING.match(text.lstrip().splitlines()[0] if text.strip() else ""):
                parts += [f"## `{path.name}`", ""]
            parts += [shift_headings(text, 2), ""]
        elif path.suffix == ".png":
            shutil.copy2(path, outdir / path.name)
            parts += [f"## Figure `{path.name}`", "", f"![{path.stem}]({path.name})", ""]
        elif path.stem not in stems:
            parts += [f"## `{path.name}` (summary)", "", "```text", json_summary(path), "```", ""]
    return "\n".join(parts).rstrip() + "\n"


def generate(outdir):
    """Write every family page and an index into ``outdir``; returns the index path."""
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    about = descriptions()
    fams = families()
    for family, paths in fams.items():
        write_if_changed(outdir / f"{family}.md", page(family, paths, outdir, about))
    lines = ["# Benchmark results", "",
             "One page per benchmark family, generated from the files committed in `benchmarks/results/`",
             "when the documentation is built.  Run a benchmark with `.venv/bin/python benchmarks/NAME.py`",
             "(`make bench` runs them all); each writes its JSON, most a Markdown table and a figure.",
             "Timings were taken on a shared 2-core VM with the PoCL CPU runtime unless a page says",
             "otherwise; the JSON files record the machine and its load.", "",
             "| family | files | about |", "|---|---:|---|"]
    for family, paths in fams.items():
        desc = about.get(family, "").replace("|", "\\|")
        lines.append(f"| [{family}]({family}.md) | {len(paths)} | {desc} |")
    lines += ["", "```{toctree}", ":hidden:", ""] + list(fams) + ["```", ""]
    index = outdir / "index.md"
    write_if_changed(index, "\n".join(lines))
    return index


def _on_builder_inited(app):
    generate(Path(app.srcdir) / "_generated" / "benchmarks")


def setup(app):
    app.connect("builder-inited", _on_builder_inited)
    return {"parallel_read_safe": True, "parallel_write_safe": True}


if __name__ == "__main__":
    print(generate(Path(__file__).resolve().parents[1] / "_generated" / "benchmarks"))
