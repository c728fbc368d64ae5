"""Run-time input preparation shared by the estimator and the training datasets: the seg net's normalised image,
the pose net's crop and sampled points, the instance classifier's metric crop, and the connected segments of a
class map. Images are RGB uint8 (H, W, 3), depth float32 metres (H, W), K the (3, 3) intrinsics."""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np
from scipy import ndimage

from posegrasp.perception.crop import backproject, crop_box, padded_box, remap_choose, sample_choose

if TYPE_CHECKING:
    from posegrasp.perception.classifier import ClassifierConfig

RGB_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
RGB_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)


def normalize_rgb(rgb: np.ndarray) -> np.ndarray:
    """uint8 (H, W, 3) RGB -> float32 (3, H, W), ImageNet mean/std normalised (in place on the planes: ~10x faster than
    on the channels-last image, the same numbers)."""
    x = rgb.transpose(2, 0, 1).astype(np.float32, order="C")
    x /= 255.0
    x -= RGB_MEAN[:, None, None]
    x /= RGB_STD[:, None, None]
    return x


def prepare_pose_input(rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, mask: np.ndarray, num_points: int,
                       crop_size: int, rng: np.random.Generator, depth_noise: float = 0.0
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Crop, point sampling and back-projection for one object mask (shared by training and inference).

    Returns (image (3, S, S) float32 normalised, choose (N,) int64 into the S x S crop, points (N, 3)
    float32 camera frame, m), or None when the mask has no pixel with valid depth.
    """
    if not mask.any():
        return None
    box = crop_box(mask)
    rmin, rmax, cmin, cmax = box
    valid = mask[rmin:rmax, cmin:cmax] & (depth[rmin:rmax, cmin:cmax] > 0)  # the crop holds the whole mask
    if not valid.any():
        return None
    choose = sample_choose(valid, num_points, rng)
    pts = backproject(depth, K, box, choose)
    if depth_noise > 0:
        z = pts[:, 2]
        pts = pts * ((z + rng.normal(0.0, depth_noise, z.shape)) / z)[:, None]  # noise along each ray
    crop = cv2.resize(np.ascontiguousarray(rgb[rmin:rmax, cmin:cmax]), (crop_size, crop_size),
                      interpolation=cv2.INTER_LINEAR)
    choose_s = remap_choose(choose, (rmax - rmin, cmax - cmin), crop_size)
    return normalize_rgb(crop), choose_s, pts.astype(np.float32)


def prepare_cls_input(rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, mask: np.ndarray, cfg: ClassifierConfig,
                      plane: np.ndarray | None = None, min_valid: int = 10) -> np.ndarray | None:
    """Fixed-metric-size crop of one segment for the instance classifier (``perception.classifier``), with the crop
    settings of ``cfg``: ``crop_size`` (size), ``crop_side`` (side), ``depth_range`` and ``height_range``.

    The square of ``side`` metres at the segment's median depth z, centred on the mask's centroid, is
    resampled to size x size px (scale s = size z / (side f_x)). Channels (6, S, S) float32: RGB in [0, 1],
    the mask, (depth - z) / depth_range clipped to [-1, 1] (0 where invalid), and the valid-depth flag.
    With ``height_range`` > 0 a 7th channel holds each pixel's height above the supporting ``plane``
    (``perception.plane``; n . X + d for the back-projected point X), clipped to [0, height_range] m and scaled to
    [0, 1]; 0 where the depth is invalid or there is no plane (None).
    RGB is not normalised here (``normalize_cls_input`` does it after augmentation). None when the
    mask has fewer than ``min_valid`` pixels with valid depth.
    """
    size, side, depth_range, height_range = cfg.crop_size, cfg.crop_side, cfg.depth_range, cfg.height_range
    box = padded_box(mask, 0)  # the mask's box: its statistics need no more
    if box is None:
        return None
    valid = mask[box] & (depth[box] > 0)
    if int(valid.sum()) < min_valid:
        return None
    z = float(_median(depth[box][valid]))
    mom = cv2.moments(mask[box].view(np.uint8), binaryImage=True)  # the centroid, ~5x faster than np.nonzero's means
    cx, cy = box[1].start + mom["m10"] / mom["m00"], box[0].start + mom["m01"] / mom["m00"]
    s = size * z / (side * float(K[0, 0]))
    A = np.array([[s, 0.0, size / 2 - s * cx], [0.0, s, size / 2 - s * cy]], dtype=np.float32)
    rgb_c = cv2.warpAffine(rgb, A, (size, size), flags=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    mask_c = cv2.warpAffine(mask.view(np.uint8), A, (size, size), flags=cv2.INTER_NEAREST)
    d_c = cv2.warpAffine(depth.astype(np.float32, copy=False), A, (size, size), flags=cv2.INTER_NEAREST)
    ok = d_c > 0
    rel = np.where(ok, np.clip((d_c - z) / depth_range, -1.0, 1.0), 0.0)
    channels = [np.ascontiguousarray(rgb_c.transpose(2, 0, 1)) / np.float32(255.0), mask_c[None], rel[None], ok[None]]
    if height_range > 0:
        height = np.zeros((size, size), dtype=np.float32)
        if plane is not None:  # crop pixel (x, y) samples image pixel ((x, y) - A[:, 2]) / s
            u = (np.arange(size, dtype=np.float32) - A[0, 2]) / s
            v = (np.arange(size, dtype=np.float32) - A[1, 2]) / s
            X = (u[None, :] - K[0, 2]) / K[0, 0] * d_c
            Y = (v[:, None] - K[1, 2]) / K[1, 1] * d_c
            h = X * plane[0] + Y * plane[1] + d_c * plane[2] + plane[3]
            height = np.where(ok, np.clip(h / height_range, 0.0, 1.0), 0.0)
        channels.append(height[None])
    return np.concatenate(channels, dtype=np.float32)


def _median(x: np.ndarray) -> np.floating:
    """``np.median`` of a 1-D float array without NaN: its middle value, or the float mean of its two middle values
    (those of ``np.partition``, the same numbers np.median reads; ~4x faster on a segment's few thousand)."""
    k = len(x) // 2
    if len(x) % 2:
        return np.partition(x, k)[k]
    lo, hi = np.partition(x, (k - 1, k))[k - 1:k + 1]
    return (lo + hi) / x.dtype.type(2)


def normalize_cls_input(x: np.ndarray) -> np.ndarray:
    """``prepare_cls_input``'s (C, S, S) with the RGB channels ImageNet-normalised."""
    x = x.astype(np.float32, copy=True)
    x[:3] -= RGB_MEAN[:, None, None]
    x[:3] /= RGB_STD[:, None, None]
    return x


def segment_components(labels: np.ndarray, min_pixels: int) -> list[tuple[int, np.ndarray]]:
    """(class, mask) of the 8-connected components of at least ``min_pixels`` pixels of every non-background class of a
    class map (H, W), ints >= 0, in that order: by class, then by the raster position of each component's first pixel.
    The segmentation net is semantic (one class per block type), while a scene may hold several blocks of a type:
    separated blocks become separate components, touching ones stay merged. A class's components are found in the box
    of each connected foreground region in turn (each lies in one), not in the whole image."""
    W = labels.shape[1]
    fg = labels > 0
    whole = padded_box(fg, 0)  # the foreground's box: the regions are those of the image, numbered alike
    if whole is None:
        return []
    _, regions = cv2.connectedComponents(fg[whole].view(np.uint8), connectivity=8)
    found = []  # (class, raster index of the first pixel, mask)
    for k, inner in enumerate(ndimage.find_objects(regions), start=1):  # boxes: ~2x faster than OpenCV's stats
        box = tuple(slice(i.start + o.start, i.stop + o.start) for i, o in zip(inner, whole))
        y, x = box[0].start, box[1].start
        lab = np.where(regions[inner] == k, labels[box], 0)  # another region may reach into the box
        for c in np.flatnonzero(np.bincount(lab.ravel())):  # the region's classes (and 0, unless it fills its box)
            if c == 0:
                continue
            m, comp, st, _ = cv2.connectedComponentsWithStats((lab == c).view(np.uint8), connectivity=8)
            for i in range(1, m):
                if st[i, cv2.CC_STAT_AREA] >= min_pixels:
                    top = st[i, cv2.CC_STAT_TOP]
                    mask = np.zeros(labels.shape, dtype=bool)
                    mask[box] = comp == i
                    found.append((int(c), (y + top) * W + x + int(np.argmax(comp[top] == i)), mask))
    return [(c, m) for c, _, m in sorted(found, key=lambda f: f[:2])]


def seam_components(labels: np.ndarray, seams: np.ndarray, min_pixels: int, passes: int = 6
                    ) -> list[tuple[int, np.ndarray]]:
    """(class, mask) of the parts of a class map (H, W), ints >= 0, cut along seams (H, W) bool (``seg_net``): the
    connected components of its foreground (labels > 0) without the seam pixels, those of at least ``min_pixels``
    pixels in raster order of their first pixel, each grown back over the seam pixels of the foreground, one ring of
    8-neighbours per pass (``passes`` passes: seams are a few pixels wide), and typed by the class most of its pixels
    have. Parts of any type are cut apart where the net sees a seam, whatever classes it gives their pixels: in a heap
    its classes are the less reliable of the two."""
    fg = labels > 0
    n, comp, stats, _ = cv2.connectedComponentsWithStats((fg & ~seams).view(np.uint8), connectivity=8)
    big = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] >= min_pixels)
    big = big[big > 0]
    if len(big) >= 2 ** 24:  # ids below 2^24 are exact in float32 (cv2.dilate's type here)
        raise ValueError(f"{len(big)} parts are more than seam_components can tell apart")
    relabel = np.zeros(n, dtype=np.float32)
    relabel[big] = np.arange(1, len(big) + 1)
    ids = relabel[comp]  # the cores, numbered from 1 in raster order of their first pixel; 0 elsewhere
    todo = fg & (ids == 0)
    disc = np.ones((3, 3), dtype=np.uint8)
    for _ in range(passes):
        if not todo.any():
            break
        grown = cv2.dilate(ids, disc)  # the highest id among each pixel's 8-neighbours
        take = todo & (grown > 0)
        ids[take] = grown[take]
        todo &= ~take
    out = []
    for k, box in enumerate(ndimage.find_objects(ids.astype(np.int32)), start=1):
        mask = np.zeros(labels.shape, dtype=bool)
        mask[box] = ids[box] == k
        out.append((int(np.bincount(labels[mask]).argmax()), mask))
    return out


def check_frame(rgb: np.ndarray, depth: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The frame as the estimator reads it: rgb uint8 (H, W, 3), depth float32 (H, W) with NaN / inf as 0 (invalid),
    K float64 (3, 3); ValueError on other shapes."""
    rgb, depth, K = np.asarray(rgb), np.asarray(depth), np.asarray(K, dtype=np.float64)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be uint8 (H, W, 3), got {rgb.dtype} {rgb.shape}")
    if depth.shape != rgb.shape[:2]:
        raise ValueError(f"depth must be (H, W) = {rgb.shape[:2]}, got {depth.shape}")
    if K.shape != (3, 3):
        raise ValueError(f"K must be 3x3, got {K.shape}")
    depth = np.nan_to_num(depth.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    return rgb, depth, K
