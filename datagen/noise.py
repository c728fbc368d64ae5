"""Sensor models applied to rendered images: a structured-light depth camera and colour camera effects.

Depth (structured light): the projector sits ``baseline`` to the right of the camera, so background just
left of a nearer surface is in its shadow (no measurement); pixels are sampled with a small random lateral
shift; axial Gaussian noise grows with distance and at grazing angles (Nguyen et al. 2012); depth is
quantised in disparity (1/8 px); pixels at depth edges and a few random ones drop out. Depth in metres along
the optical axis, 0 = no measurement. Every draw comes from the given rng.
"""

from __future__ import annotations

import cv2
import numpy as np

from posegrasp.datagen.config import DepthNoiseConfig, RgbNoiseConfig


def projector_shadow(depth: np.ndarray, fx: float, baseline: float, tol_px: float = 0.5) -> np.ndarray:
    """(H, W) bool: pixels the projector (``baseline`` m along +x) cannot light because a nearer surface
    to their right blocks its ray. A pixel u projects to projector column u - fx b / z; it is shadowed when
    some pixel further right lands at a smaller projector column."""
    disp = np.zeros_like(depth)
    np.divide(np.float32(fx * baseline), depth, out=disp, where=depth > 0)
    up = np.arange(depth.shape[1], dtype=np.float32)[None, :] - disp
    right_min = np.minimum.accumulate(up[:, ::-1], axis=1)[:, ::-1]  # min over this pixel and those right of it
    out = np.zeros(depth.shape, bool)
    out[:, :-1] = up[:, :-1] > right_min[:, 1:] + np.float32(tol_px)
    return out & (depth > 0)


def depth_edges(depth: np.ndarray, threshold: float) -> np.ndarray:
    """(H, W) bool: pixels whose 3x3 neighbourhood spans more than ``threshold`` m (invalid counts as far)."""
    d = np.where(depth > 0, depth, np.float32(1e3)).astype(np.float32)
    k = np.ones((3, 3), np.uint8)
    return (cv2.dilate(d, k) - cv2.erode(d, k)) > threshold


def gaussian(shape: tuple[int, ...], std: float, rng: np.random.Generator, dtype=np.float32) -> np.ndarray:
    """Gaussian noise N(0, std) of ``shape`` (rounded for integer dtypes), from OpenCV's generator seeded by
    ``rng`` (3x faster than numpy's)."""
    cv2.setRNGSeed(int(rng.integers(1 << 30, 1 << 31)))
    return cv2.randn(np.empty(shape, dtype), 0.0, float(std))


def pixel_shifts(shape: tuple[int, int], sigma: float, rng: np.random.Generator) -> np.ndarray:
    """(2, H, W) int8 offsets: N(0, sigma) px rounded to the nearest pixel, |offset| <= 2 (16-bit uniforms
    compared with the normal CDF at +-0.5 and +-1.5 px)."""
    from math import erf, sqrt

    cdf = [0.5 * (1 + erf(x / (sigma * sqrt(2)))) for x in (-1.5, -0.5, 0.5, 1.5)] if sigma > 0 else [0, 0, 1, 1]
    t = [int(round(c * 65536)) for c in cdf]
    u = rng.integers(0, 1 << 16, (2, *shape), dtype=np.uint16)
    k = (u >= t[2]).view(np.int8) + (u >= t[3]).view(np.int8)
    k -= (u < t[1]).view(np.int8)
    k -= (u < t[0]).view(np.int8)
    return k


def noisy_depth(depth: np.ndarray, K: np.ndarray, cfg: DepthNoiseConfig, rng: np.random.Generator,
                near: float, far: float) -> np.ndarray:
    """Structured-light measurement of a clean depth map (H, W) float32 m; returns float32 m, 0 invalid."""
    H, W = depth.shape
    fx = float(K[0, 0])
    drop = projector_shadow(depth, fx, cfg.baseline) | depth_edges(depth, cfg.edge_threshold)
    # lateral jitter: each pixel measures the depth at a randomly shifted pixel
    shift = pixel_shifts((H, W), cfg.pixel_shift, rng)
    gx, gy = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    z = cv2.remap(depth, gx + shift[0], gy + shift[1], cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
    valid = z > 0
    # axial noise, growing with distance and with the incidence angle theta = atan(|grad z| f / z)
    grad = cv2.magnitude(cv2.Sobel(z, cv2.CV_32F, 1, 0, ksize=1), cv2.Sobel(z, cv2.CV_32F, 0, 1, ksize=1))
    theta = cv2.phase(np.where(valid, z, np.float32(1.0)), grad * np.float32(0.5 * fx))  # central differences
    f32 = np.float32
    theta = np.minimum(theta, f32(np.deg2rad(85.0)))
    sigma = z - f32(cfg.z_ref)  # sigma_base + sigma_quad (z - z_ref)^2 + sigma_angle theta^2 / (pi/2 - theta)^2 / sqrt(z)
    sigma *= sigma
    sigma *= f32(cfg.sigma_quad)
    sigma += f32(cfg.sigma_base)
    grazing = f32(np.pi / 2) - theta
    grazing *= grazing
    grazing *= np.sqrt(np.maximum(z, f32(1e-3)))
    theta *= theta
    theta *= f32(cfg.sigma_angle)
    sigma += theta / grazing
    z = z + sigma * gaussian((H, W), 1.0, rng)
    # disparity quantisation
    fb = np.float32(fx * cfg.baseline)
    disp = np.round(fb / np.maximum(z, 1e-3) / cfg.disparity_step) * np.float32(cfg.disparity_step)
    z = fb / np.maximum(disp, np.float32(1e-6))
    z *= disp > 0  # (z is finite and >= 0 here: a product with a mask zeroes pixels faster than a masked store)
    # dropout: edges and projector shadow (with probability edge_dropout), plus random pixels
    u = rng.random((H, W), dtype=np.float32)
    lost = (drop & (u < cfg.edge_dropout)) | (u >= 1.0 - cfg.random_dropout) | ~valid
    z *= ~(lost | (z < near) | (z > far))
    return z


def noisy_rgb(rgb: np.ndarray, cfg: RgbNoiseConfig, rng: np.random.Generator) -> np.ndarray:
    """Exposure gain and gamma, optional Gaussian blur and Gaussian sensor noise on an (H, W, 3) uint8 image."""
    gain, gamma = rng.uniform(*cfg.gain), rng.uniform(*cfg.gamma)
    lut = np.clip(255.0 * np.clip(gain * np.arange(256) / 255.0, 0.0, 1.0) ** gamma, 0, 255)
    out = cv2.LUT(rgb, np.round(lut).astype(np.uint8))
    if rng.random() < cfg.blur_prob:
        out = cv2.GaussianBlur(out, (0, 0), rng.uniform(*cfg.blur_sigma))
    std = rng.uniform(*cfg.noise_std)
    if std > 0:
        out = cv2.add(out, gaussian(out.shape, std, rng, np.int16), dtype=cv2.CV_8U)
    return out
