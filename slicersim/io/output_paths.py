"""What an output may replace: only regular files, at a path naming a file; no physics here.

Every writer of the package (:mod:`slicersim.io.atomic`: HDF5 files, bytes, sets of files) and
the command line's early checks refuse, with the error class of the caller naming the path:

* a path ending with a separator (``--out newdir/``): it names a directory, not a file;
* an existing directory, FIFO, character or block device, socket, or a symbolic link to one,
  even with ``overwrite`` (run as root, ``--overwrite --out /dev/null`` would otherwise replace
  the device node);
* an existing file without ``overwrite``; a missing or read-only directory.

A symbolic link to a regular file is replaced by the new file; its target is never written.
"""
from __future__ import annotations

import os
import stat

from slicersim.errors import DatasetError

__all__ = ["output_path", "refuse_special", "check_output_path"]


def _kind(mode):
    """Words for a file type that is not a regular file."""
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def _who(name):
    return f"{name}: " if name else ""


def output_path(path, error_class=DatasetError, name=""):
    """The absolute path of an output *file*; a path ending with a separator names a directory
    and is refused (``error_class`` naming ``name``): it would otherwise write a file called
    like the directory."""
    text = os.fspath(path)
    if isinstance(text, bytes):
        text = os.fsdecode(text)
    if not text:
        raise error_class(f"{_who(name)}the output path is empty; give the path of a file, e.g. out.h5")
    if text.endswith(os.sep) or (os.altsep and text.endswith(os.altsep)):
        raise error_class(f"{_who(name)}{text!r} names a directory (it ends with {os.sep!r}); give the path of a "
                          "file, e.g. DIR/out.h5")
    return os.path.abspath(text)


def refuse_special(path, error_class=DatasetError, name=""):
    """Refuse (``error_class`` naming ``name``) an existing ``path`` that is not a regular file
    (a directory, FIFO, device or socket, or a symbolic link to one): only regular files are
    ever replaced.  A link to a regular file is replaced by the new file (its target is
    untouched); a dangling link likewise."""
    try:
        st = os.stat(path)                       # follows a link: what a write would reach
    except FileNotFoundError:
        return
    except OSError as exc:
        raise error_class(f"{_who(name)}cannot inspect {path}: [Errno {exc.errno}] {exc.strerror}") from None
    if not stat.S_ISREG(st.st_mode):
        link = " (a symbolic link to it)" if os.path.islink(path) else ""
        raise error_class(f"{_who(name)}{path} is {_kind(st.st_mode)}{link}, not a regular file: outputs only "
                          "ever replace regular files; choose another path")


def check_output_path(path, overwrite=False, error_class=DatasetError, name=""):
    """Refuse early an output file path (``error_class`` naming ``name``): one ending with a
    separator or naming an existing directory, anything but a regular file (FIFO, device,
    socket, a link to one: never replaced, even with ``overwrite``), an existing file without
    ``overwrite``, a missing or read-only directory.  Returns the absolute path."""
    full = output_path(path, error_class, name)
    if os.path.isdir(full):
        raise error_class(f"{_who(name)}{full} is a directory; give the path of a file inside it, e.g. "
                          f"{os.path.join(full, 'out.h5')}")
    refuse_special(full, error_class, name)
    if os.path.lexists(full) and not overwrite:
        hint = "--overwrite" if name.startswith("--") else "overwrite=True / --overwrite"
        raise error_class(f"{_who(name)}output file exists: {full} (pass {hint} to replace it)")
    directory = os.path.dirname(full)
    if not os.path.isdir(directory):
        raise error_class(f"{_who(name)}output directory does not exist (or is not writable): {directory}")
    if not os.access(directory, os.W_OK):
        raise error_class(f"{_who(name)}output directory is not writable: {directory}")
    return full
