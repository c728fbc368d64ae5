"""The bench scripts' tools (never their timings): ``bench/profile.py`` writes a profile of a tiny job, and
``bench/baseline.py`` checks a ref out so that its own code is imported, not the installed checkout's."""

from __future__ import annotations

import importlib.util
import os
import pstats
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _bench_module(name: str):
    spec = importlib.util.spec_from_file_location(f"bench_{name}", ROOT / "bench" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_profile_writes_a_profile_and_its_table_and_the_baselines(tmp_path: Path) -> None:
    """The job's profile and table, and with ``--baseline REF`` REF's beside them, made from REF's worktree."""
    env = {**os.environ, "MUJOCO_GL": "egl", "PYOPENGL_PLATFORM": "egl"}
    r = subprocess.run([sys.executable, str(ROOT / "bench" / "profile.py"), "datagen", "--size", "1", "--top", "5",
                        "--out", str(tmp_path), "--baseline", "HEAD"], env=env, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    sha = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                         text=True).stdout.strip()
    # the current profile's code from this checkout; REF's from its worktree (``baseline.checkout``'s temporary folder)
    for stem, where in (("datagen", str(ROOT)), (f"datagen@{sha}", "/posegrasp_baseline_")):
        stats = pstats.Stats(str(tmp_path / f"{stem}.prof"))
        files = {file for file, _, fn in stats.stats if fn == "generate_scene"}
        assert files, f"{stem}: the job's work is not in the profile"
        assert all(where in str(Path(f).resolve()) for f in files), (stem, files)
        text = (tmp_path / f"{stem}.txt").read_text()
        assert "function (by cumulative)" in text and "function (by tottime)" in text
        assert "generate_scene" in text  # the job's own frames, not the harness's


def test_baseline_options_are_not_passed_on() -> None:
    own_argv = _bench_module("baseline").own_argv
    assert own_argv(["200", "2", "--baseline", "cb9cd60", "--rounds=3", "--seed", "0", "--baseline-script",
                     "current"]) == ["200", "2", "--seed", "0"]


@pytest.mark.slow
def test_baseline_checkout_imports_its_own_code() -> None:
    """PYTHONPATH=WORKTREE imports every part from the worktree (the editable install maps them elsewhere), and the
    worktree is gone afterwards."""
    baseline = _bench_module("baseline")
    with baseline.checkout("HEAD") as tree:
        files = baseline._imported_from({**os.environ, "PYTHONPATH": str(tree)})
        assert all(Path(f).is_relative_to(tree.resolve()) for f in files.values()), files
    assert not tree.exists()
    listed = subprocess.run(["git", "-C", str(ROOT), "worktree", "list"], capture_output=True, text=True).stdout
    assert str(tree) not in listed


def test_shared_inputs_are_made_once_per_comparison(tmp_path: Path, monkeypatch) -> None:
    """Inside a comparison the first run's arrays are saved and later runs load them without making them."""
    import numpy as np

    baseline = _bench_module("baseline")
    made = []

    def make():
        made.append(1)
        return np.arange(6.0).reshape(2, 3), np.eye(3, dtype=np.float32)

    monkeypatch.delenv(baseline.SHARED, raising=False)
    baseline.shared_input("x.npz", make)
    assert len(made) == 1 and not list(tmp_path.iterdir())  # outside a comparison: made, nothing saved
    monkeypatch.setenv(baseline.SHARED, str(tmp_path))
    first = baseline.shared_input("x.npz", make)
    again = baseline.shared_input("x.npz", make)
    assert len(made) == 2 and len(again) == 2
    assert all(a.dtype == b.dtype and np.array_equal(a, b) for a, b in zip(first, again))


def test_host_names_the_cpu_its_features_and_the_caps_set(monkeypatch) -> None:
    """A comparison's figures carry the machine's CPU, cores, vector features (from /proc/cpuinfo) and any variable
    capping the libraries' instructions."""
    baseline = _bench_module("baseline")
    for k in baseline.ISA_CAPS:
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX2")
    h = baseline.host()
    assert h["cores"] == os.cpu_count() and h["caps"] == {"ONEDNN_MAX_CPU_ISA": "AVX2"}
    assert set(h["features"]) <= set(baseline.FEATURES.values()) and len(set(h["features"])) == len(h["features"])
    flags = next((ln for ln in Path("/proc/cpuinfo").read_text().splitlines() if ln.startswith("flags")), "").split()
    assert ("AVX2" in h["features"]) == ("avx2" in flags)
    assert ("AMX" in h["features"]) == ("amx_int8" in flags)
