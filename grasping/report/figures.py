"""The report's images: segmentation and pose overlays on a look capture (uint8 RGB arrays), the plot of success
against a perception error, and their data URIs (the page embeds every image)."""

from __future__ import annotations

import base64
import io
from dataclasses import dataclass
from typing import Callable

import numpy as np

from posegrasp.geometry import transform_points
from posegrasp.grasping.record import EpisodeRecord
from posegrasp.sim.camera import Frame

#: Outline colours (RGB) of the model at the true and at the estimated pose.
TRUE_RGB, EST_RGB = (40, 230, 60), (255, 40, 200)
#: Nearest depth (m) of a triangle drawn in a silhouette (those nearer, or behind the camera, are left out).
NEAR = 0.02
#: Fractional bits of the silhouettes' vertex coordinates (``cv2.fillConvexPoly``'s ``shift``).
_SHIFT = 4
_SUBPIXEL = 1 << _SHIFT


@dataclass
class Look:
    """An episode's re-simulated look capture: the frame, the provider's estimates, labels and overview image."""

    frame: Frame
    estimates: list
    labels: np.ndarray
    overview: np.ndarray
    objects: str = ""  # the object set's folder (``""``: the shipped blocks)


def silhouette(block, T_cam_obj: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) bool: pixels covered by ``block``'s mesh at ``T_cam_obj`` (OpenCV camera, m): its triangles lying
    wholly ``NEAR`` m or more in front of the camera, projected with ``K`` and filled, border pixels included
    (about half a pixel wider than a renderer draws it)."""
    import cv2

    tri = transform_points(T_cam_obj, block.vertices)[np.asarray(block.faces)]  # (F, 3 corners, xyz)
    tri = tri[(tri[..., 2] >= NEAR).all(axis=1)]
    uv = tri @ np.asarray(K, dtype=float).T
    px = np.round(_SUBPIXEL * uv[..., :2] / uv[..., 2:]).astype(np.int32)  # OpenCV: pixel centres at integers
    out = np.zeros((height, width), dtype=np.uint8)
    for t in px:
        cv2.fillConvexPoly(out, t, 1, shift=_SHIFT)
    return out > 0


def _outline(mask: np.ndarray, width: int = 2) -> np.ndarray:
    """Boundary pixels (``width`` px thick) of a bool mask."""
    inner = mask.copy()
    for _ in range(width):
        p = np.pad(inner, 1)
        inner = inner & p[:-2, 1:-1] & p[2:, 1:-1] & p[1:-1, :-2] & p[1:-1, 2:]
    return mask & ~inner


def segmentation_overlay(rgb: np.ndarray, labels: np.ndarray, alpha: float = 0.6) -> np.ndarray:
    """RGB (dimmed) with each nonzero label tinted in its own colour and outlined (uint8)."""
    rng = np.random.default_rng(7)
    colours = rng.integers(60, 256, size=(int(labels.max()) + 1, 3))
    out = 0.7 * rgb.astype(np.float32)
    fg = labels > 0
    out[fg] = (1 - alpha) * out[fg] + alpha * colours[labels[fg]]
    for v in np.unique(labels[fg]):
        out[_outline(labels == v, 1)] = colours[v]
    return out.astype(np.uint8)


def pose_overlay(look: Look) -> np.ndarray:
    """RGB (dimmed) with the block outlines at the true pose (green) and at the estimated pose (magenta)."""
    from posegrasp.catalog import catalog_by_id

    f = look.frame
    h, w = f.mask.shape
    cat = catalog_by_id(look.objects)
    out = (0.75 * f.rgb).astype(np.uint8)
    visible = np.unique(f.mask[f.mask > 0])
    for k in visible:  # thick, so that an estimate drawn on top of it leaves it visible
        out[_outline(silhouette(cat[int(f.obj_ids[k - 1])], f.T_cam_obj[k - 1], f.K, w, h), 4)] = TRUE_RGB
    for e in look.estimates:
        out[_outline(silhouette(cat[e.obj_id], e.T_cam_obj, f.K, w, h), 2)] = EST_RGB
    return out


def data_uri(rgb: np.ndarray, fmt: str = "jpeg") -> str:
    """``data:`` URI of a uint8 RGB image encoded as ``fmt`` (``"jpeg"``, quality 88, or ``"png"``)."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format=fmt.upper(), **({"quality": 88} if fmt == "jpeg" else {}))
    return f"data:image/{fmt};base64,{base64.b64encode(buf.getvalue()).decode()}"


def adds_mm(rec: EpisodeRecord) -> float | None:
    """ADD(-S) of the grasped estimate (mm); None without one."""
    return 1000 * rec.pose_error.err if rec.pose_error else None


def rotation_deg(rec: EpisodeRecord) -> float | None:
    """Rotation error (deg) of the grasped estimate modulo symmetries (kitting, stack); None without one."""
    return rec.estimate_error.re_deg if rec.estimate_error else None


def error_plot(records: list[EpisodeRecord], value: Callable[[EpisodeRecord], float | None] = adds_mm,
               xlabel: str = "pose error of the grasped estimate, ADD(-S) (mm)") -> str | None:
    """PNG data URI: each episode's outcome against its perception error ``value(record)`` (None: no
    estimate), with binned success rates (Wilson 95 % intervals); None when no episode has a value."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from posegrasp.grasping.stats import wilson

    pts = [(value(r), r.outcome == "success") for r in records if value(r) is not None]
    if not pts:
        return None
    x = np.array([p[0] for p in pts])
    y = np.array([p[1] for p in pts], dtype=float)
    jitter = np.random.default_rng(0).uniform(-0.04, 0.04, len(x))
    fig, ax = plt.subplots(figsize=(7.5, 3.6))
    ax.scatter(x, 100 * (y + jitter), s=14, c=np.where(y > 0, "tab:green", "tab:red"), alpha=0.7,
               label="episodes (100 = success, 0 = failure)")
    edges = np.unique(np.quantile(x, np.linspace(0, 1, min(5, len(x)) + 1)))
    if len(edges) > 1:
        idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
        mids, rates, lo, hi = [], [], [], []
        for b in range(len(edges) - 1):
            sel = idx == b
            if sel.any():
                k, n = int(y[sel].sum()), int(sel.sum())
                a, c = wilson(k, n)
                mids.append(float(np.median(x[sel])))
                rates.append(100 * k / n)
                lo.append(100 * (k / n - a))
                hi.append(100 * (c - k / n))
        ax.errorbar(mids, rates, yerr=[lo, hi], fmt="o-", color="tab:blue", capsize=4,
                    label="binned success rate (Wilson 95 %)")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("success (%)")
    ax.set_ylim(-8, 108)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower left")
    return figure_uri(fig)


def figure_uri(fig) -> str:
    """PNG data URI of a matplotlib figure (laid out tightly, 90 dpi), which it then closes."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return f"data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()}"


def animation_uri(frames: list[np.ndarray], period_s: float) -> str:
    """``data:`` URI of an animated GIF of ``frames`` (uint8 RGB, one size), each shown ``period_s`` seconds,
    looping; one palette for all frames (the scene's colours barely change), so frames store only what moved."""
    from PIL import Image

    first = Image.fromarray(frames[0]).quantize(colors=255, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    images = [first] + [Image.fromarray(f).quantize(palette=first, dither=Image.Dither.NONE) for f in frames[1:]]
    buf = io.BytesIO()
    images[0].save(buf, format="GIF", save_all=True, append_images=images[1:], duration=round(1000 * period_s),
                   loop=0, optimize=False)
    return f"data:image/gif;base64,{base64.b64encode(buf.getvalue()).decode()}"
