"""Atomic file and folder writes: nothing half-written is ever trusted.

A file is written to a temporary name in the same folder, flushed, fsynced and renamed over
the target; a folder is built under a temporary name and renamed into place. A process killed
mid-write (even with SIGKILL) leaves only ``*.tmp-*`` names behind, which readers ignore and
the next build removes.
"""
from __future__ import annotations

import errno
import glob
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path

from .errors import BuildError


#: below this many free bytes a failed write or a failed tool is put down to a full disk
DISK_FULL_BYTES = 1 << 20


def disk_full(path) -> bool:
    """True if the file system holding ``path`` has (nearly) no space left."""
    try:
        return shutil.disk_usage(path).free < DISK_FULL_BYTES
    except OSError:
        return False


def disk_error(path, e: OSError) -> BuildError:
    """The one-line error for an OSError met while writing ``path``."""
    if e.errno in (errno.ENOSPC, errno.EDQUOT):
        return BuildError(f"disk full while writing {path}")
    if e.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        return BuildError(f"cannot write {path}: permission denied")
    return BuildError(f"cannot write {path}: {e.strerror or e}")


@contextmanager
def atomic_path(target: str | os.PathLike):
    """Yield a temporary path next to `target`; on success it is renamed to `target`."""
    target = Path(target)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=target.name + ".tmp-", dir=target.parent)
        os.close(fd)
    except OSError as e:
        raise disk_error(target, e) from None
    try:
        yield Path(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except OSError as e:
        _unlink(tmp)
        raise disk_error(target, e) from None
    except BaseException:
        _unlink(tmp)
        raise


@contextmanager
def folder_lock(target: str | os.PathLike, on_wait=None):
    """Hold an exclusive lock on the folder ``target`` while the block runs: one process at a
    time builds it. The lock is a file ``.<name>.lock`` beside the folder, locked with
    ``flock``; the kernel drops the lock when the process ends, even on SIGKILL, so a killed
    build leaves no stale lock. Another process that wants the same folder waits for the
    lock. ``on_wait()`` is called once, before it waits. (Two runs of one preset started
    together both built it, and the second build's folder replaced the first's while the
    first was writing its traffic demand there: "randomTrips failed ...
    FileNotFoundError".) Without ``fcntl`` (Windows) there is no lock."""
    try:
        import fcntl
    except ImportError:         # pragma: no cover
        yield
        return
    target = Path(target)
    path = target.parent / f".{target.name}.lock"
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as e:
        raise disk_error(path, e) from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            if on_wait is not None:
                on_wait()
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)            # (and with it the lock)


def write_bytes(target, data: bytes) -> None:
    with atomic_path(target) as tmp:
        Path(tmp).write_bytes(data)


def write_text(target, text: str) -> None:
    write_bytes(target, text.encode("utf-8"))


def _unlink(p):
    try:
        os.unlink(p)
    except OSError:
        pass


def remove_stale_temps(folder: Path, name: str) -> None:
    """Remove the leftovers of killed builds of `name` in `folder` (not recursive):
    ``<name>.tmp-<pid>`` and ``<name>.tmp-old-<pid>`` whose process is gone. Another build's
    folder beside it, or one of the same name whose process still runs, is left alone (two
    builds into one parent folder at once: the second removed the first's folder while
    netconvert wrote into it)."""
    if not folder.is_dir():
        return
    for p in folder.glob(f"{glob.escape(name)}.tmp-*"):
        pid = p.name.rsplit("-", 1)[-1]
        if pid.isdigit() and _running(int(pid)):
            continue
        try:
            shutil.rmtree(p) if p.is_dir() else p.unlink()
        except OSError:
            pass


def _running(pid: int) -> bool:
    if pid == os.getpid():
        return False            # (this process's own leftover: a build that failed here)
    return process_alive(pid)


def process_alive(pid: int) -> bool:
    """Whether a process with this id exists (another user's counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:             # (another user's process)
        return True
    return True


def check_writable(folder: Path) -> None:
    """Fail early, with one line, when an output folder cannot be created or written."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".probe.tmp-", dir=folder)
        os.close(fd)
        os.unlink(tmp)
    except OSError as e:
        raise disk_error(folder, e) from None
