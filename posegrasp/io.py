"""Atomic file writing: a killed run never leaves a partial file behind."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any, Callable

import numpy as np


def atomic_write(path: str | Path, write: Callable[[Path], None]) -> Path:
    """Call ``write(tmp)`` on a temporary file beside ``path``, fsync it and rename it to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        write(tmp_path)
        os.chmod(tmp_path, 0o644)  # mkstemp creates 0600 files
        with open(tmp_path, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp_path, path)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise
    return path


def write_bytes(path: str | Path, data: bytes) -> Path:
    """Atomically write raw bytes."""
    return atomic_write(path, lambda p: p.write_bytes(data))


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def dumps_json(obj: Any, indent: int | None = 2) -> str:
    """JSON text with numpy arrays and scalars converted."""
    return json.dumps(obj, indent=indent, default=_json_default)


def write_json(path: str | Path, obj: Any, indent: int | None = 2) -> Path:
    """Atomically write ``obj`` as JSON (numpy arrays become lists)."""
    return write_bytes(path, (dumps_json(obj, indent) + "\n").encode())


def write_png(path: str | Path, image: np.ndarray) -> Path:
    """Atomically write a uint8 (H, W[, 3]) or uint16 (H, W) image as PNG, deterministically."""
    import cv2

    img = image[..., ::-1] if image.ndim == 3 else image  # RGB -> BGR for OpenCV
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise OSError(f"could not encode PNG for {path}")
    return write_bytes(path, buf.tobytes())


def write_jpg(path: str | Path, rgb: np.ndarray, quality: int = 95) -> Path:
    """Atomically write an RGB uint8 image as JPEG."""
    import cv2

    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise OSError(f"could not encode JPEG for {path}")
    return write_bytes(path, buf.tobytes())


def read_image(path: str | Path) -> np.ndarray:
    """Read a PNG/JPEG as stored (RGB for colour, uint16 kept for depth)."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise OSError(f"cannot read image {path}: missing or corrupt")
    if img.ndim == 3:
        img = img[..., :3][..., ::-1].copy()
    return img
