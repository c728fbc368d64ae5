"""Int8 inference of the seg net and the classifiers: measured ranges, the quantized nets, their files, the command."""

import json
import shutil

import numpy as np
import pytest
import torch
from torch.ao.nn.intrinsic.quantized import ConvReLU2d as QuantizedConvReLU2d

from posegrasp.cli import main
from posegrasp.errors import WeightsError
from posegrasp.perception import checkpoint, int8
from posegrasp.perception.classifier import ClassifierConfig, build_classifier
from posegrasp.perception.estimator import Estimator, EstimatorConfig
from posegrasp.perception.seg_net import SegNetConfig, build_seg_net
from posegrasp.perception.segmenter import Segmenter

pytestmark = pytest.mark.skipif(not int8.supported(), reason="this torch has no oneDNN quantized engine")


def _images(n: int, size: tuple[int, int], seed: int = 0) -> list[torch.Tensor]:
    """Smooth random images (1, 3, H, W), as normalised colour images are."""
    g = torch.Generator().manual_seed(seed)
    low = torch.randn(n, 3, size[0] // 8, size[1] // 8, generator=g)
    return list(torch.nn.functional.interpolate(low, size=size, mode="bilinear").split(1))


SEG = SegNetConfig(num_classes=4, width=0.125, input_size=(64, 96), seams=True)


def _seg_net(seed: int = 0) -> torch.nn.Module:
    torch.manual_seed(seed)
    net = build_seg_net(SEG).eval()
    with torch.no_grad():  # trained-looking batch norms: varied gains and shifts, not the identity of a fresh net
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.weight.uniform_(0.5, 1.5), m.bias.uniform_(-0.2, 0.2), m.running_var.uniform_(0.5, 2.0)
    return net


def _measured(net: torch.nn.Module, images: list[torch.Tensor]) -> dict[str, list[float]]:
    observed = int8.observing(net)
    with torch.no_grad():
        for x in images:
            observed(x)
    return int8.ranges(observed)


def test_int8_seg_net_follows_the_float_one():
    """Ranges measured on some images, then a fresh copy of the net quantized with them: every conv below the full
    resolution runs as a quantized conv + ReLU, and the logits on other images follow the float net's (correlation
    > 0.99, the class map the same on > 95 % of the pixels)."""
    float_net = _seg_net()
    measured = _measured(_seg_net(), _images(6, (64, 96)))
    assert all(lo <= hi for lo, hi in measured.values())
    q = int8.quantized(_seg_net(), measured)
    quantized = [m for m in q.modules() if isinstance(m, QuantizedConvReLU2d)]
    float_convs = [m for m in q.modules() if type(m) is torch.nn.Conv2d]
    assert len(quantized) == 14 + 3 + 4 + 5 + 2  # encoder, MFFM 1-3, up blocks
    assert len(float_convs) == 4  # the encoder's two at full resolution and the two 1x1 heads
    with torch.no_grad():
        for x in _images(3, (64, 96), seed=1):
            a, b = float_net.forward_seams(x), q.forward_seams(x)
            for u, v in zip(a, b):
                assert np.corrcoef(u.flatten().numpy(), v.flatten().numpy())[0, 1] > 0.99
            assert (a[0].argmax(1) == b[0].argmax(1)).float().mean() > 0.95


def _classifier(cfg: ClassifierConfig) -> torch.nn.Module:
    torch.manual_seed(0)
    return build_classifier(cfg).eval()


def test_int8_classifier_and_wrong_ranges():
    """A classifier's run (across its max-pools) quantizes the same way; ranges of another net are refused."""
    cfg = ClassifierConfig(obj_ids=[0, 1, 2], widths=(8, 16, 32), crop_size=32)
    measured = _measured(_classifier(cfg), [torch.randn(4, cfg.in_channels, 32, 32) for _ in range(3)])
    q = int8.quantized(_classifier(cfg), measured)
    assert sum(isinstance(m, QuantizedConvReLU2d) for m in q.modules()) == 4  # the 2 at full resolution stay float
    x = torch.randn(8, cfg.in_channels, 32, 32)
    with torch.no_grad():
        assert np.corrcoef(_classifier(cfg)(x).flatten().numpy(), q(x).flatten().numpy())[0, 1] > 0.98
    with pytest.raises(WeightsError, match="rerun 'posegrasp quantize'"):
        int8.quantized(_classifier(ClassifierConfig(obj_ids=[0, 1, 2], widths=(8,), crop_size=32)), measured)


def test_ranges_file_is_bound_to_its_weights(tmp_path):
    """``Segmenter.load`` runs int8 with the folder's ranges, float without them or when asked; ranges of other
    weights or an unreadable file are refused in one line naming the file and the fix."""
    ckpt = checkpoint.save(tmp_path / "seg", "seg", _seg_net(), SEG, None, {"step": 0})
    assert int8.read_ranges(ckpt) is None
    assert not any(isinstance(m, QuantizedConvReLU2d) for m in Segmenter.load(ckpt).model.modules())
    net, _, _ = checkpoint.load_model(ckpt, "seg")
    int8.write_ranges(ckpt, _measured(net, _images(2, (64, 96))), {"data": "images", "split": "-", "images": []})
    assert any(isinstance(m, QuantizedConvReLU2d) for m in Segmenter.load(ckpt).model.modules())
    assert not any(isinstance(m, QuantizedConvReLU2d) for m in Segmenter.load(ckpt, int8=False).model.modules())
    doc = json.loads((ckpt / int8.RANGES).read_text())
    checkpoint.save(ckpt, "seg", _seg_net(seed=1), SEG, None, {"step": 1})  # retrained: a new folder, no ranges
    assert int8.read_ranges(ckpt) is None
    (ckpt / int8.RANGES).write_text(json.dumps(doc))  # the old weights' ranges beside the new weights
    with pytest.raises(WeightsError, match="measured on other weights"):
        Segmenter.load(ckpt)
    (ckpt / int8.RANGES).write_text('{"format": "posegrasp-int8", "version": 1, "ranges": {')
    with pytest.raises(WeightsError, match=str(ckpt / int8.RANGES)):
        Segmenter.load(ckpt)
    (ckpt / int8.RANGES).write_text(json.dumps({**doc, "ranges": {k: [1, -1] for k in doc["ranges"]}}))
    with pytest.raises(WeightsError, match="is not an int8 calibration"):
        Segmenter.load(ckpt)


def test_quantize_command_on_a_trained_run(tiny_run, tiny_bop, tmp_path, capsys):
    """``posegrasp quantize`` writes the seg net's and the classifier's ranges into the run; the estimator then runs
    them in int8 (EstimatorConfig(int8=False): float) and finds objects in a test image either way."""
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    argv = ["quantize", "--weights", str(run), "--data", str(tiny_bop), "--split", "train", "--images", "4",
            "--no-progress"]
    (run / "cls" / int8.RANGES).write_text('{"mine": 1}')  # a user's file of that name: kept, nothing written
    assert main(argv) == 2
    assert "not an int8 calibration written by 'posegrasp quantize'" in capsys.readouterr().err
    assert not (run / "seg" / int8.RANGES).exists() and (run / "cls" / int8.RANGES).read_text() == '{"mine": 1}'
    assert main([*argv, "--force"]) == 0 and main(argv) == 0  # its own file it replaces
    written = capsys.readouterr().out.split()[-2:]
    assert written == [str(run / "seg" / int8.RANGES), str(run / "cls" / int8.RANGES)]
    source = json.loads((run / "seg" / int8.RANGES).read_text())["source"]
    assert source["split"] == "train" and len(source["images"]) == 4
    from posegrasp.perception.data import load_records

    rec = load_records(tiny_bop, "test")[0]
    frame = rec.load_rgb(), rec.load_depth(), rec.camera.K
    for on in (True, False):
        est = Estimator(run, EstimatorConfig(int8=on, models=tiny_bop))
        nets = [est.segmenter.model, *est.classifier.models]
        assert all(any(isinstance(m, QuantizedConvReLU2d) for m in n.modules()) == on for n in nets)
        assert est.int8_nets == (["seg", "cls"] if on else [])
        assert est(*frame).labels.shape == frame[1].shape
    for stages, kept in (("pose", True), ("seg", False)):  # a perturbed copy keeps the ranges of weights it kept
        out = tmp_path / f"perturbed_{stages}"
        argv = ["perturb", "--weights", str(run), "--out", str(out), "--rel-sigma", "0.1", "--stages", stages]
        assert main(argv) == 0
        assert int8.read_ranges(out / "seg") == (int8.read_ranges(run / "seg") if kept else None)
