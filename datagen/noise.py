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

from posegrasp.datagen import sensor
from posegrasp.datagen.config import DepthNoiseConfig, RgbNoiseConfig


def projector_shadow(depth: np.ndarray, fx: float, baseline: float, tol_px: float = 0.5) -> np.ndarray:
    """(H, W) bool: pixels the projector (``baseline`` m along +x) cannot light because a nearer surface
    to their right blocks its ray. A pixel u projects to projector column u - fx b / z; it is shadowed when
    some pixel further right lands at a smaller projector column."""
    return sensor.depth_drop(depth, np.float32(fx * baseline), np.float32(tol_px), np.inf)


def gaussian(shape: tuple[int, ...], std: float, rng: np.random.Generator, dtype=np.float32) -> np.ndarray:
    """Gaussian noise N(0, std) of ``shape`` (rounded for integer dtypes), from OpenCV's generator seeded by
    ``rng`` (3x faster than numpy's)."""
    cv2.setRNGSeed(int(rng.integers(1 << 30, 1 << 31)))
    return cv2.randn(np.empty(shape, dtype), 0.0, float(std))


def shift_thresholds(sigma: float) -> list[int]:
    """The 16-bit uniforms' thresholds of a pixel offset N(0, sigma) px rounded to the nearest pixel, |offset| <= 2:
    the normal CDF at -1.5, -0.5, 0.5 and 1.5 px, x 2^16 (``sensor.shifted``)."""
    from math import erf, sqrt

    cdf = [0.5 * (1 + erf(x / (sigma * sqrt(2)))) for x in (-1.5, -0.5, 0.5, 1.5)] if sigma > 0 else [0, 0, 1, 1]
    return [int(round(c * 65536)) for c in cdf]


def noisy_depth(depth: np.ndarray, K: np.ndarray, cfg: DepthNoiseConfig, rng: np.random.Generator,
                near: float, far: float) -> np.ndarray:
    """Structured-light measurement of a clean depth map (H, W) float32 m; returns float32 m, 0 invalid. Per pixel
    (``sensor``): z, the depth at the pixel shifted by N(0, ``pixel_shift``) px; sigma = sigma_base + sigma_quad
    (z - z_ref)^2 + sigma_angle theta^2 / ((pi/2 - theta)^2 sqrt(z)), theta the incidence angle atan(|grad z| f / z)
    (at most 85 deg); z + sigma N(0, 1) quantised in disparity steps; lost in the projector's shadow and at depth
    edges (with probability ``edge_dropout``), at random (``random_dropout``), where z is invalid or outside
    [near, far]."""
    H, W = depth.shape
    fx, f32 = float(K[0, 0]), np.float32
    fb = f32(fx * cfg.baseline)
    drop = sensor.depth_drop(depth, fb, f32(0.5), f32(cfg.edge_threshold))
    z = sensor.shifted(depth, rng.integers(0, 1 << 16, (2, H, W), dtype=np.uint16), shift_thresholds(cfg.pixel_shift))
    grad = cv2.magnitude(cv2.Sobel(z, cv2.CV_32F, 1, 0, ksize=1), cv2.Sobel(z, cv2.CV_32F, 0, 1, ksize=1))
    theta = cv2.phase(*sensor.phase_args(z, grad, f32(0.5 * fx)))  # central differences
    normal = gaussian((H, W), 1.0, rng)
    uniform = rng.random((H, W), dtype=np.float32)
    constants = sensor.DepthNoise(np.deg2rad(85.0), cfg.z_ref, cfg.sigma_quad, cfg.sigma_base, np.pi / 2,
                                  cfg.sigma_angle, fb, cfg.disparity_step, cfg.edge_dropout, 1.0 - cfg.random_dropout,
                                  near, far)
    return sensor.depth_noise(z, theta, normal, uniform, drop, constants)


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
