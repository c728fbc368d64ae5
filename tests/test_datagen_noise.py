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
