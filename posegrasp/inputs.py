"""Reading input files, bounded: every file a command reads comes through here.

A path is read only if it is a regular file (a folder, FIFO, socket or device is refused at once, saying which,
and a FIFO is never opened for reading: ``os.stat`` first, then ``O_NONBLOCK`` and ``fstat`` on the open file),
no longer than its kind's size bound (``LIMITS``), under a path the system can name. "Does not exist" is said only
of a missing file (a broken link, a link loop and a permission problem each say so). JSON and TOML nest at most
``MAX_DEPTH`` deep; JSON has no duplicate key and no non-finite number (NaN, Infinity, 1e400); a PNG or JPEG
header's size is checked against ``MAX_PIXELS`` before the image is decoded. Each refusal is one line raised as
the caller's ``UserError`` kind (``error``), naming the file.
"""

from __future__ import annotations

import errno
import json
import math
import os
import re
import stat
import struct
import sys
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from posegrasp.errors import UserError

MB = 1 << 20
#: Size bounds (bytes) by kind of file.
LIMITS = {"json": 256 * MB, "jsonl": 2048 * MB, "toml": 4 * MB, "image": 512 * MB, "csv": 1024 * MB,
          "mesh": 2048 * MB, "weights": 8192 * MB, "text": 64 * MB}
#: Deepest nesting of arrays and tables accepted in a JSON or TOML file.
MAX_DEPTH = 64
#: Most pixels an image header may claim (10k x 10k).
MAX_PIXELS = 100_000_000
#: Longest path and path component accepted (Linux's PATH_MAX and NAME_MAX).
MAX_PATH, MAX_NAME = 4095, 255

