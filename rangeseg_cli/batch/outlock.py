"""One batch at a time in an output folder: a lock file in OUT.

Two runs into one OUT would both process every image and write over each
other's files and manifest. A batch holds ``OUT/rangeseg-run.lock`` while
it runs: an exclusive ``flock`` on it (released by the kernel when the
process ends, however it ends), and in it the pid, host and start time of
the run, which a second run names when it refuses to start. A lock whose
run has ended (killed with SIGKILL, a power loss) is free: the next run
takes it over. Where ``flock`` is not supported (some network
filesystems), the file alone decides: a lock naming a process that no
longer runs on this host is stale and taken over.

Output folders on an object store (``s3://...``) are not locked: a store
has no lock a killed run would release; do not run two batches into one
URL at once.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import socket
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from ..errors import OutputError
from . import io
from .io import Location

LOCK = "rangeseg-run.lock"
log = logging.getLogger(__name__)

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None  # type: ignore[assignment]


@contextmanager
def held(out: Location, command: str = "run") -> Iterator[None]:
    """Hold the lock of the output folder ``out`` for the block (created if missing).

    Parameters
    ----------
    out
        The output folder; a URL is not locked (see the module notes).
    command
        Recorded in the lock, for the message of a run refused meanwhile.

    Raises
    ------
    OutputError
        One line naming the running batch (pid, host, start time) when
        another run holds the lock.
    """
    if not isinstance(out, Path):
        yield
        return
    io.make_folder(out)
    path = out / LOCK
    fd = _acquire(path)
    try:
        _record(fd, command)
        yield
    finally:
        _release(path, fd)


def _acquire(path: Path) -> int:
    """An open descriptor of ``path`` holding its lock (the file re-created if replaced)."""
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as exc:  # a read-only folder or disk, no permission
            raise OutputError(f"{path}: cannot write ({exc.strerror or exc})") from None
        try:
            if not _lock(fd, path):
                raise OutputError(_busy(path, _holder(fd)))
            if _same_file(fd, path):  # not deleted by a run that ended meanwhile
                return fd
        except BaseException:
            os.close(fd)
            raise
        os.close(fd)


def _lock(fd: int, path: Path) -> bool:
    """Whether this process now holds the lock of ``fd`` (``False``: another run does)."""
    if fcntl is not None:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except OSError as exc:
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                return False
            log.debug("%s: flock not supported (%s); the pid in it decides", path, exc)
    holder = _holder(fd)
    return not _alive(holder)


def _alive(holder: dict[str, Any]) -> bool:
    """Whether the run a lock file names still runs (another host's: assumed so)."""
    pid = holder.get("pid")
    if not isinstance(pid, int) or pid == os.getpid():
        return False
    if holder.get("host") != socket.gethostname():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _same_file(fd: int, path: Path) -> bool:
    try:
        return os.path.samestat(os.fstat(fd), os.stat(path))
    except FileNotFoundError:
        return False


def _holder(fd: int) -> dict[str, Any]:
    """What a lock file says of its run (empty when unreadable or not yet written)."""
    try:
        data = json.loads(os.pread(fd, 4096, 0) or b"{}")
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def _busy(path: Path, holder: dict[str, Any]) -> str:
    """The one line of a run refused because ``holder`` runs into the same folder."""
    who = (f"`rangeseg {holder.get('command', 'run')}` (pid {holder.get('pid', '?')} on "
           f"{holder.get('host', '?')}, started {holder.get('started', '?')})")
    return (f"{path.parent}: another batch is running into this folder: {who}; wait for it "
            f"to end or stop it, or choose another output folder (its lock: {path})")


def _record(fd: int, command: str) -> None:
    """Write this run's pid, host, start time and command into the held lock."""
    stale = _holder(fd)
    if stale.get("pid") not in (None, os.getpid()):
        log.info("taking over the lock of an ended run (pid %s on %s)", stale.get("pid"),
                 stale.get("host"))
    text = json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                       "started": time.strftime("%Y-%m-%d %H:%M:%S %z"),
                       "command": command}).encode()
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, text, 0)
    except OSError as exc:  # a full disk: the lock holds; only the message lacks the pid
        log.debug("cannot record this run in its lock: %s", exc)


def _release(path: Path, fd: int) -> None:
    """Delete the lock file, then let it go (a run waiting on it re-creates it)."""
    try:
        path.unlink()
    except OSError:  # a read-only or vanished folder: the lock ends with the descriptor
        pass
    os.close(fd)
