"""The command's allocator setting (slicersim/app/allocator.py)."""
import subprocess
import sys

import pytest

from slicersim.app import allocator


def test_the_command_keeps_freed_memory_and_callers_of_main_are_left_alone(monkeypatch):
    """``keep_freed_memory`` sets glibc's options where glibc is (True), refuses elsewhere (False);
    ``main`` calls it only for the command itself (argv None), not for a caller's ``main([...])``."""
    import platform
    from slicersim.app import cli
    glibc = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"
    calls = []
    monkeypatch.setattr(allocator, "keep_freed_memory", lambda: calls.append(1) or True)
    with pytest.raises(SystemExit):
        cli.main(["--help"])
    assert calls == []
    monkeypatch.setattr(sys, "argv", ["slicersim", "--help"])
    with pytest.raises(SystemExit):
        cli.main()
    assert calls == [1]
    monkeypatch.undo()
    code = "from slicersim.app.allocator import keep_freed_memory as k; print(k())"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == str(glibc)
    monkeypatch.setattr(allocator.platform, "libc_ver", lambda: ("musl", "1.2"))
    assert allocator.keep_freed_memory() is False


def test_the_command_turns_numpy_s_huge_page_requests_off_unless_the_user_chose(monkeypatch):
    """First touches of madvised huge pages stalled in compaction (3.5–4 s of system time per reduction
    on the 2-core VM): the command (argv None) turns NumPy's request off; a caller's ``main([...])``
    does not, nor does the command where ``NUMPY_MADVISE_HUGEPAGE`` is set."""
    from slicersim.app import cli
    switch = pytest.importorskip("numpy._core.multiarray")._set_madvise_hugepage
    before = switch(True)
    try:
        with pytest.raises(SystemExit):
            cli.main(["--help"])
        assert switch(True) is True                   # still on
        monkeypatch.setattr(sys, "argv", ["slicersim", "--help"])
        monkeypatch.setenv("NUMPY_MADVISE_HUGEPAGE", "1")
        with pytest.raises(SystemExit):
            cli.main()
        assert switch(True) is True                   # the user's choice stands
        monkeypatch.delenv("NUMPY_MADVISE_HUGEPAGE")
        with pytest.raises(SystemExit):
            cli.main()
        assert switch(True) is False                  # the command turned it off
    finally:
        switch(before)


@pytest.mark.parametrize("value", ["0", pytest.param("1", marks=pytest.mark.slow), pytest.param(" 1", marks=pytest.mark.slow),
                                   pytest.param("2", marks=pytest.mark.slow)])
def test_a_user_s_numpy_madvise_hugepage_stands_in_the_command(value):
    """Whatever value NumPy accepts, the command (argv None) leaves NumPy's setting as NumPy made it from
    the variable; ``no_huge_page_stalls`` returns False and never raises ("" and "garbage" already make
    ``import numpy`` fail, before slicersim is reached)."""
    import os
    code = ("import sys\n"
            "from numpy._core.multiarray import _set_madvise_hugepage as s\n"
            "before = s(True)\n"
            "s(before)\n"
            "from slicersim.app import cli\n"
            "sys.argv = ['slicersim', '--help']\n"
            "try:\n"
            "    cli.main()\n"
            "except SystemExit:\n"
            "    pass\n"
            "print(before, s(True))\n")
    env = dict(os.environ, NUMPY_MADVISE_HUGEPAGE=value)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True).stdout
    before, after = out.split()[-2:]
    assert before == after == str(bool(int(value)))


@pytest.mark.parametrize("value", ["", "0", "1", "garbage"])
def test_no_huge_page_stalls_never_raises_with_the_variable_set(monkeypatch, value):
    monkeypatch.setenv("NUMPY_MADVISE_HUGEPAGE", value)
    assert allocator.no_huge_page_stalls() is False
