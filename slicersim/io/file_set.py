"""Several files published together: all of them under their final names, or none (a set of
files that only make sense together, e.g. a footprint table and its figure); no physics here.

Each file is first written whole to a temporary beside it; the renames are journalled in a lock
file so that a writer killed among them is finished (or undone) by the next one
(:func:`recover_interrupted`).
"""
from __future__ import annotations

import os

from slicersim.errors import DatasetError
from slicersim.io.atomic import (one_line, output_path, publish, refuse_special, remove_stale_temporaries,
                                 temporary_path)

__all__ = ["write_files", "recover_interrupted"]


def _write_temporary(path, data):
    """A new fsync'd temporary for ``path`` holding ``data`` (bytes, or a callable writing to
    a binary file object); removed again on any error."""
    tmp = temporary_path(path)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o666)
    try:
        if callable(data):
            with os.fdopen(fd, "wb", closefd=False) as fh:
                data(fh)
        else:
            view, done = memoryview(data).cast("B"), 0
            while done < len(view):
                done += os.write(fd, view[done:])
        os.fsync(fd)
    except BaseException:
        os.close(fd)
        _remove(tmp)
        raise
    os.close(fd)
    return tmp


def _remove(path):
    try:
        os.remove(path)
    except FileNotFoundError:
        pass


def _same_file(path, ino):
    try:
        return os.lstat(path).st_ino == ino
    except OSError:
        return False


class _SetLock:
    """Exclusive ``fcntl.flock`` on the file ``path`` (released by the kernel when its holder
    dies, even by kill -9); it journals the holder's renames and is removed when it is done."""

    def __init__(self, path):
        self.path, self.fd = path, None

    def __enter__(self):
        import fcntl
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o666)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX)
                if _same_file(self.path, os.fstat(fd).st_ino):   # else removed by the previous holder
                    self.fd = fd
                    return self
            except BaseException:
                os.close(fd)
                raise
            os.close(fd)

    def __exit__(self, *exc):
        try:
            _remove(self.path)             # while holding it: a waiter sees it removed and retries
        finally:
            os.close(self.fd)

    def journal(self, items):
        """Record the renames about to be made: [[temporary, final path, inode]] (or none)."""
        import json
        os.ftruncate(self.fd, 0)
        if items:
            os.pwrite(self.fd, json.dumps(items).encode(), 0)
            os.fsync(self.fd)

    def recover(self):
        """Finish the renames of a writer killed among them: all its files when each is still
        there (as temporary or renamed), else none of them."""
        import json
        raw = os.pread(self.fd, 1 << 22, 0)
        try:
            items = json.loads(raw) if raw else []
        except ValueError:                 # torn journal: killed before any rename
            items = []
        done = [_same_file(path, ino) for _, path, ino in items]
        whole = all(d or os.path.lexists(tmp) for d, (tmp, _, _) in zip(done, items))
        for d, (tmp, path, _) in zip(done, items):
            if whole and not d:
                os.replace(tmp, path)
            elif not whole:
                _remove(path if d else tmp)
        self.journal(None)


def _lock_path(first, lock_name=None):
    first = os.path.abspath(os.fspath(first))
    return os.path.join(os.path.dirname(first), f".{lock_name or os.path.basename(first)}.lock")


def recover_interrupted(first, lock_name=None):
    """Complete (or remove) the set whose first file is ``first`` if its writer was killed
    while renaming it in (:func:`write_files`); nothing to do without a lock file."""
    if os.path.lexists(_lock_path(first, lock_name)):     # a writer holds it, or died holding it
        with _SetLock(_lock_path(first, lock_name)) as lock:
            lock.recover()


def write_files(files, overwrite=False, error_class=DatasetError, lock_name=None):
    """Write several files and publish them together: all of them or none; returns the paths.

    ``files``: {path: bytes, or a callable writing to a binary file object}.  Each is written
    to a temporary next to its final path (fsync'd; stale temporaries of dead writers there
    are removed first, :func:`remove_stale_temporaries`); only when all are complete are they
    renamed in (``overwrite``: replacing files, else refusing if any exists), under an
    exclusive lock, the file ``.<lock_name>.lock`` in the first path's directory (default: its
    name; ``fcntl.flock``: a killed writer never holds it), so that concurrent writers of a set
    publish one after the other.  The lock file journals the renames: a writer killed among
    them is completed (or its partial set removed) by the next one.  On any error, every
    temporary and every file already renamed in is removed (neither, never a mixture: with
    ``overwrite`` the set's previous files are then gone) and ``error_class`` is raised.
    """
    paths = [output_path(p, error_class) for p in files]
    for path in paths:
        refuse_special(path, error_class)
    if len(set(paths)) != len(paths) or not paths:
        raise error_class(f"write_files needs distinct paths, got {paths}")
    temps = []
    try:
        if len(paths) > 1:
            recover_interrupted(paths[0], lock_name)
        for directory in dict.fromkeys(os.path.dirname(p) for p in paths):
            remove_stale_temporaries(directory)
        if not overwrite:
            _refuse_existing(paths, error_class)
        for path, data in zip(paths, files.values()):
            temps.append(_write_temporary(path, data))
        if len(paths) == 1:
            publish(temps[0], paths[0], overwrite, error_class)
        else:
            with _SetLock(_lock_path(paths[0], lock_name)) as lock:
                lock.recover()
                _publish_set(lock, temps, paths, overwrite, error_class)
        temps = []
    except OSError as exc:
        if isinstance(exc, error_class):
            raise
        raise error_class(f"cannot write {paths[min(len(temps), len(paths) - 1)]}: {one_line(exc)}") from exc
    finally:
        for tmp in temps:
            _remove(tmp)
    return paths


def _refuse_existing(paths, error_class):
    for path in paths:
        if os.path.lexists(path):
            raise error_class(f"output file exists: {path} (pass overwrite=True / --overwrite to replace it)")


def _publish_set(lock, temps, paths, overwrite, error_class):
    """Rename the complete temporaries in (the caller holds the set's lock)."""
    if not overwrite:
        _refuse_existing(paths, error_class)
    inodes = [os.lstat(t).st_ino for t in temps]
    lock.journal([[t, p, i] for t, p, i in zip(temps, paths, inodes)])
    done = []
    try:
        for tmp, path in zip(temps, paths):
            publish(tmp, path, overwrite, error_class)
            done.append(path)
    except BaseException:
        for path, ino in zip(done, inodes):
            if _same_file(path, ino):
                _remove(path)
        raise
    finally:
        lock.journal(None)
