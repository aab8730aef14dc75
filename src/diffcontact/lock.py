"""One writer per output folder: an exclusive lock file that names its holder.

``output_lock(folder)`` holds ``folder/.lock`` (an ``flock`` on it, released by the operating system when the
process ends, however it ends) and writes the holder's pid, host and command into it.  A second command on the
same folder waits up to ``wait`` seconds, then raises :class:`LockError` naming the holder and the lock file.  A
lock left by a dead process holds no ``flock`` and is taken over.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from diffcontact.errors import DiffContactError
from diffcontact.files import check_output

LOCK_NAME = ".lock"


class LockError(DiffContactError, RuntimeError):
    """Another process is writing to the same output (the message names its pid and the lock file)."""


def _holder(path: Path) -> str:
    try:
        info = json.loads(path.read_text())
        return f"pid {info['pid']} on {info['host']} ({info['command']}, since {info['since']})"
    except (OSError, ValueError, KeyError, TypeError):
        return "another process (its record is not written yet)"


@contextmanager
def output_lock(folder: str | Path, wait: float = 0.0, poll: float = 0.2) -> Iterator[Path]:
    """Hold the lock of ``folder`` (created if missing, removed again if left empty) for the ``with`` block; yields
    the lock file's path.

    Raises LockError if another process holds it after ``wait`` seconds (polled every ``poll`` s)."""
    folder = check_output(folder, "output folder", folder=True)
    made = not folder.exists()
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / LOCK_NAME
    deadline = time.monotonic() + wait
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            if time.monotonic() >= deadline:
                raise LockError(
                    f"{folder} is being written by {_holder(path)}: lock {path}; wait for it to end, or write "
                    "to another output"
                ) from None
            time.sleep(poll)
            continue
        try:  # (the file may have been removed by its previous holder between our open and flock: then retry)
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        record = dict(
            pid=os.getpid(),
            host=socket.gethostname(),
            command=" ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
            since=time.strftime("%Y-%m-%d %H:%M:%S"),
        )
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(record) + "\n").encode(), 0)
        yield path
    finally:
        path.unlink(missing_ok=True)  # (before the flock is released: a waiting process then makes a new file)
        os.close(fd)
        if made and not any(folder.iterdir()):  # (a command that failed before writing leaves no empty folder)
            folder.rmdir()
