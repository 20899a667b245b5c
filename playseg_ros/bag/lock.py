"""The lock a bag's writer holds while the bag is being written, so that `recover_bag` cannot finish it
under the writer's feet.

An exclusive ``flock`` on a lock file inside the bag directory: the kernel releases it when the holding
process dies (even by SIGKILL), so a lock left by a killed writer never blocks recovery. The file holds
the holder's pid and host, for the refusal message.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import socket
from pathlib import Path

from playseg_ros.bag.errors import BagError

LOCK_FILE = ".playseg-writer.lock"


class BagLock:
    """An exclusive lock on a bag directory; `release` unlocks it and removes the lock file."""

    def __init__(self, directory: Path, fd: int | None) -> None:
        self.directory = directory
        self._fd = fd

    @classmethod
    def acquire(cls, bag: Path, directory: Path) -> BagLock:
        """Lock ``directory`` (of ``bag``); a BagError naming the holder when another process has it."""
        path = directory / LOCK_FILE
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError:
            # A read-only bag: nobody can be writing it, and whatever needs writing will fail by itself.
            return cls(directory, None)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise BagError(
                bag,
                f"is still being written by {holder(directory) or 'another process'} "
                f"({path} is locked): stop that writer first (a killed writer's lock is released)",
            ) from None
        except OSError:
            # A file system without flock (some network mounts): work unlocked rather than not at all.
            os.close(fd)
            return cls(directory, None)
        try:
            same_file = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same_file = False
        if not same_file:  # its holder finished and removed it between our open and our flock
            os.close(fd)
            raise BagError(bag, f"{directory} was finished by another process meanwhile")
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()} {socket.gethostname()}\n".encode())
        return cls(directory, fd)

    def moved_to(self, directory: Path) -> None:
        """The locked directory was renamed (the writer's final rename): the lock file moved with it."""
        self.directory = directory

    def release(self) -> None:
        """Remove the lock file, then unlock (in this order: nobody can lock a file that is going away)."""
        if self._fd is None:
            return
        with contextlib.suppress(FileNotFoundError):
            (self.directory / LOCK_FILE).unlink()
        os.close(self._fd)  # closing the last descriptor releases the flock
        self._fd = None


def holder(directory: Path) -> str | None:
    """'process <pid> on <host>' from the lock file of ``directory`` (None when there is none)."""
    try:
        pid, host = (directory / LOCK_FILE).read_text().split()[:2]
    except (OSError, ValueError):
        return None
    return f"process {pid} on {host}"


def is_locked(directory: Path) -> bool:
    """Whether a live process holds the lock of ``directory`` (without taking it for long)."""
    try:
        fd = os.open(directory / LOCK_FILE, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return False
    finally:
        os.close(fd)
    return False
