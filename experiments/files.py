"""Run-folder files: atomic writes, leftover temporaries, the folder's lock and the one-line errors.

Run folders are safe from faults and from each other (docs/robustness.md, "Run folders and faults"):
every file is written atomically (:func:`write_atomic`); a run holds an exclusive lock on its folder
(:func:`lock_folder`) for as long as it runs; a file-level failure is a :class:`RunFolderError`, one
line naming the file. Imports neither torch nor Hydra (``torchmm-run`` uses it before a run starts).
"""

from __future__ import annotations

import errno
import fcntl
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any


class RunFolderError(Exception):
    """A file of a run folder cannot be read or written, or the folder is in use: the message is one
    line that names the file (the command line prints it and exits with status 2)."""


class FolderInUse(RunFolderError):
    """Another process holds the run folder's lock (:func:`lock_folder`)."""


class UnitFileError(RunFolderError):
    """A unit's ``units/*.npz`` is missing, truncated or not the file the checkpoint recorded."""


#: temporary files of :func:`write_atomic`: ``.<name>.<random>.tmp`` next to the file
TMP_SUFFIX = ".tmp"


def error_reason(err: OSError) -> str:
    """An ``OSError`` in words (its ``strerror``, else its type): the end of a :class:`RunFolderError`."""
    return err.strerror or type(err).__name__


def write_atomic(path: Path, content: str | bytes | Callable[[Any], None]) -> None:
    """Write ``path`` atomically: into a temporary file in the same folder, flushed and fsynced, then
    moved over ``path`` with ``os.replace`` - a reader (or a run killed at any moment) sees the old file or
    the new one, never a part. ``content``: text, bytes, or ``write(binary_file)`` (e.g. ``np.savez``,
    ``figure.savefig``). Every file a run writes goes through here; a failure is a
    :class:`RunFolderError` naming ``path``."""
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=TMP_SUFFIX)
        with os.fdopen(fd, "wb") as f:
            if isinstance(content, str):
                f.write(content.encode())
            elif isinstance(content, (bytes, bytearray, memoryview)):
                f.write(content)
            else:
                content(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp's 0600 -> what open() would have made
        os.replace(tmp, path)
        tmp = None
    except OSError as err:
        raise RunFolderError(f"{path}: cannot write ({error_reason(err)})") from None
    finally:
        if tmp is not None:
            try:
                os.unlink(tmp)
            except OSError:
                pass


_UMASK: list[int] = []


def _umask() -> int:
    """The process's umask (read once: reading it means setting it, which is not thread-safe)."""
    if not _UMASK:
        mask = os.umask(0o022)
        os.umask(mask)
        _UMASK.append(mask)
    return _UMASK[0]


def remove_temporaries(folder: Path) -> None:
    """Remove what :func:`write_atomic` left behind in ``folder``, ``units/`` and ``figures/`` when a
    run was killed between writing and replacing (call it holding the folder's lock)."""
    for sub in (Path(folder), Path(folder) / "units", Path(folder) / "figures",
                Path(folder) / "figures" / "curves"):
        for tmp in sub.glob(f".*{TMP_SUFFIX}"):
            try:
                tmp.unlink()
            except OSError:
                pass


# -- the run folder's lock --------------------------------------------------------------------------
#: the lock file in a run (or sweep) folder: ``fcntl.flock``-ed by the process that runs there
LOCK_FILE = ".torchmm.lock"
#: the locks this process holds: real path of the folder -> the lock file's descriptor
LOCKS: dict[str, int] = {}


def lock_folder(folder: Path) -> bool:
    """Take the exclusive lock of ``folder`` (created if needed) for this process: ``flock`` on
    ``folder/.torchmm.lock``, released when the process ends, however it ends (SIGKILL too). True if
    taken now, False if this process holds it already. Another process holding it: :class:`FolderInUse`,
    and nothing in the folder is changed; a folder that cannot be written: :class:`RunFolderError`."""
    folder = Path(folder)
    key = os.path.realpath(folder)
    if key in LOCKS:
        return False
    lock = folder / LOCK_FILE
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    except OSError as err:
        raise RunFolderError(f"{folder}: cannot write there ({error_reason(err)})") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as err:
        holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
        os.close(fd)
        if err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            raise FolderInUse(f"{folder}: in use by another run (pid {holder}; lock {lock}); wait for it to "
                              "end or choose another folder") from None
        raise RunFolderError(f"{lock}: cannot lock ({error_reason(err)})") from None
    try:  # the lock file opens in a read-only folder too: check that the folder takes new files
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        probe_fd, probe = tempfile.mkstemp(dir=folder, prefix=".write-check.", suffix=TMP_SUFFIX)
        os.close(probe_fd)
        os.unlink(probe)
    except OSError as err:
        os.close(fd)
        raise RunFolderError(f"{folder}: cannot write there ({error_reason(err)})") from None
    LOCKS[key] = fd
    return True


def unlock_folder(folder: Path) -> None:
    """Release this process's lock of ``folder`` (if it holds it)."""
    fd = LOCKS.pop(os.path.realpath(folder), None)
    if fd is not None:
        os.close(fd)
