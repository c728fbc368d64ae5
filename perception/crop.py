"""DenseFusion's crop rule and point sampling (Wang et al. 2019).

Boxes are (rmin, rmax, cmin, cmax) in pixels, max exclusive. ``choose`` holds flat indices into a
crop (row-major) of the pixels that are in the mask and have valid depth.
"""

from __future__ import annotations

import numpy as np

#: Box side lengths are rounded up to the next of these (DenseFusion's ``border_list``).
BORDERS: tuple[int, ...] = (-1,) + tuple(range(40, 681, 40))


def _round_side(side: int) -> int:
    for lo, hi in zip(BORDERS[:-1], BORDERS[1:]):
        if lo < side < hi:
            return hi
    return side


def padded_box(mask: np.ndarray, margin: int) -> tuple[slice, slice] | None:
    """The rows and columns of the box around the nonzero pixels of ``mask`` (H, W), widened by ``margin`` px and
    clipped to the image; None for an empty mask. The columns are looked for in the box's rows only."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    r0, r1 = int(rows[0]), int(rows[-1]) + 1
    cols = np.flatnonzero(mask[r0:r1].any(axis=0))
    return slice(max(0, r0 - margin), r1 + margin), slice(max(0, int(cols[0]) - margin), int(cols[-1]) + margin + 1)


def mask_bbox(mask: np.ndarray) -> tuple[int, int, int, int]:
    """Tight (rmin, rmax, cmin, cmax) of a non-empty boolean mask, max exclusive."""
    box = padded_box(mask, 0)
    if box is None:
        raise ValueError("empty mask has no bounding box")
    return box[0].start, box[0].stop, box[1].start, box[1].stop


def crop_box(mask: np.ndarray) -> tuple[int, int, int, int]:
    """DenseFusion crop of a mask in an (H, W) image: sides rounded up to 40, 80, ..., 680 px,
    re-centred on the tight box, shifted to stay inside the image.

    Returns (rmin, rmax, cmin, cmax), max exclusive. Unlike DenseFusion (fixed 480x640), the image
    size comes from the mask, and a rounded side longer than the image is clipped to the image.
    """
    h, w = mask.shape
    rmin, rmax, cmin, cmax = mask_bbox(mask)
    r_b, c_b = _round_side(rmax - rmin), _round_side(cmax - cmin)
    rc, cc = (rmin + rmax) // 2, (cmin + cmax) // 2
    rmin, rmax = rc - r_b // 2, rc + r_b // 2
    cmin, cmax = cc - c_b // 2, cc + c_b // 2
    if rmin < 0:
        rmax, rmin = rmax - rmin, 0
    if cmin < 0:
        cmax, cmin = cmax - cmin, 0
    if rmax > h:
        rmin, rmax = rmin - (rmax - h), h
    if cmax > w:
        cmin, cmax = cmin - (cmax - w), w
    return max(rmin, 0), rmax, max(cmin, 0), cmax


def sample_choose(valid: np.ndarray, num_points: int, rng: np.random.Generator) -> np.ndarray:
    """Flat indices (num_points,) of True pixels of a crop-sized boolean array ``valid``.

    More than ``num_points`` candidates: a random subset (without replacement, from ``rng``),
    kept in raster order; fewer: all of them, padded by wrapping around (DenseFusion's rule).
    Raises ValueError when there is no candidate at all.
    """
    idx = np.flatnonzero(valid.ravel())
    if idx.size == 0:
        raise ValueError("no valid pixel to sample points from")
    if idx.size > num_points:
        idx = np.sort(rng.choice(idx, size=num_points, replace=False))
    elif idx.size < num_points:
        idx = np.pad(idx, (0, num_points - idx.size), mode="wrap")
    return idx.astype(np.int64)


def remap_choose(choose: np.ndarray, crop_hw: tuple[int, int], out_size: int) -> np.ndarray:
    """Map flat indices in an (h, w) crop to flat indices in the same crop resized to out_size^2."""
    h, w = crop_hw
    r, c = np.divmod(choose, w)
    rr = np.minimum(((r + 0.5) * out_size / h).astype(np.int64), out_size - 1)
    cc = np.minimum(((c + 0.5) * out_size / w).astype(np.int64), out_size - 1)
    return rr * out_size + cc


def backproject(depth: np.ndarray, K: np.ndarray, box: tuple[int, int, int, int],
                choose: np.ndarray) -> np.ndarray:
    """Camera-frame points (N, 3) in metres of the chosen crop pixels; depth (H, W) in metres."""
    rmin, rmax, cmin, cmax = box
    wc = cmax - cmin
    r, c = np.divmod(choose, wc)
    v = (r + rmin).astype(np.float64)
    u = (c + cmin).astype(np.float64)
    z = depth[r + rmin, c + cmin].astype(np.float64)
    x = (u - K[0, 2]) * z / K[0, 0]
    y = (v - K[1, 2]) * z / K[1, 1]
    return np.stack([x, y, z], axis=1)


def seen_facing(points: np.ndarray, normals: np.ndarray, T_cam_obj: np.ndarray, K: np.ndarray, depth: np.ndarray,
                min_cos: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A model's surface points (N, 3) with outward normals (N, 3) (object frame, m) placed at ``T_cam_obj`` (4, 4):
    those facing the camera (the cosine of a normal's angle to the line of sight above ``min_cos``) in front of it
    that project into the depth image (H, W) (m, 0: none) through K (3, 3). Returns their camera-frame points (M, 3),
    their pixels' flat indices (M,) (nearest pixel centres) and the depth seen there (M,) (m)."""
    p = points @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3]
    cos = -np.einsum("ij,ij->i", normals @ T_cam_obj[:3, :3].T, p) / np.maximum(np.linalg.norm(p, axis=1), 1e-12)
    p = p[(cos > min_cos) & (p[:, 2] > 1e-6)]
    h, w = depth.shape
    u = np.round(p[:, 0] / p[:, 2] * K[0, 0] + K[0, 2]).astype(np.int64)
    v = np.round(p[:, 1] / p[:, 2] * K[1, 1] + K[1, 2]).astype(np.int64)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    pix = v[inside] * w + u[inside]
    return p[inside], pix, depth.flat[pix]
