"""Int8 inference of the nets built of ``ConvBNReLU`` blocks (the seg net, the instance classifiers) on a CPU.

Every run of ``ConvBNReLU`` blocks and max-pools in an ``nn.Sequential`` (a lone ``ConvBNReLU`` is a run of one)
computes in int8 with oneDNN: the run's input is quantized once to u8 per tensor, x_q = round(x / s) + z with
s = (hi - lo) / 255 and z = round(-lo / s) for its measured range [lo, hi]; each conv's weights are s8 per output
channel, W_q = round(W / s_k) with s_k = max |W_k| / 127.5; each conv's integer sums are rescaled, ReLU'd and
requantized to u8 with its output's measured range; the run's output is dequantized. The convs at the input's full
resolution (the image's own and the others before the first pooling) and everything outside the runs (upsampling,
concatenations, the 1x1 heads) stay float: with only the image's conv in float, the shipped model lost 0.013 of
BOP AR on its validation split, with both of its full-resolution convs in float 0.001. On 2 cores the seg net's
240x320 forward pass then takes 0.43 of its float time on a CPU with AMX, 0.67 with AVX2 alone (oneDNN capped to it).

The activation ranges are measured once on the net's own inputs (``observing``, then ``ranges``; ``posegrasp
quantize`` does it for a run) and stored beside the weights in ``RANGES`` with the weights file's SHA-256, so
``quantized`` builds the same int8 net on any machine without data. Where torch has no oneDNN quantized engine
(``supported``), the nets run in float.
"""

from __future__ import annotations

import hashlib
import os
import warnings
from pathlib import Path
from typing import Any

import torch
from torch import nn

from posegrasp import inputs
from posegrasp import io as pio
from posegrasp.errors import WeightsError
from posegrasp.outputs import mark_json
from posegrasp.perception.runtime import for_inference
from posegrasp.perception.seg_net import ConvBNReLU

#: The file of measured activation ranges in a checkpoint folder.
RANGES = "int8.json"
FORMAT = "posegrasp-int8"
VERSION = 1
COMMAND = "quantize"  #: the command that writes ``RANGES`` (its marker)
ENGINE = "onednn"  # its activations keep all 8 bits (PyTorch's onednn default; fbgemm's needs 7 on CPUs without VNNI)


def supported() -> bool:
    """Whether this torch runs int8 convolutions on the CPU (its oneDNN quantized engine)."""
    return ENGINE in torch.backends.quantized.supported_engines


def _qconfig() -> Any:
    from torch.ao.quantization import MinMaxObserver, PerChannelMinMaxObserver, QConfig

    return QConfig(activation=MinMaxObserver.with_args(dtype=torch.quint8, reduce_range=False),
                   weight=PerChannelMinMaxObserver.with_args(dtype=torch.qint8, qscheme=torch.per_channel_symmetric))


def _run(blocks: list[nn.Module]) -> nn.Sequential:
    """An int8 run: quantize, each ``ConvBNReLU`` (batch norm folded) as one fused conv + ReLU, max-pools as they
    are, dequantize."""
    from torch.ao.nn.intrinsic import ConvReLU2d
    from torch.ao.quantization import DeQuantStub, QuantStub

    body = [ConvReLU2d(b[0], b[-1]) if isinstance(b, ConvBNReLU) else b for b in blocks]
    run = nn.Sequential(QuantStub(), *body, DeQuantStub())
    run.qconfig = _qconfig()
    return run


def _is_run(m: nn.Module) -> bool:
    return isinstance(m, ConvBNReLU) or (type(m) is nn.Sequential and len(m) > 0
                                         and all(isinstance(c, (ConvBNReLU, nn.MaxPool2d)) for c in m))


def _mark_runs(module: nn.Module, first: nn.Module) -> None:
    """Replace every run below ``module`` by its int8 form; in the run of the conv ``first``, the blocks before its
    first max-pool stay float."""
    for name, child in module.named_children():
        if not _is_run(child):
            _mark_runs(child, first)
            continue
        blocks = [child] if isinstance(child, ConvBNReLU) else list(child)
        head = 0
        if isinstance(blocks[0], ConvBNReLU) and blocks[0][0] is first:  # the blocks before the first pooling
            head = next((i for i, b in enumerate(blocks) if isinstance(b, nn.MaxPool2d)), len(blocks))
        head, rest = blocks[:head], blocks[head:]
        setattr(module, name, nn.Sequential(*head, _run(rest)) if rest else child)


def observing(model: nn.Module) -> nn.Module:
    """``model`` itself in inference form (``runtime.for_inference``) with its runs marked for int8 and observers
    recording each quantized tensor's range: its forward pass is still float. Run it on the inputs the net will
    see, then read ``ranges``."""
    from torch.ao.quantization import prepare

    if not isinstance(model, nn.Module) or not any(isinstance(m, ConvBNReLU) for m in model.modules()):
        raise WeightsError(f"{type(model).__name__} has no ConvBNReLU blocks to run in int8")
    for_inference(model)
    first = next(m for m in model.modules() if isinstance(m, nn.Conv2d))
    _mark_runs(model, first)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # torch marks its quantized dtypes deprecated
        return prepare(model, inplace=True)


