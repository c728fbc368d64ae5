"""Helpers of the fault tests: a small tmpfs to fill up, file trees compared without their wall-clock fields, a
tiny BOP dataset and training settings, and a command interrupted once its progress shows on disk."""

from __future__ import annotations

import csv
import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import pytest
from helpers import cli

#: Per file name, the keys holding wall-clock time (documented as such): left out when runs are compared.
WALL_CLOCK_KEYS = {"state.json": ("elapsed_s",), "summary.json": ("wall",), "metrics.json": ("time_per_image_s",)}
#: Per file name suffix, CSV columns of wall-clock time (training metrics, BOP results).
WALL_CLOCK_COLUMNS = {".csv": ("time_s", "time")}
#: Files holding wall-clock times only.
WALL_CLOCK_FILES = ("timings.jsonl",)

#: Training settings small enough for a few seconds a stage on the tiny dataset; a checkpoint every 2 steps.
#: datagen settings for tiny frames (80 x 60) and few blocks.
TINY_DATAGEN_TOML = """
blocks = [2, 3]
[workcell.hand_camera]
width = 80
height = 60
"""

TINY_TRAIN_TOML = """
[seg]
batch_size = 2
lr = 0.05
log_every = 1
checkpoint_every = 2
eval_every = 0
[seg.model]
width = 0.125
input_size = [96, 128]
[seg.data]
num_model_points = 200
model_pool = 1000

[pose]
batch_size = 2
lr = 1e-3
log_every = 3
checkpoint_every = 2
eval_every = 0
[pose.model]
num_points = 32
crop_size = 32
backbone_width = 8
emb_dim = 16
head_widths = [64, 32, 16]
[pose.data]
num_model_points = 200
model_pool = 1000

[refiner]
batch_size = 2
lr = 1e-3
log_every = 1
checkpoint_every = 2
eval_every = 0
[refiner.data]
num_model_points = 200
model_pool = 1000

[cls]
batch_size = 8
lr = 1e-2
log_every = 1
checkpoint_every = 2
eval_every = 0
[cls.model]
widths = [8, 16]
crop_size = 32
"""


class SmallDisk:
    """A tmpfs mounted at ``root`` whose size the test sets (root only; ``mount`` fails elsewhere)."""

    def __init__(self, root: Path):
        self.root = root

    def resize(self, kib: int) -> None:
        """The disk's size in KiB (rounded up to whole pages by the kernel)."""
        subprocess.run(["mount", "-o", f"remount,size={kib}k", str(self.root)], check=True, capture_output=True)


def _without(obj, keys: tuple[str, ...]):
    return {k: v for k, v in obj.items() if k not in keys} if isinstance(obj, dict) else obj


def comparable(path: Path, root: Path) -> bytes:
    """A file's bytes with its documented wall-clock fields left out, and ``root`` (where the run was) as ``ROOT``."""
    data = path.read_bytes().replace(str(root).encode(), b"ROOT")
    if path.name in WALL_CLOCK_FILES:
        return b""
    if path.name in WALL_CLOCK_KEYS:
        return json.dumps(_without(json.loads(data), WALL_CLOCK_KEYS[path.name])).encode()
    for suffix, cols in WALL_CLOCK_COLUMNS.items():
        if path.name.endswith(suffix):
            rows = list(csv.DictReader(io.StringIO(data.decode())))
            return json.dumps([_without(r, cols) for r in rows]).encode()
    return data


def tree(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` (relative path -> ``comparable`` bytes)."""
    return {str(p.relative_to(root)): comparable(p, root) for p in sorted(root.rglob("*")) if p.is_file()}


def assert_same_tree(got: Path, want: Path) -> None:
    a, b = tree(got), tree(want)
    assert sorted(a) == sorted(b), f"files differ: only in {got}: {sorted(set(a) - set(b))}, " \
                                   f"only in {want}: {sorted(set(b) - set(a))}"
    differ = [k for k in a if a[k] != b[k]]
    assert not differ, f"files with other bytes than an uninterrupted run's: {differ}"


def assert_one_line(stderr: str, pattern: str) -> None:
    """stderr is exactly one line, matching the regular expression ``pattern``."""
    import re

    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and re.fullmatch(pattern, lines[0]), f"expected one line like {pattern!r}, got:\n{stderr}"


def make_tiny_bop(root: Path) -> Path:
    """The perception tests' tiny BOP dataset (3 objects, train and test splits of 160 x 120 px) at ``root``, drawn
    in a child process: pyrender's EGL teardown would end the display this process's MuJoCo renders with."""
    tests = Path(__file__).parent
    code = ("import sys, importlib.util; from pathlib import Path; sys.path[:0] = [sys.argv[1]]; "
            "spec = importlib.util.spec_from_file_location('tiny_bop_maker', Path(sys.argv[1]) / 'perception' / "
            "'conftest.py'); mod = importlib.util.module_from_spec(spec); spec.loader.exec_module(mod); "
            "mod.make_tiny_bop(Path(sys.argv[2]))")
    r = subprocess.run([sys.executable, "-c", code, str(tests), str(root)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    return root


def interrupt_when(args: list[str], cwd: Path, ready: Callable[[], bool], timeout: float = 120
                   ) -> subprocess.CompletedProcess:
    """Run ``posegrasp ARGS`` in ``cwd`` in a new process group, send the group SIGINT (as Ctrl-C in a terminal
    does) once ``ready()`` holds, and return the finished process."""
    # Ctrl-C's default action in the child, whatever this process (a test runner that ignores it) passes on
    proc = subprocess.Popen(cli(*args), cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    t0 = time.monotonic()
    try:
        while not ready():
            if proc.poll() is not None:
                out, err = proc.communicate()
                pytest.fail(f"{args[0]} ended (rc {proc.returncode}) before it was interrupted:\n{err}")
            assert time.monotonic() - t0 < timeout, f"{args[0]}: no progress within {timeout} s"
            time.sleep(0.01)
        os.killpg(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
