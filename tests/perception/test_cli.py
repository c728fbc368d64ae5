"""The ``train`` / ``eval`` / ``perturb`` subcommands registered by ``perception.cli``."""

import argparse
import json
import tomllib

import pytest

from posegrasp.perception import cli
from posegrasp import ASSETS
from posegrasp.config import load_toml
from posegrasp.errors import UserError


def _parser():
    p = argparse.ArgumentParser(prog="posegrasp")
    cli.register(p.add_subparsers(dest="command", required=True))
    return p


@pytest.mark.slow
def test_train_and_eval_commands(tiny_bop, tiny_run, tmp_path, capsys):
    cfg = tmp_path / "cfg.toml"
    cfg.write_text("[seg]\nbatch_size = 2\nlog_every = 1\n[seg.model]\nwidth = 0.125\ninput_size = [64, 96]\n"
                   "[eval]\nmax_images = 1\n")
    args = _parser().parse_args(["train", "seg", "--data", str(tiny_bop), "--out", str(tmp_path / "run"),
                                 "--config", str(cfg), "--steps", "2", "--seed", "1", "--no-progress"])
    assert args.run(args) == 0
    assert json.loads(capsys.readouterr().out)["step"] == 2
    saved = json.loads((tmp_path / "run" / "seg" / "config.json").read_text())
    assert saved["train"]["seed"] == 1 and saved["model"]["input_size"] == [64, 96]
    args = _parser().parse_args(["eval", "--data", str(tiny_bop), "--weights", str(tiny_run), "--config", str(cfg),
                                 "--out", str(tmp_path / "ev"), "--gt-masks", "--no-refiner", "--no-progress"])
    assert args.run(args) == 0
    rep = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert rep["images"] == 1 and rep["ablation"]["refiner_iterations"] == 0


def test_bad_config_is_user_error(tiny_bop, tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[pose]\nbatch = 3\n")
    args = _parser().parse_args(["train", "pose", "--data", str(tiny_bop), "--out", str(tmp_path),
                                 "--config", str(cfg)])
    with pytest.raises(UserError, match="unknown key"):
        args.run(args)
    args = _parser().parse_args(["train", "refiner", "--data", str(tiny_bop), "--out", str(tmp_path / "x")])
    with pytest.raises(UserError, match="train pose"):
        args.run(args)


def test_old_names_are_read_with_a_notice(tmp_path, capsys):
    """The stage, table, keys and flags named ``refine`` and ``icp`` before are read under their new names, each
    with a one-line notice on stderr naming the new one."""
    from posegrasp.perception.evaluate import EvalConfig
    from posegrasp.perception.train_refiner import RefinerTrainConfig

    args = _parser().parse_args(["eval", "--data", ".", "--weights", ".", "--no-refine", "--no-icp"])
    assert args.no_refiner and args.no_depth_fit and "no_refine" not in vars(args) and "no_icp" not in vars(args)
    assert _parser().parse_args(["train", "refine", "--data", ".", "--out", "x"]).stage == "refiner"
    notes = capsys.readouterr().err.splitlines()
    assert notes == ["posegrasp: note: '--no-refine' is now named '--no-refiner'",
                     "posegrasp: note: '--no-icp' is now named '--no-depth-fit'",
                     "posegrasp: note: 'refine' is now named 'refiner'"]
    old = tmp_path / "old.toml"
    old.write_text("[refine]\nsteps = 7\n[eval]\nrefine_iterations = 0\nicp = false\n")
    assert load_toml(RefinerTrainConfig, old, "refiner", cli.SECTIONS, cli.RENAMED).steps == 7
    cfg = load_toml(EvalConfig, old, "eval", cli.SECTIONS, cli.RENAMED)
    assert cfg.refiner_iterations == 0 and not cfg.depth_fit
    notes = capsys.readouterr().err.splitlines()
    assert f"posegrasp: note: {old}: 'refine' is now named 'refiner'" in notes
    assert f"posegrasp: note: {old}: 'icp' is now named 'depth_fit'" in notes
    with pytest.raises(UserError, match="'icp' and 'depth_fit' are one setting"):
        old.write_text("[eval]\nicp = false\ndepth_fit = true\n")
        load_toml(EvalConfig, old, "eval", cli.SECTIONS, cli.RENAMED)


@pytest.mark.parametrize("argv, message", [
    (["--stages", "pose,nope"], "name one or more of"),
    (["--rel-sigma", "-1"], "--rel-sigma must be a finite number >= 0"),
    (["--weights", "."], "holds no pose/"),
    (["--out", "."], "is not empty"),
])
def test_perturb_rejects_bad_input(tiny_run, tmp_path, argv, message):
    base = {"--weights": str(tiny_run), "--out": str(tmp_path / "noisy"), "--rel-sigma": "0.1"}
    base.update(dict(zip(argv[::2], argv[1::2])))
    with pytest.raises(UserError, match=message):  # refused when parsed or when run
        args = _parser().parse_args(["perturb", *[x for kv in base.items() for x in kv]])
        args.run(args)


@pytest.mark.parametrize("path", sorted((ASSETS / "perception").glob("*.toml")), ids=lambda p: p.name)
def test_shipped_training_configs_load(path):
    sections = tomllib.loads(path.read_text())
    classes = {name: t.config for name, t in cli.training_stages().items()}
    assert list(classes) == ["seg", "pose", "refiner", "cls"]
    assert sections and set(sections) <= set(classes)
    for name in sections:
        cfg = load_toml(classes[name], path, section=name)
        assert cfg.steps >= 1000 and cfg.checkpoint_every <= 500
