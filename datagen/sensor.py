"""The depth camera model's per-pixel steps in compiled code (``_sensor.c``, built with the package): the same
numbers as numpy's whole-image formulas (each float operation rounded alike), in one pass each (``noise.noisy_depth``
takes half numpy's time). Images (H, W) float32, metres along the optical axis, 0 = no measurement."""

from __future__ import annotations

import ctypes
from pathlib import Path

import numpy as np

from posegrasp.native import library

_P, _I, _F = ctypes.c_void_p, ctypes.c_int64, ctypes.c_float


class DepthNoise(ctypes.Structure):
    """The noise model's constants as float32 (``_sensor.c``'s ``struct depth_noise``)."""

    _fields_ = [(name, _F) for name in ("theta_max", "z_ref", "sigma_quad", "sigma_base", "half_pi", "sigma_angle",
                                        "fb", "step", "edge_dropout", "keep_below", "near", "far")]


def _library() -> ctypes.CDLL:
    lib = library(Path(__file__).parent, "_sensor", "the depth camera model's compiled steps")
    lib.posegrasp_depth_drop.restype = ctypes.c_int
    lib.posegrasp_depth_drop.argtypes = [_P, _I, _I, _F, _F, _F, _P]
    lib.posegrasp_shifted.restype = ctypes.c_int
    lib.posegrasp_shifted.argtypes = [_P, _I, _I, _P, _P, _P]
    lib.posegrasp_phase_args.restype = None
    lib.posegrasp_phase_args.argtypes = [_P, _P, _I, _F, _P, _P]
    lib.posegrasp_depth_noise.restype = None
    lib.posegrasp_depth_noise.argtypes = [_P, _P, _P, _P, _P, _I, ctypes.POINTER(DepthNoise), _P]
    lib.posegrasp_metric_depth.restype = None
    lib.posegrasp_metric_depth.argtypes = [_P, _I, _I, _F, _F, _F, _F, _P]
    return lib


LIB = _library()


def _c(a: np.ndarray, dtype: type) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=dtype)


def depth_drop(depth: np.ndarray, fb: float, tol_px: float, edge_threshold: float) -> np.ndarray:
    """(H, W) bool: the pixels of ``depth`` in the projector's shadow (its column u - fb / z, fb = f b in px m, more
    than ``tol_px`` right of the least such column of a valid pixel right of it) or on a depth edge (the 3 x 3
    neighbourhood, invalid as 1000 m, spans more than ``edge_threshold`` m; inf: none)."""
    depth = _c(depth, np.float32)
    out = np.empty(depth.shape, np.uint8)
    if LIB.posegrasp_depth_drop(depth.ctypes.data, *depth.shape, fb, tol_px, edge_threshold, out.ctypes.data):
        raise MemoryError("depth_drop: out of memory")
    return out.view(bool)


def shifted(depth: np.ndarray, uniforms: np.ndarray, thresholds: list[int]) -> np.ndarray:
    """(H, W): each pixel of ``depth`` taken from the pixel shifted by the offsets of its 16-bit ``uniforms`` (2, H, W)
    (x, then y): +1 from thresholds[2], +2 from [3], -1 below [1], -2 below [0]; clamped to the image."""
    depth, u, t = _c(depth, np.float32), _c(uniforms, np.uint16), np.asarray(thresholds, np.int32)
    out = np.empty_like(depth)
    if LIB.posegrasp_shifted(depth.ctypes.data, *depth.shape, u.ctypes.data, t.ctypes.data, out.ctypes.data):
        raise MemoryError("shifted: out of memory")
    return out


def phase_args(z: np.ndarray, grad: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray]:
    """The incidence angle's ``cv2.phase`` arguments: z where valid, else 1; and grad * k."""
    z, grad = _c(z, np.float32), _c(grad, np.float32)
    x, y = np.empty_like(z), np.empty_like(z)
    LIB.posegrasp_phase_args(z.ctypes.data, grad.ctypes.data, z.size, k, x.ctypes.data, y.ctypes.data)
    return x, y


def depth_noise(z: np.ndarray, theta: np.ndarray, normal: np.ndarray, uniform: np.ndarray, drop: np.ndarray,
                constants: DepthNoise) -> np.ndarray:
    """The measured depth (H, W) of the shifted depth ``z`` at incidence angles ``theta`` (rad), with standard normal
    and uniform draws per pixel and the ``drop`` (bool) pixels (``noise.noisy_depth``)."""
    arrays = [_c(z, np.float32), _c(theta, np.float32), _c(normal, np.float32), _c(uniform, np.float32),
              _c(drop, np.bool_)]
    out = np.empty_like(arrays[0])
    LIB.posegrasp_depth_noise(*(a.ctypes.data for a in arrays), out.size, ctypes.byref(constants), out.ctypes.data)
    return out


def metric_depth(raw: np.ndarray, c: float, d: float, near: float, far: float) -> np.ndarray:
    """Depth (H, W) in metres from a reversed-Z depth buffer ``raw`` (bottom row first): d / (raw + c) in float64,
    rounded to float32, 0 outside [near, far]; rows flipped, top row first."""
    raw = _c(raw, np.float32)
    out = np.empty_like(raw)
    LIB.posegrasp_metric_depth(raw.ctypes.data, *raw.shape, c, d, near, far, out.ctypes.data)
    return out
