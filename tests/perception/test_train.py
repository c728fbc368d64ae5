"""A few training steps on the tiny dataset lower the loss; runs resume exactly; bad use is a UserError."""

import dataclasses
import json

import pytest
import torch
from safetensors.torch import load_file

from posegrasp.perception import checkpoint
from posegrasp.perception.data import PoseDataset, SegDataset, collate
from posegrasp.perception.losses import PoseTargets, pose_loss
from posegrasp.perception.pose_net import build_pose_net
from posegrasp.perception.seg_net import build_seg_net, seg_loss
from posegrasp.perception.train_pose import train_pose
from posegrasp.perception.train_seg import train_seg
from posegrasp.errors import UserError


def _fixed_seg_loss(model, ds):
    model.eval()
    b = collate([ds.get(i) for i in range(4)])
    with torch.no_grad():
        return float(seg_loss(model(b["image"]), b["label"]))


def test_seg_training_lowers_loss(tiny_bop, tiny_run):
    cfg = checkpoint.read_config(tiny_run / "seg")
    trained, model_cfg, _ = checkpoint.load_model(tiny_run / "seg", "seg")
    torch.manual_seed(cfg["train"]["seed"])
    initial = build_seg_net(model_cfg)
    ds = SegDataset(tiny_bop, "train", model_cfg.input_size, model_cfg.num_classes)
    assert _fixed_seg_loss(trained, ds) < 0.7 * _fixed_seg_loss(initial, ds)
    rows = (tiny_run / "seg_metrics.csv").read_text().splitlines()
    assert rows[0].startswith("step,") and len(rows) == 16


def _fixed_pose_loss(model, ds):
    model.eval()
    b = collate([ds.get(i) for i in range(0, len(ds), 3)])
    with torch.no_grad():
        q, t, c, _ = model(b["image"], b["points"], b["choose"], b["obj"])
        return pose_loss(q, t, c, PoseTargets.of(b)).dis.mean().item()


@pytest.mark.slow
def test_pose_training_lowers_loss(tiny_bop, tiny_run):
    cfg = checkpoint.read_config(tiny_run / "pose")
    trained, model_cfg, _ = checkpoint.load_model(tiny_run / "pose", "pose")
    assert model_cfg.obj_ids == [1, 2, 3] and model_cfg.symmetric == [False, True, True]
    torch.manual_seed(cfg["train"]["seed"])
    initial = build_pose_net(model_cfg)
    ds = PoseDataset(tiny_bop, "train", model_cfg)
    assert _fixed_pose_loss(trained, ds) < 0.7 * _fixed_pose_loss(initial, ds)
    state = json.loads((tiny_run / "pose" / "state.json").read_text())
    assert state["step"] == 20 and state["best_val_dis"] is not None
    assert (tiny_run / "refiner" / "model.safetensors").exists()


def test_cls_training_lowers_loss(tiny_bop, tiny_run):
    from posegrasp.perception.classifier import build_classifier
    from posegrasp.perception.data import ClsDataset

    cfg = checkpoint.read_config(tiny_run / "cls")
    trained, model_cfg, _ = checkpoint.load_model(tiny_run / "cls", "cls")
    assert model_cfg.obj_ids == [1, 2, 3] and cfg["train"]["use_seg"]
    torch.manual_seed(cfg["train"]["seed"])
    initial = build_classifier(model_cfg).eval()
    ds = ClsDataset(tiny_bop, "train", model_cfg)
    b = collate([ds.get(i) for i in range(len(ds))])
    with torch.no_grad():
        losses = [float(torch.nn.functional.cross_entropy(m(b["image"]), b["label"])) for m in (trained, initial)]
    assert losses[0] < 0.9 * losses[1]  # 60 steps: 0.89 vs 1.11 (colour, the tiny set's cue, is augmented away)
    assert len((tiny_run / "cls_metrics.csv").read_text().splitlines()) == 61


def test_unusable_model_setting_is_a_one_line_error(tiny_cls_config, tmp_path):
    """An unusable ``[cls.model]`` setting is refused when the settings are read, in one line naming it."""
    from posegrasp.config import load_toml
    from posegrasp.perception.train_cls import ClsTrainConfig

    toml = tmp_path / "cls.toml"
    toml.write_text("[cls.model]\nheight_range = -0.1\n")
    with pytest.raises(UserError, match=rf"^{toml}\.model\.height_range = -0\.1 is out of range: use 0 to 10$"):
        load_toml(ClsTrainConfig, toml, "cls")
    toml.write_text("[cls.model]\nwidths = [8, 16, 32, 64, 128]\ncrop_size = 8\n")
    with pytest.raises(UserError, match=rf"^{toml}\.model: crop_size = 8 is too small for 5 pooled stages: use at "
                                        "least 16$"):
        load_toml(ClsTrainConfig, toml, "cls")
    with pytest.raises(UserError, match="height_range = -0.1 is out of range"):
        dataclasses.replace(tiny_cls_config.model, height_range=-0.1)


