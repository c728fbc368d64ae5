"""A BOP dataset's images: depth PNG values to and from metres, and the bytes of colour, depth and mask PNGs.

Depth PNGs hold uint16 values; a value times the camera's ``depth_scale`` is millimetres.
"""

from __future__ import annotations

import cv2
import numpy as np

from posegrasp import io as pio

MM = 1e-3  # metres per millimetre
#: PNG settings, the fastest (and smallest) measured for each kind: unfiltered rows for noisy depth, plus
#: run-length deflate for masks; sub-filtered rows for colour images.
_PNG_NONE = (cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE)
_PNG_MASK = (*_PNG_NONE, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE)
_PNG_SUB = (cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_SUB)


def depth_to_png(depth_m: np.ndarray, depth_scale: float = 1.0) -> np.ndarray:
    """Depth (m) -> uint16 png values (value x depth_scale = mm); 0 stays 0, clipped at 65535."""
    v = np.round(np.asarray(depth_m, dtype=np.float64) / MM / depth_scale)
    return np.clip(np.nan_to_num(v, nan=0.0, posinf=0.0), 0, 65535).astype(np.uint16)


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
    return pio.encode_image(".png", depth_to_png(depth_m, depth_scale), _PNG_NONE)


def encode_mask(mask: np.ndarray) -> bytes:
    """A boolean mask as BOP mask PNG bytes (0/255, 8-bit)."""
    return pio.encode_image(".png", np.asarray(mask, bool).view(np.uint8) * np.uint8(255), _PNG_MASK)
