"""The segmentation stage at inference: a trained seg net turning an RGB image into a class map and class
probabilities at the image's size (``Segmenter``, ``upsampled_argmax``)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from posegrasp.perception import checkpoint as ckpt_mod
from posegrasp.perception.guided import argmax_planes
from posegrasp.perception.inputs import normalize_rgb, seam_components, segment_components
from posegrasp.perception.int8 import inference_form
from posegrasp.perception.seg_net import SegNetConfig


class Segmenter:
    """The segmentation stage alone: a seg net in inference form and its config; ``segmenter(rgb)`` -> class map."""

    def __init__(self, model: torch.nn.Module, cfg: SegNetConfig):
        self.model, self.cfg = model, cfg

    @classmethod
    def load(cls, ckpt: str | Path, int8: bool = True) -> "Segmenter":
        """From a ``seg`` checkpoint directory, the net in int8 when ``int8`` and the folder holds its measured ranges
        (``perception.int8``), else in float."""
        model, cfg, _ = ckpt_mod.load_model(Path(ckpt), "seg")
        return cls(inference_form(model, Path(ckpt), int8), cfg)

    def __call__(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Class map (H, W) int64 (0 background, else obj_id) and class probabilities (H, W, C)
        float32: softmax at the net's input size, bilinearly resized to the image (OpenCV, channels
        last, which is ~5x faster on a CPU than arg-maxing upsampled logits in torch); the class map is their
        arg-max (``upsampled_argmax``)."""
        labels, prob, _ = self.run(rgb)
        return labels, prob

    def parts(self, rgb: np.ndarray, seam_threshold: float = 0.25) -> list[tuple[int, np.ndarray]]:
        """The parts of an RGB image, (class, mask (H, W) bool) each: the class map's connected components, or where the
        net has a seam head its foreground cut apart along the pixels of seam probability above ``seam_threshold``
        (``inputs.seam_components``)."""
        labels, _, seams = self.run(rgb)
        return segment_components(labels, 1) if seams is None else seam_components(labels, seams > seam_threshold, 1)

    @torch.no_grad()
    def run(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """As ``__call__``, and for a net with a seam head the seam probabilities (H, W) float32 (``seg_net``; bilinearly
        resized to the image), else None."""
        h, w = rgb.shape[:2]
        ih, iw = self.cfg.input_size
        x = rgb if (h, w) == (ih, iw) else cv2.resize(rgb, (iw, ih), interpolation=cv2.INTER_LINEAR)
        logits, seam_logits = self.model.forward_seams(torch.from_numpy(normalize_rgb(x))[None])  # (1, C, ih, iw)
        seams = None
        if seam_logits is not None:
            s = torch.sigmoid(seam_logits[0]).numpy()
            seams = s if (h, w) == (ih, iw) else cv2.resize(s, (w, h), interpolation=cv2.INTER_LINEAR)
        small = torch.softmax(logits[0], dim=0)  # (C, ih, iw)
        prob = np.ascontiguousarray(small.permute(1, 2, 0).numpy())  # (ih, iw, C)
        if (h, w) == (ih, iw):
            return argmax_planes(small.numpy()).astype(np.int64), prob, seams
        prob = cv2.resize(prob, (w, h), interpolation=cv2.INTER_LINEAR)  # (h, w, C)
        if prob.ndim == 2:  # OpenCV drops a single channel axis
            prob = prob[..., None]
        return upsampled_argmax(small.numpy(), prob), prob, seams


def upsampled_argmax(small: np.ndarray, prob: np.ndarray) -> np.ndarray:
    """``prob.argmax(axis=-1)`` as int64 (H, W), where ``prob`` (H, W, C) is ``small`` (C, h, w) resized bilinearly by
    OpenCV (``INTER_LINEAR``, half-pixel centres). A pixel's value is a convex combination of ``small`` at the (up to)
    2 x 2 source pixels around x_s = (x + 1/2) w / W - 1/2 (likewise y), all within one pixel of the nearest,
    round(x_s). Where ``small``'s arg-max is one class c over that nearest pixel's 3 x 3 neighbourhood, p_c >= p_k at
    each source pixel, so also in their combination: the arg-max is c. So the class map is the nearest-neighbour
    upsampling of ``small``'s, and only the pixels near its class boundaries (a few per cent of a frame) are arg-maxed
    in ``prob``: the same map (to float rounding) ~3x faster."""
    lab = argmax_planes(small)  # (h, w)
    disc = np.ones((3, 3), dtype=np.uint8)
    mixed = (cv2.dilate(lab, disc) != cv2.erode(lab, disc)).view(np.uint8)  # neighbourhoods of more than one class
    H, W = prob.shape[:2]
    out = cv2.resize(lab, (W, H), interpolation=cv2.INTER_NEAREST_EXACT)  # source pixel round(x_s), round(y_s)
    near = np.nonzero(cv2.resize(mixed, (W, H), interpolation=cv2.INTER_NEAREST_EXACT))
    out[near] = prob[near].argmax(axis=-1)
    return out.astype(np.int64)