def _observers(model: nn.Module) -> dict[str, Any]:
    return {name: m.activation_post_process for name, m in model.named_modules()
            if hasattr(m, "activation_post_process")}


def ranges(model: nn.Module) -> dict[str, list[float]]:
    """Each observed tensor's range [lo, hi] in an ``observing`` model, by module name; ValueError when one saw no
    input yet."""
    out = {}
    for name, obs in _observers(model).items():
        lo, hi = float(obs.min_val), float(obs.max_val)
        if not lo <= hi:
            raise ValueError(f"{name} saw no input: run the observing model on some inputs first")
        out[name] = [lo, hi]
    return out


def quantized(model: nn.Module, measured: dict[str, list[float]]) -> nn.Module:
    """``model`` itself, its runs in int8 with the activation ranges ``measured`` (``ranges``); WeightsError when
    they are not this net's. Sets torch's quantized engine, process-wide, to ``ENGINE``."""
    from torch.ao.quantization import convert

    torch.backends.quantized.engine = ENGINE
    observers = _observers(observing(model))
    if set(observers) != set(measured):
        raise WeightsError(f"the int8 ranges name the layers {sorted(set(measured) ^ set(observers))[:3]} this net "
                           f"lacks or has unnamed: rerun 'posegrasp quantize'")
    for name, obs in observers.items():
        obs.min_val, obs.max_val = (torch.tensor(v, dtype=torch.float32) for v in measured[name])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return convert(model, inplace=True)


def runs_int8(model: nn.Module) -> bool:
    """Whether ``model`` has int8 runs (``quantized``'s)."""
    from torch.ao.nn.quantized import Quantize

    return any(isinstance(m, Quantize) for m in model.modules())


def weights_sha256(ckpt: Path) -> str:
    """SHA-256 (hex) of the checkpoint's ``model.safetensors``."""
    return hashlib.sha256((Path(ckpt) / "model.safetensors").read_bytes()).hexdigest()


def write_ranges(ckpt: Path, measured: dict[str, list[float]], source: dict[str, Any]) -> Path:
    """Write ``measured`` into the checkpoint folder ``ckpt`` (``RANGES``, atomically), with where they come from."""
    doc = {"format": FORMAT, "version": VERSION, "engine": ENGINE, "weights_sha256": weights_sha256(ckpt),
           "source": source, "ranges": measured}
    return pio.write_json(Path(ckpt) / RANGES, mark_json(doc, COMMAND))


def read_ranges(ckpt: Path) -> dict[str, list[float]] | None:
    """The activation ranges stored in the checkpoint folder ``ckpt``; None without ``RANGES``. WeightsError when the
    file is unreadable or was measured on other weights."""
    path = Path(ckpt) / RANGES
    if not os.path.lexists(path):
        return None
    doc = inputs.read_json(path, WeightsError)
    try:
        if doc["format"] != FORMAT or doc["version"] != VERSION:
            raise ValueError(f"format {doc['format']!r} version {doc['version']!r}")
        sha, measured = doc["weights_sha256"], {str(k): [float(v[0]), float(v[1])] for k, v in doc["ranges"].items()}
        if not all(lo <= hi for lo, hi in measured.values()):
            raise ValueError("a range [lo, hi] with lo > hi")
    except (ValueError, KeyError, TypeError, IndexError) as e:
        raise WeightsError(f"{path} is not an int8 calibration ({e}): rerun 'posegrasp quantize' or delete "
                           "it") from None
    if sha != weights_sha256(ckpt):
        raise WeightsError(f"{path} was measured on other weights than {Path(ckpt) / 'model.safetensors'}: rerun "
                           "'posegrasp quantize' or delete it")
    return measured


def copy_ranges(src: Path, dst: Path) -> None:
    """The ranges stored in the checkpoint folder ``src`` into ``dst``, whose weights are the same tensors re-saved;
    nothing when ``src`` has none."""
    measured = read_ranges(src)
    if measured is not None:
        write_ranges(dst, measured, inputs.read_json(Path(src) / RANGES, WeightsError)["source"])


def inference_form(model: nn.Module, ckpt: Path, int8: bool) -> nn.Module:
    """``model`` (loaded from the checkpoint folder ``ckpt``) as it runs at inference: int8 when ``int8``, the folder
    holds its measured ranges and torch can (``supported``), else float (``runtime.for_inference``)."""
    measured = read_ranges(ckpt) if int8 and supported() else None
    return for_inference(model) if measured is None else quantized(model, measured)
