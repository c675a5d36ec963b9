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
