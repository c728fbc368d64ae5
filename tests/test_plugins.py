"""Perception plug-ins end to end: a provider outside the package (a file or module by ``py:``, an installed entry
point, the depth-only example) drives real trial campaigns; bad providers fail their episodes with "perception
error", never the campaign."""

from __future__ import annotations

import dataclasses
import io
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console

from helpers import run_cli
from posegrasp.errors import UserError
from posegrasp.grasping.config import TrialConfig
from posegrasp.grasping.perception import Estimate, PerceptionError, call_with_timeout, checked_estimates
from posegrasp.grasping.provider_registry import make_provider
from posegrasp.grasping.runfolder import EPISODES
from posegrasp.grasping.trials import Display, run_trials

ROOT = Path(__file__).resolve().parents[1]
CFG = TrialConfig(min_blocks=1, max_blocks=1)

#: A plug-in that checks what it receives, logs each call into the folder ARGS and finds nothing.
SPY = '''
import json, os
import numpy as np

class Spy:
    name = "spy"

    def __init__(self, folder):
        self.folder = folder

    def estimate(self, obs, seed):
        assert obs.rgb.dtype == np.uint8 and obs.rgb.shape == (obs.height, obs.width, 3)
        assert obs.depth.dtype == np.float32 and obs.depth.shape == (obs.height, obs.width)
        assert 0.2 < float(np.median(obs.depth)) < 1.0  # metres
        assert obs.K.shape == (3, 3) and not hasattr(obs, "mask")
        with open(os.path.join(self.folder, f"{obs.scene_id}_{obs.im_id}_{os.getpid()}.json"), "w") as f:
            json.dump({"scene_id": obs.scene_id, "im_id": obs.im_id, "seed": seed}, f)
        return []

def make(args):
    return Spy(args)
'''

#: A plug-in that misbehaves in a different way in each episode (``obs.scene_id``).
BAD = '''
import time
from dataclasses import dataclass
import numpy as np

@dataclass
class E:
    obj_id: int
    T_cam_obj: object
    score: float

MODES = ["raise", "type", "nan", "rot", "mm", "id", "hang", "item", "shape", "score"]

class Bad:
    name = "bad"

    def estimate(self, obs, seed):
        mode = MODES[obs.scene_id]
        T = np.eye(4)
        T[2, 3] = 0.4
        if mode == "raise":
            raise RuntimeError("model file missing")
        if mode == "type":
            return {"obj_id": 1}
        if mode == "nan":
            T[0, 3] = float("nan")
        if mode == "rot":
            T[:3, :3] *= 1.01
        if mode == "mm":
            T[:3, 3] *= 1000
        if mode == "hang":
            time.sleep(3600)
        if mode == "item":
            return [(1, T, 1.0)]
        if mode == "shape":
            T = T[:3]
        return [E(99 if mode == "id" else 1, T, float("inf") if mode == "score" else 0.9)]

def make(args):
    return Bad()
'''

#: What each BAD episode records as its perception error.
BAD_WORDS = ["raised RuntimeError: model file missing", "returned dict, not a list of Estimate", "NaN",
             "not orthonormal", "millimetres?", "obj_id 99 is not in the object set", "did not answer within 5 s",
             "is a tuple, not an Estimate", "shape (3, 4)", "score inf is not finite"]


def _records(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / EPISODES).read_text().splitlines()]


def _quiet() -> Console:
    return Console(file=io.StringIO())


@pytest.mark.slow
def test_plugin_file_and_module_drive_trials_with_one_and_two_workers(tmp_path, monkeypatch):
    (tmp_path / "spy_provider.py").write_text(SPY)
    calls1, calls2 = tmp_path / "calls1", tmp_path / "calls2"
    calls1.mkdir()
    calls2.mkdir()
    monkeypatch.chdir(tmp_path)  # a relative file path: recorded absolute, found by the workers
    run_trials(tmp_path / "a", 2, 0, f"py:spy_provider.py:make:{calls1}", 1, CFG, Display(_quiet(), False))
    assert not (tmp_path / "__pycache__").exists()  # the plug-in file was loaded without writing beside it
    monkeypatch.syspath_prepend(str(tmp_path))  # the same plug-in as an importable module, in two workers
    run_trials(tmp_path / "b", 2, 0, f"py:spy_provider:make:{calls2}", 2, CFG, Display(_quiet(), False))
    a, b = _records(tmp_path / "a"), _records(tmp_path / "b")
    assert [r["failure"] for r in a] == ["no detection"] * 2
    assert a[0]["perception"] == f"py:{tmp_path / 'spy_provider.py'}:make:{calls1}"
    assert [dict(r, perception=None) for r in a] == [dict(r, perception=None) for r in b]
    for calls in (calls1, calls2):  # the pick-area look of each episode (and the report's), its ids in obs
        assert {p.name.rsplit("_", 1)[0] for p in calls.glob("*.json")} == {"0_0", "1_0"}
    pids = [{int(p.stem.split("_")[2]) for p in calls.glob("*.json")} for calls in (calls1, calls2)]
    assert os.getpid() not in pids[0] | pids[1]  # the plug-in runs in a process of its own (grasping.plugin_host)


