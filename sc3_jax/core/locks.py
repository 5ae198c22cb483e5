"""One writer per results store, episode store or training workdir.

Two sweeps on one ``--out`` would write every record twice; two trainers on one workdir log every step twice and
the second's checkpoint breaks the first. :func:`hold` takes an advisory ``fcntl.flock`` on ``DIR/.lock`` for as
long as the writer runs; a second writer gets a one-line ``UserError`` naming the holder's pid. The kernel drops the
lock when its process dies (SIGKILL included), so a stale lock of a dead process is simply taken over. Readers (a
report read while its sweep runs) take no lock.
"""
from __future__ import annotations

import contextlib
import fcntl
import os
import socket
from collections.abc import Iterator
from pathlib import Path

from sc3_jax.core.errors import UserError

LOCK_NAME = ".lock"


class Lock:
    """A held lock; :meth:`release` (or the end of the process) gives it back."""

    def __init__(self, directory: str | os.PathLike, what: str):
        self._fd: int | None = None
        self.path = Path(directory) / LOCK_NAME
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(self._fd, 200, 0).decode(errors="replace").strip() or "unknown"
            os.close(self._fd)
            self._fd = None
            raise UserError(f"{self.path.parent} is in use by another {what} (pid {holder}): wait for it to end or "
                            "stop it, or use another directory") from None
        os.ftruncate(self._fd, 0)
        os.pwrite(self._fd, f"{os.getpid()} on {socket.gethostname()}\n".encode(), 0)

    def release(self) -> None:
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    def __del__(self):  # a writer object dropped without release (its run ended by an exception)
        self.release()


def held(directory: str | os.PathLike) -> bool:
    """Whether a live writer holds ``directory``'s lock now. Asked without writing: a directory with no lock file has
    no writer, and a reader's brief shared probe of an existing one creates and changes nothing."""
    path = Path(directory) / LOCK_NAME
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # no lock file (never written by a writer), or none this reader may open
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)  # closing drops the probe's own lock
    return False


@contextlib.contextmanager
def hold(directory: str | os.PathLike, what: str) -> Iterator[Lock]:
    """Hold ``directory``'s lock for the block (``what``: the kind of writer, for the message)."""
    lock = Lock(directory, what)
    try:
        yield lock
    finally:
        lock.release()