def test_cls_lr_schedule():
    from posegrasp.perception.train_cls import ClsTrainConfig, cls_lr

    cfg = ClsTrainConfig(steps=100, lr=1.0, warmup=0.1)
    assert cls_lr(cfg, 0) == pytest.approx(0.1) and cls_lr(cfg, 9) == pytest.approx(1.0)
    assert cls_lr(cfg, 55) == pytest.approx(0.5) and cls_lr(cfg, 100) == pytest.approx(0.0, abs=1e-12)


@pytest.mark.slow
def test_resume_is_exact_and_guarded(tiny_bop, tiny_configs, tmp_path):
    _, pose, _ = tiny_configs
    pose = dataclasses.replace(pose, model=dataclasses.replace(pose.model, num_points=32, crop_size=32),
                               batch_size=2, checkpoint_every=2, eval_every=2, eval_samples=4, decay_margin=1.0)
    a, b = tmp_path / "a", tmp_path / "b"
    train_pose(tiny_bop, a, pose, steps=4, progress=False)
    train_pose(tiny_bop, b, pose, steps=2, progress=False)
    with pytest.raises(UserError, match="--resume"):
        train_pose(tiny_bop, b, pose, steps=4, progress=False)
    train_pose(tiny_bop, b, None, steps=4, resume=True, progress=False)
    wa, wb = load_file(a / "pose" / "model.safetensors"), load_file(b / "pose" / "model.safetensors")
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    sa = json.loads((a / "pose" / "state.json").read_text())
    sb = json.loads((b / "pose" / "state.json").read_text())
    assert sa["decayed"] and sa["lr"] == sb["lr"] == pytest.approx(1e-3 * 0.3) and sa["w"] == sb["w"]
    assert [r.split(",")[0] for r in (b / "pose_metrics.csv").read_text().splitlines()] == \
        ["step", "1", "2", "3", "4"]


@pytest.mark.slow
def test_seg_resume_after_interrupted_save(tiny_bop, tiny_configs, tmp_path):
    seg, _, _ = tiny_configs
    seg = dataclasses.replace(seg, checkpoint_every=1)
    train_seg(tiny_bop, tmp_path, seg, steps=2, progress=False)
    # a save killed between its two renames leaves only the previous checkpoint as .seg.old
    (tmp_path / "seg").rename(tmp_path / ".seg.old")
    assert checkpoint.exists(tmp_path / "seg")
    out = train_seg(tiny_bop, tmp_path, None, steps=3, resume=True, progress=False)
    assert out["step"] == 3


@pytest.mark.slow
def test_seg_batches_prepared_by_workers_train_the_same_weights(tiny_bop, tiny_configs, tmp_path):
    seg, _, _ = tiny_configs
    train_seg(tiny_bop, tmp_path / "here", seg, steps=3, progress=False)
    train_seg(tiny_bop, tmp_path / "workers", dataclasses.replace(seg, workers=2), steps=3, progress=False)
    wa, wb = (load_file(tmp_path / r / "seg" / "model.safetensors") for r in ("here", "workers"))
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    if not torch.cuda.is_available():
        with pytest.raises(UserError, match="no CUDA GPU"):
            train_seg(tiny_bop, tmp_path / "gpu", dataclasses.replace(seg, device="cuda"), steps=1, progress=False)
    with pytest.raises(UserError, match="not a torch device"):
        train_seg(tiny_bop, tmp_path / "bad", dataclasses.replace(seg, device="gpu0"), steps=1, progress=False)


