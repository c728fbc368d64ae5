"""A full disk, for every command that writes: one line ``posegrasp: error: no space left on <folder>``, exit 74, no
traceback, and nothing a later run trusts; once there is room, the same command (``train`` with ``--resume``) ends
with the files of a run that never met a full disk (wall-clock fields aside).

Each command runs in the same relative folder twice: on an ample disk (the reference), then on a small tmpfs sized
to about half of what the reference wrote, which is then enlarged for the rerun. Mounting needs root: elsewhere
these tests are skipped with that reason."""

from __future__ import annotations

import os
import shutil
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import pytest
import trimesh
from faults import (TINY_DATAGEN_TOML, TINY_TRAIN_TOML, SmallDisk, assert_one_line, assert_same_tree,
                    make_tiny_bop)
from helpers import build_once, run_cli

PAGE = 4096
NO_SPACE_LINE = r"posegrasp: error: no space left on \S+"


@pytest.fixture
def small_disk(tmp_path: Path):
    """A 64 KiB tmpfs under ``tmp_path``, unmounted afterwards; skipped where it cannot be mounted."""
    if os.geteuid() != 0:
        pytest.skip(reason="mounting a small tmpfs (a disk to fill up) needs root")
    root = tmp_path / "disk"
    root.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(root)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(reason=f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield SmallDisk(root)
    finally:
        subprocess.run(["umount", "-l", str(root)], capture_output=True)


def _write_inputs(d: Path) -> None:
    (d / "datagen.toml").write_text(TINY_DATAGEN_TOML)
    (d / "train.toml").write_text(TINY_TRAIN_TOML)
    trimesh.creation.box([0.06, 0.04, 0.02]).export(d / "box.obj")
    trimesh.creation.cylinder(0.015, 0.05, sections=16).export(d / "cyl.stl")
    assert run_cli("objects", "import", str(d / "box.obj"), str(d / "cyl.stl"), "--out", str(d / "set"),
                   "--no-progress").returncode == 0
    make_tiny_bop(d / "bop")


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, Path]:
    """Inputs the commands read: a tiny dataset, settings, meshes and an object set (built once for the run's
    workers)."""
    d = build_once(tmp_path_factory, "full_disk_inputs", _write_inputs)
    return {"data": d / "bop", "datagen": d / "datagen.toml", "train": d / "train.toml", "box": d / "box.obj",
            "cyl": d / "cyl.stl", "set": d / "set"}


@pytest.fixture(scope="module")
def trained(inputs, tmp_path_factory) -> Path:
    """A run with all four stages trained for 2 steps (built once for the run's workers)."""
    def train(run: Path) -> None:
        for stage in ("seg", "pose", "refiner", "cls"):
            r = run_cli("train", stage, "--data", str(inputs["data"]), "--out", str(run), "--config",
                        str(inputs["train"]), "--steps", "2", "--no-progress")
            assert r.returncode == 0, r.stderr

    return build_once(tmp_path_factory, "full_disk_trained", train)


@pytest.fixture(scope="module")
def trial_run(tmp_path_factory) -> Path:
    """A 2-episode oracle campaign (built once for the run's workers)."""
    def campaign(d: Path) -> None:
        r = run_cli("trials", "--episodes", "2", "--seed", "0", "--workers", "1", "--out", str(d / "run"),
                    "--no-progress")
        assert r.returncode == 0, r.stderr

    return build_once(tmp_path_factory, "full_disk_trials", campaign) / "run"


@dataclass
class Case:
    """A writing command: ``args`` run in a folder whose ``out`` it writes; ``prepare(folder)`` first."""

    args: list[str]
    rerun: list[str] = field(default_factory=list)  # extra arguments of the rerun
    prepare: Callable[[Path], None] = lambda folder: None
    fraction: float = 0.5  # of the reference's pages the small disk holds


