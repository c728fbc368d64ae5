"""The segmentation stage at inference: a trained seg net turning an RGB image into a class map and class
probabilities at the image's size (``Segmenter``, ``ClassProbabilities``, ``upsampled_argmax``)."""

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

#: Channel counts OpenCV resizes by other code (Intel IPP's, on x86), whose sums ``ClassProbabilities`` does not repeat.
_OWN_CODE = (1, 3, 4)


def _taps(n_out: int, n_in: int, clamp: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """OpenCV's bilinear taps along one axis (``cv::resize``, INTER_LINEAR, half-pixel centres): output pixel d reads
    input pixels i0, i1 with weights w0 = 1 - f, w1 = f (float32), f the fraction of s = (d + 1/2) n_in / n_out - 1/2
    (computed in double, rounded to float). ``clamp`` (OpenCV's columns): outside [0, n_in - 1] the nearest pixel with
    weights (1, 0); else (its rows) the taps alone are clipped to the image."""
    s = ((np.arange(n_out) + 0.5) * (1.0 / (n_out / n_in)) - 0.5).astype(np.float32)
    i0 = np.floor(s).astype(np.int64)
    f = s - i0.astype(np.float32)
    if clamp:
        f[(i0 < 0) | (i0 >= n_in - 1)] = 0.0
    return np.clip(i0, 0, n_in - 1), np.clip(i0 + 1, 0, n_in - 1), np.float32(1.0) - f, f


class ClassProbabilities:
    """Class probabilities (H, W, C) float32 of an image's pixels: those of the seg net's input size (C, h, w) resized
    bilinearly, as ``cv2.resize(..., INTER_LINEAR)`` (half-pixel centres), but only at the pixels read. A frame's whole
    map takes ~2 ms, while the pipeline reads the few per cent of its pixels near class boundaries and in segments.

    Output pixel (y, x) is b0 (a0 S[y0, x0] + a1 S[y0, x1]) + b1 (a0 S[y1, x0] + a1 S[y1, x1]) with OpenCV's taps
    (``_taps``) and its float32 products and sums, so the numbers are cv2.resize's bit for bit; for 1, 3 or 4 channels,
    which OpenCV resizes by other code, the whole map is cv2.resize's, made at the first read."""

    def __init__(self, small: np.ndarray, size: tuple[int, int]):
        self.small = np.ascontiguousarray(small, dtype=np.float32)  # (C, h, w)
        C, h, w = self.small.shape
        self.shape = (int(size[0]), int(size[1]), C)  #: (H, W, C)
        self._cols = _taps(self.shape[1], w, True)
        self._rows = _taps(self.shape[0], h, False)
        self._full: np.ndarray | None = None

    def _whole(self) -> np.ndarray:
        if self._full is None:
            H, W, C = self.shape
            full = cv2.resize(np.ascontiguousarray(self.small.transpose(1, 2, 0)), (W, H),
                              interpolation=cv2.INTER_LINEAR)
            self._full = full.reshape(H, W, C)  # OpenCV drops a single channel axis
        return self._full

    def pixels(self, rows: np.ndarray, cols: np.ndarray, channel: int | None = None) -> np.ndarray:
        """The probabilities at pixels (rows[i], cols[i]): (n, C), or (n,) of class ``channel``."""
        if self.shape[2] in _OWN_CODE:
            full = self._whole()[rows, cols]
            return full if channel is None else full[:, channel]
        x0, x1, a0, a1 = (t[cols] for t in self._cols)
        y0, y1, b0, b1 = (t[rows] for t in self._rows)
        C, h, w = self.small.shape
        S = self.small.reshape(C, h * w) if channel is None else self.small[channel].reshape(1, h * w)

        def at(y: np.ndarray, x: np.ndarray) -> np.ndarray:
            return np.take(S, y * w + x, axis=1)  # (c, n)

        top = at(y0, x0) * a0 + at(y0, x1) * a1
        bottom = at(y1, x0) * a0 + at(y1, x1) * a1
        out = top * b0 + bottom * b1
        return out.T if channel is None else out[0]

    def at(self, mask: np.ndarray, channel: int | None = None) -> np.ndarray:
        """The probabilities at the pixels of ``mask`` (H, W) bool, in raster order: (n, C), or (n,) of class
        ``channel`` (as ``prob[mask]``, ``prob[..., channel][mask]`` of the whole map)."""
        return self.pixels(*np.nonzero(mask), channel=channel)

    def __array__(self, dtype: np.dtype | None = None, copy: bool | None = None) -> np.ndarray:
        """The whole map (H, W, C) (cv2.resize's)."""
        full = self._whole()
        return full if dtype is None else full.astype(dtype)


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

    def __call__(self, rgb: np.ndarray) -> tuple[np.ndarray, ClassProbabilities]:
        """Class map (H, W) int64 (0 background, else obj_id) and class probabilities (H, W, C) float32: softmax at the
        net's input size, bilinearly resized to the image where read (``ClassProbabilities``); the class map is their
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
    def run(self, rgb: np.ndarray) -> tuple[np.ndarray, ClassProbabilities, np.ndarray | None]:
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
        small = torch.softmax(logits[0], dim=0).numpy()  # (C, ih, iw)
        prob = ClassProbabilities(small, (h, w))
        if (h, w) == (ih, iw):
            return argmax_planes(small).astype(np.int64), prob, seams
        return upsampled_argmax(small, prob), prob, seams


def upsampled_argmax(small: np.ndarray, prob: ClassProbabilities) -> np.ndarray:
    """``prob.argmax(axis=-1)`` as int64 (H, W), where ``prob`` (H, W, C) is ``small`` (C, h, w) resized bilinearly by
    OpenCV (``INTER_LINEAR``, half-pixel centres). A pixel's value is a convex combination of ``small`` at the (up to)
    2 x 2 source pixels around x_s = (x + 1/2) w / W - 1/2 (likewise y), all within one pixel of the nearest,
    round(x_s). Where ``small``'s arg-max is one class c over that nearest pixel's 3 x 3 neighbourhood, p_c >= p_k at
    each source pixel, so also in their combination: the arg-max is c. So the class map is the nearest-neighbour
    upsampling of ``small``'s, and only the pixels near its class boundaries (a few per cent of a frame) are arg-maxed
    in ``prob`` (read there only): the same map (to float rounding) ~6x faster than the whole map's."""
    lab = argmax_planes(small)  # (h, w)
    disc = np.ones((3, 3), dtype=np.uint8)
    mixed = (cv2.dilate(lab, disc) != cv2.erode(lab, disc)).view(np.uint8)  # neighbourhoods of more than one class
    H, W = prob.shape[:2]
    out = cv2.resize(lab, (W, H), interpolation=cv2.INTER_NEAREST_EXACT)  # source pixel round(x_s), round(y_s)
    near = _nearest_of(mixed, H, W)
    out[near] = prob.pixels(*near).argmax(axis=-1)
    return out.astype(np.int64)


def _nearest_of(mask: np.ndarray, H: int, W: int) -> tuple[np.ndarray, np.ndarray]:
    """The pixels (rows, columns) of ``mask`` (h, w) resized to (H, W) by OpenCV's INTER_NEAREST_EXACT that are set,
    found from the set pixels of ``mask`` (a few per cent) rather than by scanning the resized mask. The nearest source
    row of each output row is OpenCV's own (a resized column of row numbers), non-decreasing, so the output rows of
    source row i are the run of length n_i after those of the rows before it; likewise the columns."""
    def runs(n_out: int, n_in: int, axis: int) -> tuple[np.ndarray, np.ndarray]:
        idx = np.arange(n_in, dtype=np.float32).reshape((n_in, 1) if axis == 0 else (1, n_in))
        size = (1, n_out) if axis == 0 else (n_out, 1)
        src = cv2.resize(idx, size, interpolation=cv2.INTER_NEAREST_EXACT).ravel().astype(np.int64)
        count = np.bincount(src, minlength=n_in)
        return np.cumsum(count) - count, count  # first output index and count per source index

    (r0, rn), (c0, cn) = runs(H, mask.shape[0], 0), runs(W, mask.shape[1], 1)
    i, j = np.nonzero(mask)
    ny, nx = rn[i], cn[j]
    n = ny * nx  # output pixels per set source pixel
    k = np.repeat(np.arange(len(i)), n)
    within = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
    return r0[i][k] + within // nx[k], c0[j][k] + within % nx[k]
