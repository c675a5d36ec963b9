"""The benchmark registry (``benchmarks/registry.py``) covers every script, and its smoke arguments parse.

Cheap: no benchmark runs.  The arguments are checked against each script's own argparse parser,
captured by running the script's ``main`` with ``ArgumentParser.parse_args`` replaced (the parser is
built before any work starts), so an argument renamed in a script fails here rather than in CI's
``make bench-smoke``.
"""
import argparse
import ast
import importlib.util
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"


def _load(name):
    sys.path.insert(0, str(BENCH))
    try:
        spec = importlib.util.spec_from_file_location(f"_bench_{name}", BENCH / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    finally:
        sys.path.remove(str(BENCH))


registry = _load("registry")
NAMES = [b.name for b in registry.BENCHMARKS]


def _has_main(path):
    tree = ast.parse(path.read_text(encoding="utf-8"))
    return any(isinstance(n, ast.FunctionDef) and n.name == "main" for n in tree.body)


def test_every_script_is_registered_or_listed():
    scripts = {p.stem for p in BENCH.glob("*.py") if not p.name.startswith("_")}
    listed = set(NAMES) | set(registry.NOT_BENCHMARKS)
    assert sorted(scripts - listed) == [], "register these in benchmarks/registry.py (or list them as non-benchmarks)"
    assert len(NAMES) == len(set(NAMES)), "a benchmark is registered twice"
    assert not set(NAMES) & set(registry.NOT_BENCHMARKS)


@pytest.mark.parametrize("name", NAMES)
def test_entry_is_complete(name):
    bench = registry.BY_NAME[name]
    path = BENCH / bench.script
    assert path.is_file() and _has_main(path), f"{bench.script}: missing or without main()"
    assert bench.question.endswith("?") and bench.baseline and bench.acceptance
    assert bench.smoke_only_help or bench.smoke or bench.smoke_network is not None, "no smallest size"
    if bench.smoke_only_help:
        assert bench.note, "say why it has no smoke size"
    if bench.check is not None:
        assert bench.check.op in ("<=", ">=", "==")


class _Parsed(Exception):
    pass


@pytest.mark.parametrize("name", NAMES)
def test_smoke_arguments_parse(name, monkeypatch):
    """Each script's own parser accepts its smoke arguments (and ``--out`` where the runner adds it)."""
    bench = registry.BY_NAME[name]
    module = _load(name)
    original = argparse.ArgumentParser.parse_args
    seen = []

    def capture(parser, args=None, namespace=None):
        seen.append(parser)
        raise _Parsed

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", capture)
    monkeypatch.setattr(sys, "argv", [bench.script])
    with pytest.raises(_Parsed):
        module.main()
    parser = seen[0]
    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", original)
    out = ["--out", "/tmp/x"] if bench.out_arg else []
    for args in {tuple(bench.smoke), tuple(bench.smoke_network or ())}:
        parser.parse_args(list(args) + out)            # SystemExit (exit 2) if an argument is wrong


def test_runner_lists_everything(capsys):
    run = _load("run")
    assert run.main(["--list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in lines] == NAMES
    with pytest.raises(SystemExit) as exc:
        run.main(["no_such_benchmark"])
    assert exc.value.code == 2


def test_runner_smoke_commands():
    """Smoke mode: the registry's arguments and --out; help-only benchmarks just parse; full size: --out only."""
    run = _load("run")
    by = registry.BY_NAME
    argv, mode = run.command(by["checksum_cost"], True, False, Path("/tmp/o"))
    assert mode == "smoke" and argv[2:] == list(by["checksum_cost"].smoke) + ["--out", "/tmp/o"]
    argv, mode = run.command(by["mock_survey"], True, False, Path("/tmp/o"))
    assert mode == "help" and argv[2:] == ["--help"]
    argv, mode = run.command(by["checksum_cost"], False, False, Path("/tmp/o"))
    assert mode == "full" and argv[2:] == ["--out", "/tmp/o"]
    argv, mode = run.command(by["etc_vs_reference"], True, True, Path("/tmp/o"))
    assert mode == "smoke+ref" and "--skip-reference" not in argv


def test_check_evaluates():
    check = registry.Check("x", "summary.speedup", ">=", 300)
    assert check.evaluate({"summary": {"speedup": 301.0}}) is True
    assert check.evaluate({"summary": {"speedup": 299.0}}) is False
    assert check.evaluate({"summary": {}}) is None


def test_readme_table_is_current():
    """benchmarks/README.md holds the registry's table (``run.py --list --markdown``)."""
    run = _load("run")
    readme = (BENCH / "README.md").read_text(encoding="utf-8")
    assert run.readme_table(registry.BENCHMARKS) in readme, \
        "regenerate the table of benchmarks/README.md with `python benchmarks/run.py --list --markdown`"