def pages_kib(root: Path) -> int:
    """KiB of whole pages the files under ``root`` take on a tmpfs."""
    return sum(-(-p.stat().st_size // PAGE) * PAGE for p in root.rglob("*") if p.is_file()) // 1024


def full_disk_then_resume(case: Case, disk, ref: Path) -> None:
    ref.mkdir()
    case.prepare(ref)
    before = pages_kib(ref)
    r = run_cli(*case.args, cwd=ref)
    assert r.returncode == 0, r.stderr
    wrote = pages_kib(ref) - before
    disk.resize(200 * 1024)
    case.prepare(disk.root)
    disk.resize(pages_kib(disk.root) + int(case.fraction * wrote) // 4 * 4 + 4)
    filler = disk.root / ".filler"  # a page, so that even a 0 KiB room is a non-zero tmpfs size
    filler.write_bytes(b"\0" * PAGE)
    full = run_cli(*case.args, cwd=disk.root)
    assert full.returncode == 74, f"rc {full.returncode}:\n{full.stderr}"
    assert_one_line(full.stderr, NO_SPACE_LINE)
    filler.unlink()
    disk.resize(200 * 1024)
    again = run_cli(*case.args, *case.rerun, cwd=disk.root)
    assert again.returncode == 0, again.stderr
    assert_same_tree(disk.root, ref)


def copy_stages(run: Path, *stages: str) -> Callable[[Path], None]:
    def prepare(folder: Path) -> None:
        for s in stages:
            shutil.copytree(run / s, folder / "out" / s)
    return prepare


def test_scene(small_disk, tmp_path):
    full_disk_then_resume(Case(["scene", "--seed", "0", "--blocks", "2", "--resolution", "80x60", "--out", "out"]),
                          small_disk, tmp_path / "ref")


def test_datagen(small_disk, tmp_path, inputs):
    full_disk_then_resume(Case(["datagen", "--out", "out", "--scenes", "3", "--views", "2", "--seed", "0", "--workers",
                                "1", "--config", str(inputs["datagen"]), "--no-progress"]), small_disk, tmp_path / "ref")


def test_dataset_show(small_disk, tmp_path, inputs):
    full_disk_then_resume(Case(["dataset", "show", str(inputs["data"]), "--split", "train", "--scene", "0", "--im",
                                "0", "--out", "out/show.png"]), small_disk, tmp_path / "ref")


def test_dataset_merge(small_disk, tmp_path, inputs):
    full_disk_then_resume(Case(["dataset", "merge", "out", f"{inputs['data']}:train", f"{inputs['data']}:train"]),
                          small_disk, tmp_path / "ref")


def test_calibrate(small_disk, tmp_path):
    full_disk_then_resume(Case(["calibrate", "--out", "out/hand_eye.json", "--poses", "3"]), small_disk,
                          tmp_path / "ref")


def test_objects_import(small_disk, tmp_path, inputs):
    full_disk_then_resume(Case(["objects", "import", str(inputs["box"]), str(inputs["cyl"]), "--out", "out",
                                "--no-progress"]), small_disk, tmp_path / "ref")


def test_objects_show(small_disk, tmp_path, inputs):
    full_disk_then_resume(Case(["objects", "show", str(inputs["set"]), "--out", "out/show.png"]), small_disk,
                          tmp_path / "ref")


@pytest.mark.slow
@pytest.mark.parametrize("stage, needs", [("seg", ()), ("pose", ()), ("refiner", ("pose",)), ("cls", ("seg",))])
def test_train(small_disk, tmp_path, inputs, trained, stage, needs):
    full_disk_then_resume(Case(["train", stage, "--data", str(inputs["data"]), "--out", "out", "--config",
                                str(inputs["train"]), "--steps", "6", "--no-progress"], rerun=["--resume"],
                               prepare=copy_stages(trained, *needs)), small_disk, tmp_path / "ref")


@pytest.mark.slow
def test_eval(small_disk, tmp_path, inputs, trained):
    full_disk_then_resume(Case(["eval", "--data", str(inputs["data"]), "--weights", str(trained), "--out", "out",
                                "--max-images", "2", "--no-progress"]), small_disk, tmp_path / "ref")


@pytest.mark.slow
def test_perturb(small_disk, tmp_path, trained):
    full_disk_then_resume(Case(["perturb", "--weights", str(trained), "--out", "out", "--rel-sigma", "0.1",
                                "--stages", "seg,pose"]), small_disk, tmp_path / "ref")


@pytest.mark.slow
def test_trials(small_disk, tmp_path):
    full_disk_then_resume(Case(["trials", "--episodes", "2", "--seed", "0", "--workers", "1", "--out", "out",
                                "--export-captures", "captures", "--no-progress"]), small_disk, tmp_path / "ref")


@pytest.mark.slow
def test_report(small_disk, tmp_path, trial_run):
    def prepare(folder: Path) -> None:
        shutil.copytree(trial_run, folder / "out", ignore=shutil.ignore_patterns("report.html"))

    full_disk_then_resume(Case(["report", "out"], prepare=prepare), small_disk, tmp_path / "ref")


@pytest.mark.slow
def test_compare(small_disk, tmp_path, trial_run):
    full_disk_then_resume(Case(["compare", str(trial_run), str(trial_run), "--out", "out/compare.json"]), small_disk,
                          tmp_path / "ref")
