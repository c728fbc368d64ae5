"""The structured-light depth model and the colour camera effects, on synthetic images."""

from __future__ import annotations

import dataclasses

import numpy as np

from posegrasp.datagen.config import DepthNoiseConfig, RgbNoiseConfig
from posegrasp.datagen.noise import noisy_depth, noisy_rgb, projector_shadow
from posegrasp.sim.camera import intrinsics

H, W = 240, 320
K = intrinsics(W, H, 55.0)


def box_on_plane(z_plane: float, z_box: float) -> np.ndarray:
    """A fronto-parallel plane with a nearer square in the middle (m)."""
    d = np.full((H, W), z_plane, np.float32)
    d[90:150, 130:190] = z_box
    return d


def test_same_rng_same_measurement_and_sensible_statistics():
    cfg = DepthNoiseConfig()
    clean = box_on_plane(0.6, 0.5)
    a = noisy_depth(clean, K, cfg, np.random.default_rng(1), 0.15, 2.0)
    b = noisy_depth(clean, K, cfg, np.random.default_rng(1), 0.15, 2.0)
    c = noisy_depth(clean, K, cfg, np.random.default_rng(2), 0.15, 2.0)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    ok = a > 0
    assert 0.9 < ok.mean() < 0.999  # some dropout, mostly valid
    err = np.abs(a - clean)[ok]
    assert np.median(err) < 1.5e-3 and np.percentile(err, 99) < 0.02


def test_axial_noise_grows_with_distance_and_disparity_is_quantised():
    fine = dataclasses.replace(DepthNoiseConfig(), pixel_shift=0.0, random_dropout=0.0, disparity_step=1e-4)
    std = []
    for z in (0.4, 1.2):
        d = noisy_depth(np.full((H, W), z, np.float32), K, fine, np.random.default_rng(0), 0.15, 2.0)
        std.append(float(np.std(d[20:-20, 20:-20] - z)))
    sigma = [fine.sigma_base + fine.sigma_quad * (z - fine.z_ref) ** 2 for z in (0.4, 1.2)]
    np.testing.assert_allclose(std, sigma, rtol=0.1)
    cfg = DepthNoiseConfig()
    d = noisy_depth(np.full((H, W), 1.2, np.float32), K, cfg, np.random.default_rng(0), 0.15, 2.0)
    levels = np.unique(d[d > 0])
    step = 1.2 ** 2 * cfg.disparity_step / (K[0, 0] * cfg.baseline)  # depth step of one disparity step
    assert len(levels) <= 6 and np.allclose(np.diff(levels), step, rtol=0.2)


def test_projector_shadow_falls_left_of_nearer_surfaces():
    clean = box_on_plane(0.8, 0.4)
    shadow = projector_shadow(clean, K[0, 0], 0.05)
    band = K[0, 0] * 0.05 * (1 / 0.4 - 1 / 0.8)  # disparity difference (px)
    assert shadow[120, 130 - int(band) + 1:130].all()  # background just left of the box
    assert not shadow[120, 190:].any() and not shadow[120, 130:190].any()
    cfg = dataclasses.replace(DepthNoiseConfig(), edge_dropout=1.0)
    d = noisy_depth(clean, K, cfg, np.random.default_rng(0), 0.15, 2.0)
    assert (d[100:140, 130 - int(band) + 1:128] == 0).mean() > 0.9


def test_rgb_effects():
    rgb = np.random.default_rng(0).integers(40, 200, (H, W, 3), dtype=np.uint8)
    cfg = RgbNoiseConfig()
    a, b = noisy_rgb(rgb, cfg, np.random.default_rng(5)), noisy_rgb(rgb, cfg, np.random.default_rng(5))
    np.testing.assert_array_equal(a, b)
    assert a.shape == rgb.shape and a.dtype == np.uint8 and not np.array_equal(a, rgb)
    bright = dataclasses.replace(cfg, gain=(1.2, 1.2), gamma=(1.0, 1.0), blur_prob=0.0, noise_std=(0.0, 0.0))
    np.testing.assert_allclose(noisy_rgb(rgb, bright, np.random.default_rng(0)).mean(), rgb.mean() * 1.2, rtol=0.02)


