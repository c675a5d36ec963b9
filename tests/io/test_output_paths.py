"""Outputs replace only regular files: directories, FIFOs, devices and links to them are refused
(even with overwrite), a path ending with '/' is not written as a file; real files in tmp_path."""
import os
import stat

import numpy as np
import pytest

from slicersim.errors import DatasetError, ParameterError, RampFileError
from slicersim.io.atomic import AtomicH5File, atomic_bytes
from slicersim.io.file_set import write_files
from slicersim.io.output_paths import check_output_path
from slicersim.io.rampfile import RampWriter


def _fifo(tmp_path, name="pipe"):
    path = tmp_path / name
    os.mkfifo(path)
    return path


def _specials(tmp_path):
    """A FIFO, a symbolic link to it, and (as root) a character device like /dev/null."""
    fifo = _fifo(tmp_path)
    link = tmp_path / "link-to-pipe"
    link.symlink_to(fifo)
    out = [fifo, link]
    if os.geteuid() == 0:
        dev = tmp_path / "null"
        os.mknod(dev, stat.S_IFCHR | 0o666, os.makedev(1, 3))
        out.append(dev)
    return out


def _unchanged(path, before):
    st = os.lstat(path)
    assert (st.st_mode, st.st_ino, st.st_rdev) == before


@pytest.mark.parametrize("kind", [0, 1, 2])
def test_overwrite_never_replaces_a_fifo_a_link_to_one_or_a_device(tmp_path, kind):
    specials = _specials(tmp_path)
    if kind >= len(specials):
        pytest.skip("a device node needs root")
    path = specials[kind]
    st = os.lstat(path)
    before = (st.st_mode, st.st_ino, st.st_rdev)
    with pytest.raises(DatasetError, match="not a regular file"):
        atomic_bytes(path, b"data", overwrite=True)
    with pytest.raises(DatasetError, match="not a regular file"):
        write_files({path: b"data"}, overwrite=True)
    with pytest.raises(DatasetError, match="not a regular file"):
        with AtomicH5File(path, overwrite=True) as f:
            f.write("x", np.zeros(3))
    with pytest.raises(RampFileError, match="not a regular file"):
        RampWriter(path, 1, 2, (4, 4), overwrite=True).check()
    _unchanged(path, before)
    assert not [n for n in os.listdir(tmp_path) if n.startswith(".")]      # no temporary left


def test_dev_null_is_refused_as_root():
    """Run as root, --overwrite --out /dev/null replaced the device; the check refuses it before writing."""
    if os.geteuid() != 0:
        pytest.skip("/dev/null is replaceable only by root")
    st = os.lstat("/dev/null")
    with pytest.raises(RampFileError, match="--out: /dev/null is a character device"):
        check_output_path("/dev/null", True, RampFileError, "--out")
    assert stat.S_ISCHR(os.lstat("/dev/null").st_mode) and os.lstat("/dev/null").st_ino == st.st_ino


def test_a_link_to_a_regular_file_is_replaced_and_its_target_untouched(tmp_path):
    target = tmp_path / "target.txt"
    target.write_bytes(b"theirs")
    link = tmp_path / "out.bin"
    link.symlink_to(target)
    atomic_bytes(link, b"ours", overwrite=True)
    assert target.read_bytes() == b"theirs"
    assert not os.path.islink(link) and link.read_bytes() == b"ours"


@pytest.mark.parametrize("trailing", ["/", ""])
def test_a_directory_path_is_never_written_as_a_file(tmp_path, trailing):
    """`--out newdir/` wrote a *file* named newdir; an existing directory is refused too."""
    new = str(tmp_path / "newdir") + trailing
    if not trailing:
        os.mkdir(new)
    with pytest.raises(DatasetError, match="names a directory|is a directory"):
        atomic_bytes(new, b"x", overwrite=True)
    with pytest.raises(DatasetError, match="names a directory|is a directory"):
        with AtomicH5File(new, overwrite=True):
            pass
    with pytest.raises(ParameterError, match="--out: .*(names a directory|is a directory)"):
        check_output_path(new, True, ParameterError, "--out")
    assert os.path.isdir(new) if not trailing else not os.path.lexists(new.rstrip("/"))


def test_existing_file_and_missing_directory_are_named(tmp_path):
    out = tmp_path / "a.h5"
    out.write_bytes(b"x")
    with pytest.raises(ParameterError, match=r"--out: output file exists: .*a\.h5 \(pass --overwrite"):
        check_output_path(out, False, ParameterError, "--out")
    assert check_output_path(out, True, ParameterError, "--out") == str(out)
    with pytest.raises(ParameterError, match="--out: output directory does not exist"):
        check_output_path(tmp_path / "no" / "a.h5", True, ParameterError, "--out")


def test_an_empty_output_path_is_named_as_empty():
    """`--out ''` said "'' names a directory (it ends with '/')"."""
    with pytest.raises(ParameterError, match=r"^--out: the output path is empty; give the path of a file"):
        check_output_path("", True, ParameterError, "--out")
