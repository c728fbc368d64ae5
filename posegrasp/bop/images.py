"""A BOP dataset's images: read and checked against the camera (``read``), depth PNG values to and from metres,
and the bytes of colour, depth and mask PNGs.

Depth PNGs hold uint16 values; a value times the camera's ``depth_scale`` is millimetres.
"""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
from isal import isal_zlib

from posegrasp import inputs
from posegrasp import io as pio
from posegrasp.errors import DatasetFileError

MM = 1e-3  # metres per millimetre
#: Colour PNGs: sub-filtered rows, fast deflate (OpenCV's encoder).
_PNG_SUB = (cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_SUB)
_PNG_SIGNATURE, _JPEG_SIGNATURE = b"\x89PNG\r\n\x1a\n", b"\xff\xd8"


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(data, zlib.crc32(kind)))


def encode_grey_png(image: np.ndarray) -> bytes:
    """An (H, W) uint8 or uint16 image as greyscale PNG bytes: unfiltered rows deflated by ISA-L at level 1,
    3-14x faster than libpng's fastest zlib setting for depth and masks, and files as small (the pixels decode
    identically; only the deflate stream differs)."""
    a = np.asarray(image)
    if a.ndim != 2 or a.dtype not in (np.uint8, np.uint16) or 0 in a.shape:
        raise ValueError(f"expected a non-empty (H, W) uint8 or uint16 image, got {a.dtype} {a.shape}")
    h, w = a.shape
    rows = np.zeros((h, 1 + w * a.itemsize), np.uint8)  # filter byte 0 (none), then the row's samples
    rows[:, 1:] = a.astype(a.dtype.newbyteorder(">"), copy=False).view(np.uint8).reshape(h, -1)
    header = struct.pack(">IIBBBBB", w, h, 8 * a.itemsize, 0, 0, 0, 0)
    return _PNG_SIGNATURE + _chunk(b"IHDR", header) + _chunk(b"IDAT", isal_zlib.compress(rows, 1)) \
        + _chunk(b"IEND", b"")


def depth_to_png(depth_m: np.ndarray, depth_scale: float = 1.0) -> np.ndarray:
    """Depth (m) -> uint16 png values (value x depth_scale = mm); 0 stays 0, clipped at 65535."""
    v = np.asarray(depth_m).astype(np.float64)  # a copy, then in place: 2.5x faster than new arrays at each step
    v /= MM
    v /= depth_scale
    np.round(v, out=v)
    v[~np.isfinite(v)] = 0.0  # NaN and +-inf (-inf would clip to 0 too)
    return np.clip(v, 0, 65535, out=v).astype(np.uint16)


def depth_from_png(png: np.ndarray, depth_scale: float = 1.0) -> np.ndarray:
    """BOP depth png values (x depth_scale = mm) -> depth float32 (H, W) in metres; 0 stays 0."""
    return np.asarray(png).astype(np.float32) * np.float32(depth_scale * MM)


def quantise_depth(depth_m: np.ndarray, depth_scale: float) -> np.ndarray:
    """Depth (m) in steps of ``depth_scale`` mm, float32: what a BOP depth png of it reads back as (bit for bit)."""
    return depth_from_png(depth_to_png(depth_m, depth_scale), depth_scale)


def encode_rgb(rgb: np.ndarray, ext: str, jpg_quality: int = 95) -> bytes:
    """An RGB uint8 image (H, W, 3) as BOP colour image bytes; ``ext`` ``jpg`` or ``png``."""
    if ext == "jpg":
        return pio.encode_image(".jpg", rgb, [cv2.IMWRITE_JPEG_QUALITY, jpg_quality])
    return pio.encode_image(".png", rgb, _PNG_SUB)


def encode_depth(depth_m: np.ndarray, depth_scale: float = 1.0) -> bytes:
    """A depth map (m) as BOP depth PNG bytes (uint16, value x depth_scale = mm)."""
    return encode_grey_png(depth_to_png(depth_m, depth_scale))


def encode_mask(mask: np.ndarray) -> bytes:
    """A boolean mask as BOP mask PNG bytes (0/255, 8-bit)."""
    return encode_grey_png(np.asarray(mask, bool).view(np.uint8) * np.uint8(255))


#: What each kind of image must be: (dtype, allowed channel counts, words for the message).
_KINDS = {"rgb": (np.uint8, (1, 3, 4), "an 8-bit colour (or grey) PNG/JPEG"),
          "depth": (np.uint16, (1,), "a 16-bit single-channel PNG (value x depth_scale = mm)"),
          "mask": (np.uint8, (1,), "an 8-bit single-channel PNG")}


def read(path: str | Path, kind: str, size: tuple[int, int] | None = None) -> np.ndarray:
    """Image ``path`` as stored (RGB (H, W, 3) or (H, W) uint8, depth (H, W) uint16), checked: a whole PNG or JPEG
    (not truncated), of ``kind`` (``rgb``, ``depth`` or ``mask``: dtype and channels as ``_KINDS``), ``size``
    (width, height) px when given, a depth image with some measurement, a mask not covering every pixel.
    ``DatasetFileError`` naming the file and what was expected otherwise."""
    path = Path(path)
    dtype, channels, what = _KINDS[kind]
    if not os.path.lexists(path):
        raise DatasetFileError(f"{path}: expected {what} (it does not exist)")
    data = inputs.read_bytes(path, "image", DatasetFileError)
    whole = (data.startswith(_PNG_SIGNATURE) and b"IEND" in data[-12:]) or \
            (data.startswith(_JPEG_SIGNATURE) and data.rstrip(b"\0").endswith(b"\xff\xd9"))
    if not whole:
        raise DatasetFileError(f"{path}: expected {what}, got a truncated or corrupt file ({len(data)} bytes)")
    img = inputs.decode_image(data, f"{path}: expected {what}, got", DatasetFileError)
    c = 1 if img.ndim == 2 else img.shape[2]
    if img.dtype != dtype or c not in channels:
        got = f"{img.dtype.itemsize * 8}-bit, {c} channel{'s' if c > 1 else ''}"
        raise DatasetFileError(f"{path}: expected {what}, got {got}")
    if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
        raise DatasetFileError(f"{path}: expected {size[0]}x{size[1]} px as camera.json, got {img.shape[1]}x{img.shape[0]}")
    if kind == "depth" and not img.any():
        raise DatasetFileError(f"{path}: expected depth measurements, got an image of zeros")
    if kind == "mask" and img.all():
        raise DatasetFileError(f"{path}: expected a mask of one object, got every pixel set")
    return pio.swap_red_blue(img) if c > 1 else img