def _numpy_noisy_depth(depth: np.ndarray, cfg: DepthNoiseConfig, rng: np.random.Generator, near: float, far: float
                       ) -> np.ndarray:
    """The depth model as numpy's whole-image formulas, the reference of the compiled steps (``datagen.sensor``)."""
    import cv2

    from posegrasp.datagen.noise import gaussian, shift_thresholds

    f32, fx = np.float32, float(K[0, 0])
    disp = np.zeros_like(depth)
    np.divide(f32(fx * cfg.baseline), depth, out=disp, where=depth > 0)
    up = np.arange(depth.shape[1], dtype=f32)[None, :] - disp
    right_min = np.minimum.accumulate(up[:, ::-1], axis=1)[:, ::-1]
    drop = np.zeros(depth.shape, bool)
    drop[:, :-1] = up[:, :-1] > right_min[:, 1:] + f32(0.5)
    drop &= depth > 0
    far_d = np.where(depth > 0, depth, f32(1e3))
    drop |= (cv2.dilate(far_d, np.ones((3, 3), np.uint8)) - cv2.erode(far_d, np.ones((3, 3), np.uint8))) > \
        cfg.edge_threshold
    t = shift_thresholds(cfg.pixel_shift)
    u = rng.integers(0, 1 << 16, (2, *depth.shape), dtype=np.uint16)
    k = (u >= t[2]).view(np.int8) + (u >= t[3]).view(np.int8) - (u < t[1]).view(np.int8) - (u < t[0]).view(np.int8)
    gx, gy = np.meshgrid(np.arange(depth.shape[1], dtype=f32), np.arange(depth.shape[0], dtype=f32))
    z = cv2.remap(depth, gx + k[0], gy + k[1], cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
    valid = z > 0
    grad = cv2.magnitude(cv2.Sobel(z, cv2.CV_32F, 1, 0, ksize=1), cv2.Sobel(z, cv2.CV_32F, 0, 1, ksize=1))
    theta = np.minimum(cv2.phase(np.where(valid, z, f32(1)), grad * f32(0.5 * fx)), f32(np.deg2rad(85.0)))
    sigma = (z - f32(cfg.z_ref)) ** 2 * f32(cfg.sigma_quad) + f32(cfg.sigma_base)
    grazing = (f32(np.pi / 2) - theta) ** 2 * np.sqrt(np.maximum(z, f32(1e-3)))
    sigma += theta ** 2 * f32(cfg.sigma_angle) / grazing
    z = z + sigma * gaussian(depth.shape, 1.0, rng)
    fb = f32(fx * cfg.baseline)
    disp = np.round(fb / np.maximum(z, 1e-3) / cfg.disparity_step) * f32(cfg.disparity_step)
    z = fb / np.maximum(disp, f32(1e-6)) * (disp > 0)
    u = rng.random(depth.shape, dtype=f32)
    lost = (drop & (u < cfg.edge_dropout)) | (u >= 1.0 - cfg.random_dropout) | ~valid
    return z * ~(lost | (z < near) | (z > far))


def test_compiled_steps_give_numpys_numbers():
    g = np.random.default_rng(7)
    wide = dataclasses.replace(DepthNoiseConfig(), pixel_shift=0.6, sigma_angle=0.002, random_dropout=0.05)
    for seed, cfg, shape in ((0, DepthNoiseConfig(), (H, W)), (1, wide, (H, W)), (2, wide, (17, 29))):
        d = np.full(shape, 0.7, np.float32) + np.linspace(0, 0.05, shape[1], dtype=np.float32)
        for _ in range(6):  # nearer boxes, holes and a far patch
            r, c = g.integers(0, shape[0]), g.integers(0, shape[1])
            d[r:r + g.integers(3, 60), c:c + g.integers(3, 60)] -= np.float32(g.uniform(0.01, 0.4))
        d[g.random(shape) < 0.02] = 0
        d[:2, :5] = 2.5
        d[-1, -3:] = np.nan  # numpy's NaN pixels stay NaN
        want = _numpy_noisy_depth(d, cfg, np.random.default_rng(seed), 0.15, 2.0)
        got = noisy_depth(d, K, cfg, np.random.default_rng(seed), 0.15, 2.0)
        assert want.tobytes() == got.tobytes() and np.isnan(got).any()
