"""The depth fit's compiled kernels (``_icp.c``, ``_score.c``, built with the package as ``_kernels``), and the
ctypes structures that hand them a frame's ``FitContext`` (``_kernels.h`` declares them).

A kernel runs a whole batch of fits in one call, with the GIL released, its rows shared out over
``torch.get_num_threads()`` threads of torch's own OpenMP team (``_parallel.h``): each row's result is the same on any
number. The structures point into tensors that ``KernelFrame`` keeps alive.
"""

from __future__ import annotations

import ctypes
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from posegrasp.native import library

if TYPE_CHECKING:
    from posegrasp.perception.depth_fit.context import FitContext

_P = ctypes.c_void_p


class CObserved(ctypes.Structure):
    _fields_ = [("rows", ctypes.c_int64), ("n", ctypes.c_int64), ("points", _P), ("weights", _P), ("obj", _P),
                ("table", _P)]


class CGrids(ctypes.Structure):
    _fields_ = [(name, _P) for name in ("lo", "cell", "last", "strides", "start", "index")]


class CBuckets(ctypes.Structure):
    _fields_ = [(name, _P) for name in ("lo", "size", "shape", "start", "first", "rows")]


class CFields(ctypes.Structure):
    _fields_ = [(name, _P) for name in ("values", "lo", "cell", "top", "margin", "strides", "start")]


class CScene(ctypes.Structure):
    _fields_ = [(name, ctypes.c_int64) for name in ("m", "height", "width", "s")] + \
        [("models", _P), ("ok", _P), ("depth", _P)] + [(name, ctypes.c_float) for name in ("fx", "fy", "cx", "cy")] + \
        [("plane", _P), ("supports", _P)]


class CScoreConfig(ctypes.Structure):
    _fields_ = [(name, ctypes.c_float) for name in ("truncation", "violation_margin", "violation_weight",
                                                     "float_margin", "float_weight")]


def _library() -> ctypes.CDLL:
    """The compiled kernels, beside this module."""
    lib = library(Path(__file__).parent, "_kernels", "the depth fit's compiled kernels")
    lib.posegrasp_icp_steps.restype = ctypes.c_int
    lib.posegrasp_icp_steps.argtypes = [ctypes.POINTER(CObserved), ctypes.POINTER(CGrids), ctypes.POINTER(CBuckets),
                                        ctypes.c_int, ctypes.c_int64, _P, _P, _P, _P, _P, ctypes.c_int64]
    lib.posegrasp_scores.restype = ctypes.c_int
    lib.posegrasp_scores.argtypes = [ctypes.POINTER(CObserved), ctypes.POINTER(CGrids), ctypes.POINTER(CFields),
                                     ctypes.POINTER(CScene), ctypes.POINTER(CScoreConfig), ctypes.c_int64, _P, _P, _P,
                                     ctypes.c_int64]
    return lib


LIB = _library()


def _ptr(x: torch.Tensor | None) -> int | None:
    return None if x is None else x.data_ptr()


class KernelFrame:
    """A ``FitContext`` as the kernels' structures (``grids``, ``buckets``, ``fields``, ``scene``), and
    ``observed(obj)``: its observed points for fits of objects obj (H,); the tensors they point into are kept here."""

    def __init__(self, frame: FitContext):
        g, f = frame.grids, frame.grids.fields
        self.keep = [x.contiguous() for x in (
            frame.points, frame.weights, frame.table, g.lo, g.cell, g.max, g.strides[..., 0], g.start, g.index,
            f.values, f.lo, f.cell, f.top, f.margin, f.strides, f.start, frame.models, frame.model_ok.to(torch.uint8),
            frame.depth)]
        self.points, self.weights, self.table = self.keep[:3]
        self.grids = CGrids(*map(_ptr, self.keep[3:9]))
        self.fields = CFields(*map(_ptr, self.keep[9:16]))
        plane = None if frame.plane is None else frame.plane.float().contiguous()
        sup = None if frame.supports is None else frame.supports.float().contiguous()
        self.keep += [plane, sup]
        K = np.asarray(frame.K, dtype=np.float64)
        h, w = frame.depth.shape
        self.models = self.keep[16]
        self.scene = CScene(self.models.shape[1], h, w, 0 if sup is None else sup.shape[1],
                           *map(_ptr, self.keep[16:19]), K[0, 0], K[1, 1], K[0, 2], K[1, 2], _ptr(plane), _ptr(sup))
        self.plane = plane if plane is not None else torch.zeros(4)
        b = [x.contiguous() for x in (g.bucket_lo, g.bucket_size, g.bucket_shape, g.bucket_start, g.bucket_first,
                                      g.bucket_rows)]
        self.keep += b
        self.buckets = CBuckets(*map(_ptr, b))

    def observed(self, obj: torch.Tensor) -> tuple[CObserved, torch.Tensor]:
        """The structure of the fits of objects obj (H,), and the int64 obj it points into (keep it alive for the
        call)."""
        obj = obj.long().contiguous()
        return CObserved(len(obj), self.points.shape[1], self.points.data_ptr(), self.weights.data_ptr(),
                         obj.data_ptr(), self.table.data_ptr()), obj
