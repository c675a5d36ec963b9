"""Every code block of README.md runs as pasted.

Fenced ```python blocks are executed with ``exec`` in a fresh temporary directory; ```bash /
```console / ```sh blocks run through ``bash -e`` in a temporary directory with the virtual
environment's ``bin`` first on ``PATH`` (so ``slicersim`` and ``python`` are this project's);
``make ...`` lines are skipped (they are the set-up itself).  Blocks that take more than ~20 s on a
2-core machine (a full-detector ramp and its reduction, a Dask campaign) carry the ``slow`` marker.
Also checks the README's size and that README and docs hold no dated development notes.
"""
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
FENCE = re.compile(r"^```(\w*)[^\n]*\n(.*?)^```\s*$", re.M | re.S)
SHELLS = ("bash", "console", "sh", "shell")
#: a block containing one of these takes more than ~20 s
SLOW = ("--spectra", "campaign run")
#: history belongs in CHANGELOG.md, not in the README or the docs
HISTORY = re.compile(r"[0-9]+ Nov|until (now|this)|before this fix|has not been rerun")
MAX_README_LINES = 250


def readme_blocks():
    """(language, code, first line number) of every fenced block of README.md."""
    text = README.read_text(encoding="utf-8")
    return [(m.group(1).lower(), m.group(2), text.count("\n", 0, m.start()) + 1) for m in FENCE.finditer(text)]


def _shell_script(code):
    """The block's shell lines without the ``make`` ones (a leading ``$ `` prompt removed)."""
    lines = [re.sub(r"^\$ ", "", line) for line in code.splitlines()]
    return "\n".join(line for line in lines if not re.match(r"\s*make(\s|$)", line))


def _params():
    params = []
    for lang, code, line in readme_blocks():
        marks = [pytest.mark.slow] if any(s in code for s in SLOW) else []
        params.append(pytest.param(lang, code, id=f"README.md:{line}-{lang or 'text'}", marks=marks))
    return params


def test_readme_has_code_blocks_of_known_languages():
    blocks = readme_blocks()
    assert len(blocks) >= 5, "the README shows one example per job"
    unknown = [(lang, line) for lang, _, line in blocks if lang not in ("python",) + SHELLS]
    assert not unknown, f"README blocks in a language this test cannot run: {unknown}"


@pytest.mark.parametrize("lang,code", _params())
def test_readme_block_runs(lang, code, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    if lang == "python":
        exec(compile(code, "README.md", "exec"), {"__name__": "__readme__"})
        return
    script = _shell_script(code)
    if not script.strip():
        assert re.search(r"^\s*make\s", code, re.M), "a shell block with nothing to run"
        return                                           # the set-up commands themselves
    env = dict(os.environ, PATH=os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")]),
               MPLBACKEND="Agg")
    done = subprocess.run(["bash", "-e", "-o", "pipefail", "-c", script], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=1200)
    assert done.returncode == 0, f"exit {done.returncode}\n--- stdout\n{done.stdout[-3000:]}\n--- stderr\n{done.stderr[-3000:]}"


def test_readme_is_short():
    n = len(README.read_text(encoding="utf-8").splitlines())
    assert n <= MAX_README_LINES, f"README.md has {n} lines (at most {MAX_README_LINES}: details go to docs/)"


def test_no_history_in_readme_and_docs():
    files = [README] + [p for p in (ROOT / "docs").rglob("*")
                        if p.is_file() and p.suffix in (".md", ".rst", ".py", ".txt")
                        and not {"_build", "_generated"} & set(p.relative_to(ROOT / "docs").parts)]
    hits = [f"{p.relative_to(ROOT)}:{i}: {line.strip()[:80]}" for p in files
            for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1) if HISTORY.search(line)]
    assert not hits, "dated notes or history (they belong in CHANGELOG.md):\n" + "\n".join(hits)