@pytest.mark.slow
def test_seg_fine_tunes_from_init_weights(tiny_bop, tiny_run, tiny_configs, tmp_path):
    seg, _, _ = tiny_configs
    ds = SegDataset(tiny_bop, "train", seg.model.input_size, 4)

    def ds_loss(run):
        return _fixed_seg_loss(checkpoint.load_model(run / "seg", "seg")[0], ds)

    train_seg(tiny_bop, tmp_path / "ft", dataclasses.replace(seg, init=str(tiny_run), lr=1e-4), steps=1,
              progress=False)
    train_seg(tiny_bop, tmp_path / "scratch", dataclasses.replace(seg, lr=1e-4), steps=1, progress=False)
    # one small step from the trained weights stays near them; one from scratch does not
    assert ds_loss(tmp_path / "ft") < 1.2 * ds_loss(tiny_run) < ds_loss(tmp_path / "scratch")
    assert checkpoint.read_config(tmp_path / "ft" / "seg")["train"]["init"] == str(tiny_run)
    h, w = seg.model.input_size  # another input size: the same weights, adapted
    small = dataclasses.replace(seg, init=str(tiny_run), model=dataclasses.replace(seg.model, input_size=(h - 32, w)))
    train_seg(tiny_bop, tmp_path / "small", small, steps=1, progress=False)
    assert checkpoint.read_config(tmp_path / "small" / "seg")["model"]["input_size"] == [h - 32, w]
    # a seam head added to a net without one: the rest of the net carried over (lr 0: unchanged), the head trained
    seams = dataclasses.replace(seg, init=str(tiny_run), lr=0.0, model=dataclasses.replace(seg.model, seams=True))
    train_seg(tiny_bop, tmp_path / "seams", seams, steps=1, progress=False)
    net, base = (checkpoint.load_model(r / "seg", "seg")[0] for r in (tmp_path / "seams", tiny_run))
    assert net.seam is not None and base.seam is None
    assert torch.equal(net.classifier.weight, base.classifier.weight)
    assert "seam_loss" in (tmp_path / "seams" / "seg_metrics.csv").read_text().splitlines()[0]
    with pytest.raises(UserError, match="have a seam head this run's seg net lacks"):  # not dropped unasked
        train_seg(tiny_bop, tmp_path / "drop", dataclasses.replace(seg, init=str(tmp_path / "seams")), steps=1,
                  progress=False)
    wide = dataclasses.replace(seg, init=str(tiny_run), model=dataclasses.replace(seg.model, width=0.25))
    with pytest.raises(UserError, match="another seg model config"):
        train_seg(tiny_bop, tmp_path / "bad", wide, steps=1, progress=False)
    with pytest.raises(UserError, match="no seg checkpoint"):
        train_seg(tiny_bop, tmp_path / "none", dataclasses.replace(seg, init=str(tmp_path)), steps=1, progress=False)


def test_training_zeroes_subnormal_weights(tiny_bop, tiny_run, tiny_configs, tmp_path):
    """Subnormal weights, which x86 CPUs multiply ~100x slower, are zeroed before the first step (at lr 0 the only
    change to the weights)."""
    seg, _, _ = tiny_configs
    net, net_cfg, _ = checkpoint.load_model(tiny_run / "seg", "seg")
    w = net.classifier.weight.detach().clone()
    net.classifier.weight.data[0] = 1e-39
    checkpoint.save(tmp_path / "init" / "seg", "seg", net, net_cfg, None, {"step": 0})
    train_seg(tiny_bop, tmp_path / "ft", dataclasses.replace(seg, init=str(tmp_path / "init"), lr=0.0), steps=1,
              progress=False)
    out = checkpoint.load_model(tmp_path / "ft" / "seg", "seg")[0].classifier.weight
    assert not out[0].any() and torch.equal(out[1:], w[1:])


@pytest.mark.slow
def test_pose_fine_tuning_with_the_symmetry_loss(tiny_bop, tiny_run, tiny_configs, tmp_path):
    _, pose, _ = tiny_configs
    start = load_file(tiny_run / "pose" / "model.safetensors")
    cfg = dataclasses.replace(pose, sym_loss="min_sym", init=str(tiny_run), eval_every=0)
    train_pose(tiny_bop, tmp_path / "ft", cfg, steps=2, progress=False)
    after = load_file(tmp_path / "ft" / "pose" / "model.safetensors")
    assert set(after) == set(start) and any(not torch.equal(after[k], start[k]) for k in start)  # from the init
    learned = [k for k in start if "running_" not in k and "num_batches" not in k]  # not batch-norm statistics
    assert all(torch.allclose(after[k], start[k], atol=0.01) for k in learned)  # 2 Adam steps of lr 1e-3
    with pytest.raises(UserError, match="sym_loss"):
        train_pose(tiny_bop, tmp_path / "bad", dataclasses.replace(pose, sym_loss="add"), steps=1, progress=False)


def test_cls_fine_tunes_from_init_weights_with_their_model_settings(tiny_bop, tiny_run, tiny_cls_config, tmp_path):
    """``train cls --init``: the weights and the ``[cls.model]`` settings (here a height channel the config does not
    name) come from the checkpoint; training moves the weights."""
    from posegrasp.perception.train_cls import train_cls

    start = load_file(tiny_run / "cls" / "model.safetensors")
    cfg = dataclasses.replace(tiny_cls_config, init=str(tiny_run),
                              model=dataclasses.replace(tiny_cls_config.model, height_range=0.08))
    train_cls(tiny_bop, tmp_path / "ft", cfg, steps=2, progress=False)
    after = load_file(tmp_path / "ft" / "cls" / "model.safetensors")
    assert set(after) == set(start) and any(not torch.equal(after[k], start[k]) for k in start)
    assert checkpoint.read_config(tmp_path / "ft" / "cls")["model"] == checkpoint.read_config(tiny_run / "cls")["model"]
