"""Where a command may write: one rule for every output path.

- An output **file** replaces an existing file only if this command wrote it (the marker it puts in what it
  writes: a JSON object's ``"written_by"``, a PNG's ``Software`` text chunk), or with ``--force``; never a file the
  command reads (one of its inputs, or a file inside an input folder), never a folder, FIFO, device or socket.
  A link in its place is replaced by the new file, not followed.
- An output **folder** is new, empty (empty subfolders and a lock file aside), or the command's own: it holds one
  of the command's records (``Record``: a file the command writes there, recognised by its contents, not by its
  name alone). ``posegrasp.lock`` applies it when it locks the folder (its lock file is opened without following a
  link).

Each refusal is one ``UserError`` line naming the path and what to do; nothing is written before it.
"""

from __future__ import annotations

import json
import os
import stat
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

from posegrasp.errors import UserError
from posegrasp.inputs import what_is

#: Key of the marker in a JSON object a command writes as its output file.
MARKER_KEY = "written_by"
#: Largest record or marked file read to recognise it (bytes).
_RECORD_BYTES = 64 << 20


def marker(command: str) -> str:
    """The marker text of ``command`` (e.g. ``posegrasp compare``)."""
    return f"posegrasp {command}"


def mark_json(doc: dict[str, Any], command: str) -> dict[str, Any]:
    """``doc`` with ``command``'s marker as its first key."""
    return {MARKER_KEY: marker(command), **{k: v for k, v in doc.items() if k != MARKER_KEY}}


def mark_image(data: bytes, command: str) -> bytes:
    """PNG bytes ``data`` with a ``Software`` text chunk naming ``command`` after the header chunk; JPEG bytes with
    a comment segment naming it after the start marker."""
    text = marker(command).encode()
    if data.startswith(b"\xff\xd8"):
        return data[:2] + b"\xff\xfe" + struct.pack(">H", len(text) + 2) + text + data[2:]
    body = b"tEXt" + b"Software\0" + text
    chunk = struct.pack(">I", len(body) - 4) + body + struct.pack(">I", zlib.crc32(body))
    return data[:33] + chunk + data[33:]


def _small_regular(path: Path) -> bytes | None:
    """The bytes of ``path`` if it is a regular file of at most ``_RECORD_BYTES`` (no link followed), else None."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError:
        return None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_size > _RECORD_BYTES:
            return None
        with os.fdopen(os.dup(fd), "rb") as f:
            return f.read(_RECORD_BYTES)
    except OSError:
        return None
    finally:
        os.close(fd)


def written_by(path: Path) -> str | None:
    """The command's marker in the file at ``path`` (a PNG or a JSON object), None if it has none."""
    data = _small_regular(path)
    if data is None:
        return None
    if data.startswith(b"\x89PNG\r\n\x1a\n"):
        i = 8
        while i + 8 <= len(data):
            n, kind = struct.unpack(">I", data[i:i + 4])[0], data[i + 4:i + 8]
            if kind == b"tEXt" and data[i + 8:i + 8 + n].startswith(b"Software\0"):
                return data[i + 17:i + 8 + n].decode(errors="replace")
            if kind in (b"IDAT", b"IEND"):
                return None
            i += 12 + n
        return None
    if data.startswith(b"\xff\xd8\xff\xfe") and len(data) > 6:
        n = struct.unpack(">H", data[4:6])[0]
        return data[6:4 + n].decode(errors="replace")
    doc = _json(data)
    return doc.get(MARKER_KEY) if isinstance(doc, dict) and isinstance(doc.get(MARKER_KEY), str) else None


def _json(data: bytes) -> Any:
    try:
        return json.loads(data)
    except (ValueError, RecursionError):
        return None


def _inside(p: Path, folder: Path) -> bool:
    return p == folder or folder in p.parents


