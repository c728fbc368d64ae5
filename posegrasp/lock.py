"""An exclusive lock on an output folder, so two commands never write into one folder at once.

``folder_lock(out)`` takes ``fcntl.flock`` on ``<out>/.posegrasp.lock`` for the life of the ``with`` block and
writes the holder's PID into the file. The kernel releases a flock when its holder dies, however it dies, so a
lock left by a killed run is simply taken over (the PID then only tells who held it). A second process gets a
one-line ``UserError`` naming the holder. On release the file is removed, so a finished folder holds only its
results; a lock file found replaced after ``flock`` (removed by a holder releasing meanwhile) is opened again.
Folders the lock created and nothing was written into are removed on release. ``owns`` are the command's records
(``posegrasp.outputs.Record``); a folder that holds something but none of them is someone else's and is refused.
The lock file is opened without following a link, and only if it is a regular file.
"""

from __future__ import annotations

import errno
import fcntl
import os
import stat
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from posegrasp.errors import UserError
from posegrasp.inputs import what_is
from posegrasp.outputs import Record, check_own_folder

LOCK_FILE = ".posegrasp.lock"


def _holder(path: Path) -> str:
    """The PID recorded in a lock file, or ``?`` when it cannot be read yet."""
    try:
        return path.read_text().strip() or "?"
    except OSError:
        return "?"


def _open_locked(path: Path) -> int:
    """A descriptor of ``path`` holding its exclusive flock (retried while the file is being replaced)."""
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, 0o644)
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            os.close(fd)
            raise UserError(f"{path} is {what_is(mode)}, not a lock file; remove it or choose another --out")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise UserError(f"{path.parent} is in use by another posegrasp process (PID {_holder(path)}); "
                            "wait for it to finish or choose another --out") from None
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)  # the holder removed the file between our open and flock: lock the new one


def _created(folder: Path) -> list[Path]:
    """The folders ``mkdir(parents=True)`` of ``folder`` will create, deepest first."""
    made = []
    while not folder.exists() and folder != folder.parent:
        made.append(folder)
        folder = folder.parent
    return made


def check_owned(folder: Path, owns: tuple[Record | str, ...]) -> None:
    """``posegrasp.outputs.check_own_folder`` of ``folder``, its lock file aside."""
    check_own_folder(folder, owns, ignore=(LOCK_FILE,))


@contextmanager
def folder_lock(folder: str | Path, owns: tuple[Record | str, ...] = ()) -> Iterator[Path]:
    """Create ``folder`` if needed and hold its exclusive lock inside the block; yields the folder. Folders it
    created and that stay empty (a run that failed before writing) are removed again. With ``owns`` (the command's
    records, ``posegrasp.outputs.Record``), a non-empty folder holding none of them is refused (``check_owned``)."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise UserError(f"{folder} is a file, not a folder; choose another --out")
    made = _created(folder.absolute())
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd = _open_locked(folder / LOCK_FILE)
    except UserError:
        raise
    except OSError as e:
        why = "its lock file is a link" if e.errno == errno.ELOOP else e.strerror
        raise UserError(f"cannot lock output folder {folder}: {why}; choose another --out") from None
    path = folder / LOCK_FILE
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        if owns:
            check_owned(folder, owns)
        yield folder
    finally:
        path.unlink(missing_ok=True)  # while still holding the lock: a waiting opener sees another inode
        os.close(fd)
        for d in made:
            try:
                d.rmdir()
            except OSError:  # not empty: something was written
                break
