"""Output folders are locked (``posegrasp.lock``): a second writer gets one line naming the holder's PID, a lock
left by a killed run is taken over, and settings left by a failed start do not refuse the corrected command."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import cli
from test_workers import TINY_TOML

from posegrasp.datagen.config import load_datagen_config
from posegrasp.datagen.generate import SETTINGS_FILE, generate_dataset, is_complete
from posegrasp.errors import UserError
from posegrasp.grasping.config import TrialConfig
from posegrasp.grasping.runfolder import CAMPAIGN, EPISODES
from posegrasp.grasping.trials import Display, run_trials
from posegrasp.lock import LOCK_FILE, folder_lock
from posegrasp.perception.evaluate import evaluate
from posegrasp.perception.train_seg import train_seg

HOLD = "import sys, time; from posegrasp.lock import folder_lock\nwith folder_lock(sys.argv[1]):\n" \
       "    print('held', flush=True); time.sleep(120)"


@pytest.fixture
def tiny_toml(tmp_path) -> Path:
    p = tmp_path / "tiny.toml"
    p.write_text(TINY_TOML)
    return p


@pytest.fixture
def holder(tmp_path):
    """A process holding the lock of ``tmp_path / "held"``; killed with SIGKILL at the end."""
    folder = tmp_path / "held"
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(folder)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    yield folder, proc
    proc.kill()
    proc.wait()


def wait_for_lock(folder: Path, proc: subprocess.Popen) -> None:
    t0 = time.monotonic()
    while not ((folder / LOCK_FILE).is_file() and (folder / LOCK_FILE).read_text().strip() == str(proc.pid)):
        assert proc.poll() is None, proc.stderr.read()
        assert time.monotonic() - t0 < 120, "the lock was never taken"
        time.sleep(0.01)


@pytest.mark.slow
def test_two_datagen_runs_on_one_folder_and_a_stale_lock(tmp_path, tiny_toml):
    out = tmp_path / "ds"
    args = cli("datagen", "--out", str(out), "--scenes", "1", "--views", "2", "--workers", "1", "--config",
               str(tiny_toml), "--no-progress")
    first = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        wait_for_lock(out, first)
        first.send_signal(signal.SIGSTOP)  # holds the lock, frozen, while the second run tries
        second = subprocess.run(args, capture_output=True, text=True, timeout=300)
    finally:
        first.send_signal(signal.SIGKILL)
        first.wait()
    assert second.returncode == 2, second.stderr
    assert second.stderr.count("\n") == 1 and "Traceback" not in second.stderr
    assert f"PID {first.pid}" in second.stderr and str(out) in second.stderr
    assert (out / LOCK_FILE).read_text().strip() == str(first.pid)  # the killed run's lock stays behind ...
    done = subprocess.run(args, capture_output=True, text=True, timeout=300)  # ... and is taken over
    assert done.returncode == 0, done.stderr
    assert is_complete(out, "train_pbr", 0) and not (out / LOCK_FILE).exists()


def test_every_output_folder_is_locked(holder, tmp_path):
    folder, proc = holder
    calls = {
        "trials": lambda: run_trials(folder, 1, seed=0, perception="oracle", workers=1, cfg=TrialConfig()),
        "train": lambda: train_seg(tmp_path / "no-data", folder, steps=1, progress=False),
        "eval": lambda: evaluate(tmp_path / "no-data", tmp_path / "no-weights", folder, progress=False),
        "datagen": lambda: generate_dataset(folder, 1, 1),
    }
    for name, call in calls.items():
        with pytest.raises(UserError) as e:
            call()
        msg = str(e.value)
        if name == "train":  # it checks the dataset first: refused before the folder is touched
            assert "is not a BOP dataset" in msg and "\n" not in msg, f"{name}: {msg}"
            continue
        assert f"PID {proc.pid}" in msg and "\n" not in msg, f"{name}: {msg}"
    assert sorted(p.name for p in folder.iterdir()) == [LOCK_FILE], "a refused command wrote into the folder"


def test_a_lock_of_a_killed_process_is_taken_over(holder, tmp_path):
    folder, proc = holder
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert (folder / LOCK_FILE).read_text().strip() == str(proc.pid)
    with folder_lock(folder):
        assert (folder / LOCK_FILE).read_text().strip() == str(os.getpid())
    assert not (folder / LOCK_FILE).exists()
    with folder_lock(tmp_path / "new" / "run"):  # created for a run that wrote nothing: removed again
        pass
    assert not (tmp_path / "new").exists()
    (tmp_path / "file").write_text("x")
    with pytest.raises(UserError, match="is a file"):
        with folder_lock(tmp_path / "file"):
            pass


def test_a_failed_datagen_start_leaves_the_folder_usable(tmp_path, tiny_toml):
    out = tmp_path / "ds"
    cfg = load_datagen_config(tiny_toml)
    with pytest.raises(UserError, match="3 blocks do not fit"):  # refused before anything is written ...
        generate_dataset(out, 1, 1, seed=1, cfg=dataclasses.replace(cfg, blocks=(3, 3), min_spacing=0.2), workers=1)
    assert not (out / "train_pbr" / SETTINGS_FILE).exists()
    generate_dataset(out, 1, 1, seed=2, cfg=cfg, workers=1)  # ... so the folder takes other settings
    assert json.loads((out / "train_pbr" / SETTINGS_FILE).read_text())["seed"] == 2
    with pytest.raises(UserError, match="other settings"):  # now it does
        generate_dataset(out, 1, 1, seed=3, cfg=cfg, workers=1)


@pytest.mark.slow
def test_a_failed_trials_start_leaves_the_folder_usable(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / CAMPAIGN).write_text(json.dumps({"seed": 99, "perception": "oracle"}))  # what a start that failed left
    run_trials(out, 1, seed=0, perception="oracle", workers=1, cfg=TrialConfig(), display=Display(progress=False))
    assert json.loads((out / CAMPAIGN).read_text())["seed"] == 0 and (out / EPISODES).read_text().count("\n") == 1
    with pytest.raises(UserError, match="different campaign"):
        run_trials(out, 1, seed=1, perception="oracle", workers=1, cfg=TrialConfig(), display=Display(progress=False))