@pytest.mark.slow
def test_bad_providers_fail_their_episodes_not_the_campaign(tmp_path):
    (tmp_path / "bad.py").write_text(BAD)
    cfg = dataclasses.replace(CFG, perception_timeout_s=5.0)  # the hung call costs it; the rest answer in it under load
    t0 = time.perf_counter()
    summary = run_trials(tmp_path / "run", len(BAD_WORDS), 0, f"py:{tmp_path / 'bad.py'}:make", 2, cfg,
                         Display(_quiet(), False))
    recs = _records(tmp_path / "run")
    assert [r["failure"] for r in recs] == ["perception error"] * len(BAD_WORDS)
    for r, words in zip(recs, BAD_WORDS):
        assert words in r["perception_error"] and "\n" not in r["perception_error"], (r["episode"], r)
    assert summary["failures"] == {"perception error": len(BAD_WORDS)}
    assert "perception error" in (tmp_path / "run" / "report.html").read_text()
    assert time.perf_counter() - t0 < 120  # the hung provider cost its timeout, not an hour


def test_checks_accept_good_estimates_and_name_the_bad_one():
    T = np.eye(4)
    T[:3, 3] = (0.01, -0.02, 0.45)
    good = checked_estimates([Estimate(2, T, 0.5), Estimate(np.int64(3), T.tolist(), np.float32(1.0))], {2, 3})
    assert [(e.obj_id, e.score) for e in good] == [(2, 0.5), (3, 1.0)] and good[1].T_cam_obj.dtype == np.float64
    assert checked_estimates((), {1}) == []
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # det -1: a reflection
    bad = T.copy()
    bad[:3, :3] = R
    with pytest.raises(PerceptionError, match=r"estimate 1 \(obj_id 2\).*det -1"):
        checked_estimates([Estimate(2, T, 0.5), Estimate(2, bad, 0.5)], {2})
    with pytest.raises(PerceptionError, match="obj_id True is not an integer"):
        checked_estimates([Estimate(True, T, 0.5)])


def test_timeout_restores_a_running_timer_and_works_off_the_main_thread():
    fired = []
    old = signal.signal(signal.SIGALRM, lambda *a: fired.append(1))
    try:
        signal.setitimer(signal.ITIMER_REAL, 2.0)
        with pytest.raises(PerceptionError, match="within 0.2 s"):
            call_with_timeout(lambda: time.sleep(30), 0.2)
        assert call_with_timeout(lambda: 7, 0.2) == 7
        left = signal.getitimer(signal.ITIMER_REAL)[0]
        assert 1.0 < left < 2.0  # the caller's timer is back, less the time spent
        signal.setitimer(signal.ITIMER_REAL, 0)
    finally:
        signal.signal(signal.SIGALRM, old)
    out: list = []

    def in_thread() -> None:
        try:
            call_with_timeout(lambda: time.sleep(30), 0.2)
        except PerceptionError as e:
            out.append(str(e))
        out.append(call_with_timeout(lambda: 5, 0.2))

    t = threading.Thread(target=in_thread)
    t.start()
    t.join(10)
    assert out[1] == 5 and "within 0.2 s" in out[0]


@pytest.mark.slow
def test_installed_entry_point_is_found_by_name(tmp_path):
    pkg, target = tmp_path / "pkg", tmp_path / "site"
    (pkg / "tinyprov").mkdir(parents=True)
    (pkg / "tinyprov" / "__init__.py").write_text(SPY)
    (pkg / "pyproject.toml").write_text(
        '[build-system]\nrequires = ["setuptools"]\nbuild-backend = "setuptools.build_meta"\n'
        '[project]\nname = "tinyprov"\nversion = "0.1"\n'
        '[project.entry-points."posegrasp.perception"]\ntinyprov = "tinyprov:make"\noracle = "tinyprov:make"\n')
    pip = [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--target",
           str(target), str(pkg)]
    subprocess.run(pip, check=True, capture_output=True, timeout=180)
    env = dict(os.environ, PYTHONPATH=str(target))
    calls = tmp_path / "calls"
    calls.mkdir()
    run = run_cli("trials", "--perception", f"tinyprov:{calls}", "--episodes", "1", "--workers", "1", "--no-progress",
                  "--out", str(tmp_path / "run"), env=env)
    assert run.returncode == 0, run.stderr
    assert [p.name.split("_")[:2] for p in calls.glob("*.json")] == [["0", "0"]]
    assert _records(tmp_path / "run")[0]["failure"] == "no detection"
    names = subprocess.run([sys.executable, "-c", NAMES], env=env, capture_output=True, text=True, timeout=120)
    built_in, unknown = names.stdout.splitlines()
    assert built_in == "OracleProvider", names.stderr  # a built-in name wins over an installed one
    assert "installed: oracle, tinyprov" in unknown


#: Prints the class ``--perception oracle`` builds and the error for an unknown name.
NAMES = """from posegrasp.errors import UserError
from posegrasp.grasping.provider_registry import make_provider
print(type(make_provider("oracle")).__name__)
try:
    make_provider("sonar")
except UserError as e:
    print(e)
"""


@pytest.mark.slow
def test_depth_only_example_grasps_blocks(tmp_path):
    spec = f"py:{ROOT / 'examples' / 'providers' / 'depth_only.py'}:make_provider"
    provider = make_provider(spec)
    assert provider.name == "depth-only"
    with pytest.raises(UserError, match="MIN_HEIGHT_MM,MAX_POINTS"):
        make_provider(spec + ":five")
    summary = run_trials(tmp_path / "run", 2, 0, spec, 1, dataclasses.replace(CFG, max_blocks=3), Display(_quiet(), False))
    recs = _records(tmp_path / "run")
    assert summary["success"] == 2, recs
    assert all(r["failure"] != "perception error" for r in recs)
    assert all(r["pose_error"]["err"] < 0.01 for r in recs)  # ADD(-S) under 1 cm
