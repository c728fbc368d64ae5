"""Drawing one BOP image with its labels (``posegrasp dataset show``): visible masks, amodal outlines, projected
3D boxes and axes, next to the depth image."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from posegrasp import bop
from posegrasp.errors import UserError
from posegrasp.geometry import transform_points

#: Edges of a box whose 8 corners are indexed by bits (x, y, z).
_BOX_EDGES = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]


def find_record(root: str | Path, split: str, scene_id: int, im_id: int) -> bop.ImageRecord:
    """The BOP image record (m) of ``scene_id`` / ``im_id``, or a UserError naming what exists."""
    scenes = bop.list_scenes(root, split)
    if scene_id not in scenes:
        raise UserError(f"scene {scene_id} is not in {bop.split_dir(root, split)} (scenes: {scenes[:10]}...)")
    records = {r.im_id: r for r in bop.iter_scene_images(root, split, [scene_id])}
    if im_id not in records:
        raise UserError(f"image {im_id} is not in scene {scene_id} (images: {sorted(records)[:20]})")
    return records[im_id]


def _colour(i: int) -> tuple[int, int, int]:
    """A distinct RGB colour per annotation index."""
    hsv = np.uint8([[[(i * 47) % 180, 220, 255]]])
    return tuple(int(c) for c in cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0])


def _project(K: np.ndarray, T_cam_obj: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = transform_points(T_cam_obj, pts)
    z = p[:, 2]
    uv = (p[:, :2] / np.where(z > 1e-6, z, 1.0)[:, None]) * K[[0, 1], [0, 1]] + K[:2, 2]
    return uv, z > 1e-6


def _line(img: np.ndarray, a: np.ndarray, b: np.ndarray, colour, thickness: int = 1) -> None:
    s = 16  # sub-pixel precision bits of cv2.line's shift
    pa, pb = (tuple(int(round(v * s)) for v in p) for p in (a, b))
    cv2.line(img, pa, pb, colour, thickness, cv2.LINE_AA, shift=4)


def draw_labels(rec: bop.ImageRecord, infos: dict[int, bop.ObjectInfo]) -> np.ndarray:
    """RGB (H, W, 3) with each annotation's visible mask tinted, amodal outline, 3D box, axes and obj id."""
    rgb = rec.load_rgb()
    img = rgb.astype(np.float32)
    K = rec.camera.K
    for g in rec.instances:
        col = np.array(_colour(g.gt_index), np.float32)
        vis = rec.load_mask(g.gt_index, visible=True)
        img[vis] = 0.55 * img[vis] + 0.45 * col
    out = np.clip(img, 0, 255).astype(np.uint8)
    for g in rec.instances:
        col = _colour(g.gt_index)
        full = rec.load_mask(g.gt_index, visible=False).astype(np.uint8)
        contours, _ = cv2.findContours(full, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(out, contours, -1, col, 1)
        info = infos.get(g.obj_id)
        if info is None:
            continue
        corners = np.array([[(i >> a) & 1 for a in range(3)] for i in range(8)], float) * info.size_xyz + info.min_xyz
        uv, ok = _project(K, g.T_cam_obj, corners)
        for a, b in _BOX_EDGES:
            if ok[a] and ok[b]:
                _line(out, uv[a], uv[b], col)
        L = 0.3 * info.diameter
        uv, ok = _project(K, g.T_cam_obj, np.array([[0, 0, 0], [L, 0, 0], [0, L, 0], [0, 0, L]], float))
        if ok.all():
            for j, axc in enumerate([(255, 40, 40), (40, 220, 40), (60, 90, 255)], start=1):
                _line(out, uv[0], uv[j], axc, 2)
            x, y = (int(v) for v in uv[0])
            cv2.putText(out, str(g.obj_id), (x + 4, y - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1,
                        cv2.LINE_AA)
    return out


def depth_image(depth_m: np.ndarray) -> np.ndarray:
    """Depth (m) as an RGB colour map over its valid range; invalid pixels black."""
    valid = depth_m > 0
    out = np.zeros((*depth_m.shape, 3), np.uint8)
    if valid.any():
        lo, hi = np.percentile(depth_m[valid], [1, 99])
        t = np.clip((depth_m - lo) / max(hi - lo, 1e-6), 0, 1)
        cmap = cv2.applyColorMap((255 * (1 - t)).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
        out[valid] = cmap[valid]
    return out


def show_image(root: str | Path, split: str, scene_id: int, im_id: int) -> np.ndarray:
    """Side-by-side panel: labelled RGB and colour-mapped depth of one image."""
    rec = find_record(root, split, scene_id, im_id)
    infos = bop.load_models_info(root)
    return np.hstack([draw_labels(rec, infos), depth_image(rec.load_depth())])