_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISSOCK, "a socket"),
          (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"))


def what_is(mode: int) -> str:
    """Words for a file of ``st_mode`` ``mode``: "a folder", "a FIFO (named pipe)", ..., "a file"."""
    return next((w for test, w in _KINDS if test(mode)), "a file")


def _stat(path: Path, error: type[UserError]) -> os.stat_result:
    """``os.stat(path)`` (links followed), or ``error`` saying why there is no file to read."""
    text = os.fsdecode(path)
    if len(text.encode(errors="surrogateescape")) > MAX_PATH or any(len(c.encode(errors="surrogateescape")) > MAX_NAME
                                                                      for c in Path(text).parts):
        raise error(f"{text[:80]}...: the path is too long to name a file")
    try:
        return os.stat(path)
    except FileNotFoundError:
        why = "is a broken link" if os.path.lexists(path) else "does not exist"
        raise error(f"{path} {why}") from None
    except OSError as e:
        why = {errno.ELOOP: "is a link loop", errno.ENOTDIR: "does not exist (a folder above it is a file)",
               errno.ENAMETOOLONG: "is too long a path", errno.EACCES: "cannot be read (permission denied)"}
        raise error(f"{path} {why.get(e.errno, 'cannot be read: ' + str(e.strerror))}") from None


def check_file(path: str | Path, kind: str = "text", error: type[UserError] = UserError) -> int:
    """The size (bytes) of ``path`` if it is a regular file within ``LIMITS[kind]``, else ``error`` naming it."""
    path = Path(path)
    st = _stat(path, error)
    if not stat.S_ISREG(st.st_mode):
        raise error(f"{path} is not a file (it is {what_is(st.st_mode)})")
    if st.st_size > LIMITS[kind]:
        raise error(f"{path} is {st.st_size} bytes, more than a {kind} file may be ({LIMITS[kind]})")
    return st.st_size


def reason(e: UserError, path: str | Path) -> str:
    """The message of an error of this module about ``path`` without the path it starts with."""
    text = str(e)
    return text[len(str(path)):].lstrip(": ") if text.startswith(str(path)) else text


def read_bytes(path: str | Path, kind: str = "text", error: type[UserError] = UserError) -> bytes:
    """The bytes of the regular file ``path`` (``check_file``), read without ever blocking on a FIFO."""
    path = Path(path)
    check_file(path, kind, error)
    limit = LIMITS[kind]
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as e:
        raise error(f"{path} cannot be read: {e.strerror}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):  # replaced since the stat
            raise error(f"{path} is not a file (it is {what_is(st.st_mode)})")
        chunks, n = [], 0
        while n <= limit:
            chunk = os.read(fd, min(limit + 1 - n, 16 * MB))
            if not chunk:
                break
            chunks.append(chunk)
            n += len(chunk)
    except OSError as e:
        raise error(f"{path} cannot be read: {e.strerror}") from None
    finally:
        os.close(fd)
    if n > limit:
        raise error(f"{path} is more than a {kind} file may be ({limit} bytes)")
    return b"".join(chunks)


def read_text(path: str | Path, kind: str = "text", error: type[UserError] = UserError) -> str:
    """``read_bytes`` as UTF-8 text."""
    try:
        return read_bytes(path, kind, error).decode("utf-8")
    except UnicodeDecodeError:
        raise error(f"{path} is not UTF-8 text") from None


_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.S)
_TOML_STRING = re.compile(rb'"""[\s\S]*?"""|\'\'\'[\s\S]*?\'\'\'|"(?:[^"\\\n]|\\.)*"|\'[^\'\n]*\'|#[^\n]*')


def depth(data: bytes | str, toml: bool = False) -> int:
    """How deep the arrays and tables of a JSON (or TOML) text nest (brackets inside strings and comments not
    counted)."""
    import numpy as np

    raw = data.encode("utf-8", "surrogatepass") if isinstance(data, str) else data
    raw = (_TOML_STRING if toml else _STRING).sub(b"", raw)
    b = np.frombuffer(raw, np.uint8)
    steps = np.isin(b, (ord("["), ord("{"))).astype(np.int32) - np.isin(b, (ord("]"), ord("}"))).astype(np.int32)
    return int(np.cumsum(steps).max(initial=0))


def _no_duplicates(where: str, error: type[UserError]):
    def hook(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
        d = dict(pairs)
        if len(d) != len(pairs):
            seen: set[str] = set()
            dup = next(k for k, _ in pairs if k in seen or seen.add(k))
            raise error(f"{where}: key {dup!r} appears twice in one object")
        return d
    return hook


def _finite(where: str, error: type[UserError]):
    def parse(text: str) -> float:
        v = float(text)
        if not math.isfinite(v):
            raise error(f"{where}: number {text[:40]} is out of range (not finite)")
        return v
    return parse


def _constant(name: str) -> float:
    raise ValueError(f"{name} is not a JSON number")


def parse_json(data: bytes | str, where: str, error: type[UserError] = UserError, finite: bool = True) -> Any:
    """The JSON value of ``data`` (UTF-8): nested at most ``MAX_DEPTH`` deep, no duplicate key in an object, every
    number finite (``finite`` False: NaN and infinities are read, for a reader that names the key holding one,
    ``nonfinite``);
    ``error`` naming ``where`` otherwise."""
    try:
        text = data.decode("utf-8") if isinstance(data, bytes) else data
    except UnicodeDecodeError:
        raise error(f"{where}: expected UTF-8 JSON text, got binary data") from None
    if depth(text) > MAX_DEPTH:
        raise error(f"{where}: JSON nested more than {MAX_DEPTH} deep")
    try:
        if not finite:
            return json.loads(text, object_pairs_hook=_no_duplicates(where, error))
        return json.loads(text, object_pairs_hook=_no_duplicates(where, error), parse_float=_finite(where, error),
                          parse_constant=_constant)
    except UserError:
        raise
    except (ValueError, RecursionError) as e:  # json.JSONDecodeError, NaN / Infinity, an int of too many digits
        raise error(f"{where}: expected valid JSON ({str(e).splitlines()[0][:200]})") from None


def nonfinite(doc: Any, where: str = "") -> tuple[str, float] | None:
    """The key path (``a/0/b``) and value of the first NaN or infinity in the JSON value ``doc``, None if none."""
    if isinstance(doc, float) and not math.isfinite(doc):
        return where, doc
    items = doc.items() if isinstance(doc, dict) else enumerate(doc) if isinstance(doc, list) else ()
    for k, v in items:
        found = nonfinite(v, f"{where}/{k}" if where else str(k))
        if found:
            return found
    return None


def read_json(path: str | Path, error: type[UserError] = UserError, kind: str = "json", finite: bool = True) -> Any:
    """``parse_json`` of the regular file ``path`` (``read_bytes``)."""
    return parse_json(read_bytes(path, kind, error), str(path), error, finite)


def parse_toml(text: str, where: str, error: type[UserError] = UserError) -> dict[str, Any]:
    """The TOML document of ``text``: nested at most ``MAX_DEPTH`` deep (``tomllib.TOMLDecodeError`` as it is)."""
    import tomllib

    if depth(text, toml=True) > MAX_DEPTH:
        raise error(f"{where}: TOML nested more than {MAX_DEPTH} deep")
    try:
        return tomllib.loads(text)
    except RecursionError:
        raise error(f"{where}: TOML nested too deep") from None


def image_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) px claimed by a PNG's IHDR or a JPEG's frame header, None if neither is found."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24 and data[12:16] == b"IHDR":
        return struct.unpack(">II", data[16:24])
    if data[:2] != b"\xff\xd8":
        return None
    i = 2
    while i + 9 <= len(data):
        if data[i] != 0xFF:
            return None
        marker, n = data[i + 1], struct.unpack(">H", data[i + 2:i + 4])[0]
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            h, w = struct.unpack(">HH", data[i + 5:i + 9])
            return w, h
        i += 2 + n
    return None


def check_image_header(data: bytes, where: str, error: type[UserError] = UserError) -> None:
    """``error`` if the image header in ``data`` claims more than ``MAX_PIXELS`` pixels (or none)."""
    size = image_size(data)
    if size is not None and (size[0] * size[1] > MAX_PIXELS or 0 in size):
        raise error(f"{where}: the image header claims {size[0]}x{size[1]} px (at most {MAX_PIXELS} pixels)")


_CAPTURING = threading.Lock()
#: Words of the messages libpng and libjpeg print about a damaged image.
_LIBRARY_WORDS = ("libpng", "JPEG", "PNG", "IDAT", "iCCP")


@contextmanager
def library_output(fds: tuple[int, ...] = (2,)) -> Iterator[list[str]]:
    """What C libraries (libpng, OpenCASCADE) print to the file descriptors ``fds`` meanwhile, kept from the
    terminal: the yielded list holds its lines once the block ends (one capture at a time in the process)."""
    said: list[str] = []
    with _CAPTURING, tempfile.TemporaryFile() as tmp:
        sys.stdout.flush()
        sys.stderr.flush()
        saved = [os.dup(fd) for fd in fds]
        for fd in fds:
            os.dup2(tmp.fileno(), fd)
        try:
            yield said
        finally:
            for fd, old in zip(fds, saved):
                os.dup2(old, fd)
                os.close(old)
            tmp.seek(0)
            said += tmp.read().decode(errors="replace").splitlines()


def decode_image(data: bytes, where: str, error: type[UserError] = UserError) -> Any:
    """``cv2.imdecode`` of PNG or JPEG ``data`` (as stored: colour BGR, depth uint16), its header's size checked
    first (``check_image_header``); a damaged image (one the codec warns about, or fails on) is ``error`` naming
    ``where``, and the codec's own messages do not reach the terminal."""
    import cv2
    import numpy as np

    check_image_header(data, where, error)
    with library_output() as said:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    damage = [ln for ln in said if any(w in ln for w in _LIBRARY_WORDS)]
    others = [ln for ln in said if ln not in damage]
    if others:
        print("\n".join(others), file=sys.stderr)
    if img is None or damage:
        why = f" ({damage[0].strip()[:120]})" if damage else ""
        raise error(f"{where}: a truncated or corrupt image{why}")
    return img
