"""Sphinx extension: the command-line reference, generated from the argparse parser.

Walks :func:`slicersim.app.cli.build_parser` and every sub-parser (``slicersim etc``,
``slicersim survey plan``, ...) and writes ``docs/_generated/cli.md``: one section per command
with its description and its ``--help`` text (every option with its default), so the page can
never disagree with the program.  Also runnable as a script: ``python docs/_ext/cli_reference.py``.
"""
import argparse
import os
from pathlib import Path

from _write import write_if_changed

HEADER = """# Command-line reference

Generated from the argument parser (`slicersim.app.cli.build_parser()`) when the documentation
is built: this is exactly what `slicersim COMMAND --help` prints.  User errors (bad values,
impossible requests, existing outputs, Ctrl-C) print one line `slicersim: error: ...` and exit
with status 2; an internal error prints its traceback and a line asking to report it, and exits
with status 3 (see [API conventions](../api_conventions.md)).

"""


def _subcommands(parser):
    """(name, sub-parser) pairs of ``parser``'s sub-parsers, in the order they were added."""
    for action in parser._actions:                      # argparse has no public walk
        if isinstance(action, argparse._SubParsersAction):
            seen = set()
            for name, sub in action.choices.items():
                if id(sub) not in seen:
                    seen.add(id(sub))
                    yield name, sub


def walk(parser, path=()):
    """Yield (command words, parser) for ``parser`` and every sub-parser below it, depth first."""
    yield path, parser
    for name, sub in _subcommands(parser):
        yield from walk(sub, path + (name,))


def render():
    """The Markdown text of the CLI reference."""
    from slicersim.app.cli import build_parser
    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"                       # a stable line width for the help texts
    try:
        parts = [HEADER]
        for words, parser in walk(build_parser()):
            title = " ".join(("slicersim",) + words)
            level = "#" * min(2 + max(len(words) - 1, 0), 4)
            parts.append(f"{level} `{title}`\n\n")
            parts.append("```text\n" + parser.format_help().rstrip() + "\n```\n\n")
        return "".join(parts)
    finally:
        if old is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = old


def generate(outdir):
    """Write ``outdir/cli.md``; returns its path."""
    path = Path(outdir) / "cli.md"
    write_if_changed(path, render())
    return path


def _on_builder_inited(app):
    generate(Path(app.srcdir) / "_generated")


def setup(app):
    app.connect("builder-inited", _on_builder_inited)
    return {"parallel_read_safe": True, "parallel_write_safe": True}


if __name__ == "__main__":
    print(generate(Path(__file__).resolve().parents[1] / "_generated"))
