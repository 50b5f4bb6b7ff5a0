"""One process at a time on a hardware rig: an exclusive `flock` on a lock file named after the rig.

The kernel drops the lock when its process ends however it ends (SIGKILL included), so a crash never
leaves a rig locked; the file holds the owner's pid, to tell the next one who has it. Simulated rigs
live inside their process and need none.
"""

from __future__ import annotations

import fcntl
import os
import re
import tempfile
from pathlib import Path

from model.errors import UserInputError

SYSTEM_LOCK_DIR = Path("/run/lock")  # machine-wide, as a bench is: whichever store a process writes to


class RigInUseError(UserInputError):
    """Another process has the rig open."""


def lock_path(rig_name: str) -> Path:
    folder = SYSTEM_LOCK_DIR if os.access(SYSTEM_LOCK_DIR, os.W_OK) else Path(tempfile.gettempdir())
    slug = re.sub(r"[^A-Za-z0-9_.-]+", "-", rig_name).strip("-") or "rig"
    return folder / f"hdrig-rig-{slug}.lock"


class RigLock:
    """Held from `take` until `release` (or the process's end)."""

    def __init__(self, path: Path, fd: int) -> None:
        self.path, self._fd = path, fd

    @classmethod
    def take(cls, rig_name: str) -> RigLock:
        path = lock_path(rig_name)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            owner = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise RigInUseError(f"rig {rig_name!r} in use by pid {owner} (lock {path})") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        return cls(path, fd)

    def release(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)  # closing drops the flock
            self._fd = -1