def check_out_file(path: str | Path, command: str, inputs: Iterable[str | Path] = (), force: bool = False,
                   what: str = "", sealed: Iterable[str | Path] = (), option: str = "--out") -> Path:
    """``path`` (given as ``option``; "" for a file the command names itself) if ``command`` may write its output file
    there (the module's rule), else a one-line UserError. ``inputs``: files and folders the command reads (no file of
    them is replaced); ``sealed``: input folders nothing may be added to (a dataset: a new image there would change
    it); ``what``: the file the command writes (default: a file written by it)."""
    path = Path(path)
    real = path.parent.resolve() / path.name
    name, fix = (f"{option} {path}", "name a new file") if option else (str(path), "move it away")
    for i in sealed:
        if _inside(real, Path(i).resolve()):
            raise UserError(f"{name} is inside {i}, which this command reads; name a file outside it")
    if not os.path.lexists(path):
        return path
    st = os.lstat(path)
    if not (stat.S_ISREG(st.st_mode) or stat.S_ISLNK(st.st_mode)):
        raise UserError(f"{name} is {what_is(st.st_mode)}; {fix}")
    for i in inputs:
        if _inside(real, Path(i).resolve()) or _inside(path.resolve(), Path(i).resolve()):
            raise UserError(f"{name} is an input of this command ({i}); {fix}")
    if not force and (stat.S_ISLNK(st.st_mode) or written_by(path) != marker(command)):
        what = "a link" if stat.S_ISLNK(st.st_mode) else f"not {what or 'a file'} written by '{marker(command)}'"
        raise UserError(f"{name} already exists and is {what}; {fix}, or pass --force to replace it")
    return path


@dataclass(frozen=True)
class Record:
    """A file a command writes in its output folder, by which the folder is recognised as the command's: the files
    matching ``pattern`` (a glob below the folder), each a regular file that is a JSON object (for a JSON-lines
    file: its first line) holding every key of ``keys``, or whose bytes begin with ``head``. With neither, a file
    of that name is enough (only for names no user file has, such as the command's own temporary files)."""

    pattern: str
    keys: tuple[str, ...] = ()
    head: bytes = b""

    def matches(self, folder: Path) -> bool:
        """Whether ``folder`` holds a file that is this record."""
        return any(self._is(p) for p in folder.glob(self.pattern))

    def _is(self, p: Path) -> bool:
        if not (self.keys or self.head):
            return p.is_file() and not p.is_symlink()
        data = _small_regular(p)
        if data is None:
            return False
        if self.head:
            return data.startswith(self.head)
        doc = _json(data.split(b"\n", 1)[0] if p.suffix == ".jsonl" else data)
        if isinstance(doc, list) and doc:
            doc = doc[0]
        return isinstance(doc, dict) and all(k in doc for k in self.keys)

    def __str__(self) -> str:
        return self.pattern


def _holds_a_file(p: Path) -> bool:
    """Is ``p`` a file (of any kind), or a folder with one somewhere inside?"""
    return p.is_symlink() or not p.is_dir() or any(q.is_symlink() or not q.is_dir() for q in p.rglob("*"))


def check_own_folder(folder: Path, records: tuple[Record | str, ...], ignore: tuple[str, ...] = ()) -> None:
    """A one-line UserError if ``folder`` holds a file (besides those named in ``ignore``; empty folders do not
    count) but none of ``records`` (a str is a ``Record`` of that name alone): a folder this command did not
    write."""
    entries = sorted(p.name for p in folder.iterdir() if p.name not in ignore and _holds_a_file(p)) \
        if folder.is_dir() else []
    recs = [r if isinstance(r, Record) else Record(r) for r in records]
    if entries and not any(r.matches(folder) for r in recs):
        shown = ", ".join(entries[:3]) + (", ..." if len(entries) > 3 else "")
        raise UserError(f"{folder} is not empty ({shown}) and was not written by this command (it has none of "
                        f"{', '.join(map(str, recs))}); choose a new or empty --out")
