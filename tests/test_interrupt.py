"""Ctrl-C (SIGINT to the process group, as a terminal sends it) during datagen, trials and train: one line saying how
to resume, exit 130, no traceback from the command or its workers; the resumed run ends with the files of an
uninterrupted one (wall-clock fields aside). A training killed outright (SIGKILL) resumes to the same bytes too:
weights, optimizer state and JSON configs."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest
from faults import TINY_DATAGEN_TOML, TINY_TRAIN_TOML, assert_one_line, assert_same_tree, interrupt_when, make_tiny_bop
from helpers import build_once, cli, run_cli

pytestmark = pytest.mark.slow  # each test runs its command three times in child processes

RERUN = r"posegrasp: interrupted; run the same command again to resume"
RESUME = r"posegrasp: interrupted; run the same command with --resume to continue"


def lines(path: Path) -> int:
    try:
        return path.read_text().count("\n")
    except FileNotFoundError:
        return 0


def interrupted_then_resumed(tmp_path: Path, args: list[str], ready, message: str, rerun: tuple[str, ...] = ()
                             ) -> None:
    ref, cut = tmp_path / "ref", tmp_path / "cut"
    ref.mkdir()
    cut.mkdir()
    r = interrupt_when(args, cut, lambda: ready(cut))
    assert r.returncode == 130, f"rc {r.returncode}:\n{r.stderr}"
    assert_one_line(r.stderr, message)
    assert "Traceback" not in r.stdout
    again = run_cli(*args, *rerun, cwd=cut)
    assert again.returncode == 0, again.stderr
    done = run_cli(*args, cwd=ref)
    assert done.returncode == 0, done.stderr
    assert_same_tree(cut, ref)


# Enough work that the signal lands while it runs, however busy the machine.


def test_datagen(tmp_path):
    (tmp_path / "datagen.toml").write_text(TINY_DATAGEN_TOML)
    args = ["datagen", "--out", "out", "--scenes", "24", "--views", "2", "--seed", "0", "--workers", "2", "--config",
            str(tmp_path / "datagen.toml"), "--no-progress"]
    interrupted_then_resumed(tmp_path, args, lambda d: any((d / "out" / "train_pbr").glob("*/scene_gt.json")), RERUN)


def test_trials(tmp_path):
    args = ["trials", "--episodes", "10", "--seed", "0", "--workers", "2", "--out", "out", "--no-progress"]
    interrupted_then_resumed(tmp_path, args, lambda d: lines(d / "out" / "episodes.jsonl") >= 1, RERUN)


def _write_tiny(d: Path) -> None:
    (d / "train.toml").write_text(TINY_TRAIN_TOML)
    make_tiny_bop(d / "bop")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> tuple[Path, Path]:
    """The tiny dataset and the training settings (built once for the run's workers)."""
    d = build_once(tmp_path_factory, "interrupt_tiny", _write_tiny)
    return d / "bop", d / "train.toml"


def train_args(tiny: tuple[Path, Path], stage: str = "seg", steps: int = 6) -> list[str]:
    return ["train", stage, "--data", str(tiny[0]), "--out", "out", "--config", str(tiny[1]), "--steps", str(steps),
            "--no-progress"]


def test_train(tmp_path, tiny):
    # pose logs every 3 steps and checkpoints every 2: the stop's checkpoint carries values not yet logged
    interrupted_then_resumed(tmp_path, train_args(tiny, "pose"), lambda d: lines(d / "out" / "pose_metrics.csv") >= 2, RESUME,
                             rerun=("--resume",))
    state = json.loads((tmp_path / "cut" / "out" / "pose" / "state.json").read_text())
    assert state["step"] == 6 and "pending" not in state


def test_train_killed_resumes_to_the_same_bytes(tmp_path, tiny):
    ref, cut = tmp_path / "ref", tmp_path / "cut"
    ref.mkdir()
    cut.mkdir()
    proc = subprocess.Popen(cli(*train_args(tiny)), cwd=cut, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            start_new_session=True)
    state = cut / "out" / "seg" / "state.json"
    t0 = time.monotonic()
    try:
        while not state.exists():  # the first checkpoint (step 2) is written
            assert proc.poll() is None, proc.stderr.read().decode()
            assert time.monotonic() - t0 < 120, "no checkpoint within 120 s"
            time.sleep(0.01)
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert json.loads(state.read_text())["step"] < 6, "the run finished before it was killed"
    assert run_cli(*train_args(tiny), "--resume", cwd=cut).returncode == 0
    assert run_cli(*train_args(tiny), cwd=ref).returncode == 0
    for name in ("model.safetensors", "optimizer.safetensors", "config.json"):
        assert (cut / "out" / "seg" / name).read_bytes() == (ref / "out" / "seg" / name).read_bytes(), name
    assert_same_tree(cut, ref)
