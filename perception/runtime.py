"""How the trained nets run on a CPU at inference: BatchNorms folded into convolutions, subnormal weights zeroed,
channels-last weights (``for_inference``), convolutions with their weights laid out for oneDNN once (``packed``),
numpy's BLAS on one thread (``one_blas_thread``, ``with_one_blas_thread``), and torch on a given number of threads
(``torch_threads``)."""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable, Iterator

import torch
from threadpoolctl import ThreadpoolController
from torch import nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

_BLAS: ThreadpoolController | None = None


def one_blas_thread() -> contextlib.AbstractContextManager:
    """A context in which numpy's BLAS (OpenBLAS) runs on one thread. The pipeline's numpy products are small, but
    past ~2.6e5 multiply-adds OpenBLAS splits them over its threads, which then spin-wait for more work and take the
    cores from torch's next stage: on 2 cores a classifier after the supporting plane's fit ran 2x slower."""
    global _BLAS
    if _BLAS is None:
        _BLAS = ThreadpoolController()
    return _BLAS.limit(limits=1, user_api="blas")


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """A context in which torch runs its CPU ops on ``n`` threads; the count before it is restored after."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def with_one_blas_thread(method: Callable) -> Callable:
    """``method`` run in ``one_blas_thread()`` (a decorator)."""
    @functools.wraps(method)
    def wrapper(*args, **kwargs):
        with one_blas_thread():
            return method(*args, **kwargs)
    return wrapper


def for_inference(model: torch.nn.Module) -> torch.nn.Module:
    """``model`` itself, in eval mode, its BatchNorms folded into their convolutions (``fold_batch_norms``), its
    subnormal weights zeroed (``flush_subnormals``) and its 2D convolutions' weights channels-last: the outputs stay the
    same (to float rounding; inputs may stay NCHW) and come ~35 % faster on a CPU (oneDNN's native layout), a
    classifier's on a frame's 19 crops another ~35 % faster without the BatchNorms. For inference only: the model no
    longer trains or loads a checkpoint as it did."""
    fold_batch_norms(model.eval())
    flush_subnormals(model)
    return model.to(memory_format=torch.channels_last)


def flush_subnormals(model: torch.nn.Module) -> None:
    """Zero every subnormal value (0 < |w| < ``torch.finfo(dtype).tiny``, 1.2e-38 in float32) of ``model``'s floating
    parameters and buffers (at inference, and every few steps in training). Training leaves some (weights of a dead
    channel decay towards 0; a folded BatchNorm of tiny gain scales its convolution's weights there). A product with
    one is below float32's range, so it adds nothing to a sum of normal terms, but x86 CPUs multiply subnormals in
    microcode, ~100x slower: 8,500 of them in a seg net's 1/16-resolution convolutions made its forward pass 1.7x
    slower."""
    with torch.no_grad():
        for t in (*model.parameters(), *model.buffers()):
            if t.is_floating_point():
                t.masked_fill_((t != 0) & (t.abs() < torch.finfo(t.dtype).tiny), 0.0)


def fold_batch_norms(model: torch.nn.Module) -> None:
    """Each BatchNorm2d of ``model`` (in eval mode) folded into the Conv2d whose output it normalises and replaced by an
    identity: W' = W g / s, b' = (b - mu) g / s + beta per output channel (g, beta: its affine weights; mu, s^2: its
    running mean and variance + eps). The pairs are a Conv2d followed by a BatchNorm2d in an ``nn.Sequential`` and
    those a module names in its ``conv_bn_pairs`` (attribute names: (conv, bn), ...)."""
    for m in list(model.modules()):
        pairs = list(getattr(m, "conv_bn_pairs", ()))
        if isinstance(m, torch.nn.Sequential):
            pairs += [(str(i), str(i + 1)) for i in range(len(m) - 1)
                      if isinstance(m[i], torch.nn.Conv2d) and isinstance(m[i + 1], torch.nn.BatchNorm2d)]
        for conv, bn in pairs:
            setattr(m, conv, fuse_conv_bn_eval(getattr(m, conv), getattr(m, bn)))
            setattr(m, bn, torch.nn.Identity())


class PackedConv2d(nn.Module):
    """A float ``Conv2d`` at inference with its weights reordered into oneDNN's layout once per input shape: torch's
    own CPU convolution reorders them at every call, about 40 % of its time on a pose net's 6 x 6 feature maps. The
    same oneDNN convolution: the outputs (channels-last) are the convolution's to float rounding (oneDNN may pick
    another kernel on one thread)."""

    def __init__(self, conv: nn.Conv2d):
        super().__init__()
        self.conv = conv
        self._weights: dict[torch.Size, torch.Tensor] = {}  # by input shape

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        c = self.conv
        x = x.contiguous(memory_format=torch.channels_last)
        w = self._weights.get(x.shape)
        if w is None:
            if len(self._weights) >= 16:  # (batch sizes vary with the objects in view)
                self._weights.clear()
            w = self._weights[x.shape] = torch._C._nn.mkldnn_reorder_conv2d_weight(
                c.weight.detach().to_mkldnn(), list(c.padding), list(c.stride), list(c.dilation), c.groups,
                list(x.shape))
        return torch.ops.mkldnn._convolution_pointwise(x, w, c.bias, c.padding, c.stride, c.dilation, c.groups,
                                                       "none", [], "")


def packed(model: nn.Module) -> nn.Module:
    """``model`` itself (in inference form, ``for_inference``) with each of its float ``Conv2d`` a ``PackedConv2d``,
    where torch runs convolutions with oneDNN on this CPU (else unchanged). For inference only."""
    if not (torch.backends.mkldnn.is_available() and hasattr(torch.ops.mkldnn, "_convolution_pointwise")):
        return model
    for name, child in model.named_children():
        if type(child) is nn.Conv2d and child.padding_mode == "zeros" and child.weight.dtype == torch.float32:
            setattr(model, name, PackedConv2d(child))
        else:
            packed(child)
    return model
