"""One daemon per control socket: an advisory lock file beside the socket.

A second daemon started by mistake (by hand, beside the systemd one) used to fail to bind, and
on its way out delete the running daemon's socket. Now it takes this lock first, before
touching the socket, the link, the camera or the outputs, and exits when another holds it.
The lock is `fcntl.flock` on `<socket_path>.lock`: the kernel releases it when the holder
exits, however it exits, so a crash leaves no stale lock. The file itself stays (removing a
lock file races with the next daemon opening it); it holds the holder's pid, for the message.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
from pathlib import Path

EXIT_ALREADY_RUNNING = 75  # sysexits EX_TEMPFAIL: the lock is held; nothing was touched
LOCK_SUFFIX = ".lock"


class AlreadyRunning(RuntimeError):  # noqa: N818 -- names the situation, as the CLI prints it
    """Another daemon holds the lock of this control socket."""


def lock_path(socket_path: str | os.PathLike[str]) -> Path:
    """The lock file of a control socket."""
    return Path(f"{os.fspath(socket_path)}{LOCK_SUFFIX}")


class DaemonLock:
    """The exclusive lock of one control socket, held for the daemon's life."""

    def __init__(self, socket_path: str | os.PathLike[str]) -> None:
        self.path = lock_path(socket_path)
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        """True between acquire() and release()."""
        return self._fd is not None

    def acquire(self) -> None:
        """Take the lock now or raise AlreadyRunning (naming the holder); never waits."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read_pid(fd)
            os.close(fd)
            who = f"pid {holder}" if holder else "another process"
            raise AlreadyRunning(
                f"another orbitar daemon ({who}) holds {self.path}: it serves this control "
                "socket; this one exits without touching it"
            ) from None
        except BaseException:
            os.close(fd)
            raise
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd = fd

    def release(self) -> None:
        """Give the lock back (the file stays)."""
        fd, self._fd = self._fd, None
        if fd is not None:
            with contextlib.suppress(OSError):
                fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)


def _read_pid(fd: int) -> int | None:
    """The pid the holder wrote, if readable."""
    try:
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
        return int(text) if text.isdigit() else None
    except OSError:
        return None
