"""The offline BOP path: a campaign's captures exported as a BOP test split (``--export-captures``), a BOP results
file replayed as a provider (``--perception bop-csv:``), and the link between them exact: the shipped model's
``posegrasp eval`` results replayed give the very episodes the live model gives."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console

from posegrasp import bop
from posegrasp.bop import results as bop_results
from posegrasp.bop.check import check_dataset
from posegrasp.errors import UserError
from posegrasp.grasping.bop_csv import BopCsvProvider, from_spec
from posegrasp.grasping.captures import export_captures
from posegrasp.grasping.compare import compare_runs, load_run
from posegrasp.grasping.config import TrialConfig
from posegrasp.grasping.model_provider import SHIPPED_MODEL
from posegrasp.grasping.perception import Observation
from posegrasp.grasping.runfolder import EPISODES, read_records
from posegrasp.grasping.trials import Display, campaign_settings, run_trials
from posegrasp.lock import folder_lock

QUIET = dict(display=Display(Console(file=io.StringIO()), False))
QUIET_EXPORT = dict(console=Console(file=io.StringIO()), progress=False)


def files(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` (relative path -> bytes)."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def captures_only(root: Path, episodes: int, cfg: TrialConfig, seed: int = 0) -> dict:
    cfg, mount = campaign_settings(episodes, cfg)
    return export_captures(root, episodes, seed, 1, cfg, mount, **QUIET_EXPORT)


def records(run: Path) -> dict[int, dict]:
    """The run's episode records without the provider's name."""
    return {i: {k: v for k, v in r.items() if k != "perception"} for i, r in read_records(run / EPISODES).items()}


@pytest.mark.slow
def test_stack_captures_equal_the_full_episodes_and_resume(tmp_path):
    """Both looks of two stack episodes: the full episodes' export is byte for byte the captures-only one, a valid
    BOP test split; a scene left incomplete by a kill is redone identically; the folder is locked and bound."""
    cfg = TrialConfig(task="stack")
    run_trials(tmp_path / "run", 2, 0, "oracle", 1, cfg, export=tmp_path / "full", **QUIET)
    out = captures_only(tmp_path / "only", 2, cfg)
    assert out["images"] == 4
    full, only = files(tmp_path / "full"), files(tmp_path / "only")
    assert only == full
    assert {"test/000001/rgb/000000.png", "test/000001/rgb/000001.png", "test/000001/depth/000001.png",
            "test_targets_bop19.json", "camera.json", "models/models_info.json"} <= set(only)
    report = check_dataset(tmp_path / "only")
    assert report.ok, report.problems[:3]
    assert report.images == 4
    assert bop.load_camera(tmp_path / "only").depth_scale == 0.1
    cams = bop.load_scene_camera(tmp_path / "only" / "test" / "000000" / "scene_camera.json")
    assert cams[1].T_cam_world is not None  # the camera's world pose at the base look

    # a kill while scene 1 was written: its last file missing, a temporary file left
    (tmp_path / "only" / "test" / "000001" / "scene_gt_info.json").unlink()
    (tmp_path / "only" / "test" / ".x.tmp").write_bytes(b"torn")
    assert captures_only(tmp_path / "only", 2, cfg)["captured_episodes"] == 1
    assert files(tmp_path / "only") == full
    with pytest.raises(UserError, match="other settings"):
        captures_only(tmp_path / "only", 2, cfg, seed=1)
    with folder_lock(tmp_path / "only"), pytest.raises(UserError, match="in use by another posegrasp process"):
        captures_only(tmp_path / "only", 2, cfg)


@pytest.mark.slow
def test_replayed_eval_results_give_the_live_model_episodes(tmp_path):
    """Two pick-and-place episodes: the live model (exporting its captures) and the replay of ``posegrasp eval``'s
    results on the captures-only export record the same episodes (outcome, pose error, everything); compare
    pairs a bop-csv run with a model run and an oracle run."""
    cfg = TrialConfig()
    n = 2
    captures_only(tmp_path / "export", n, cfg)
    run_trials(tmp_path / "live", n, 0, "model", 1, cfg, export=tmp_path / "live_export", **QUIET)
    assert files(tmp_path / "live_export") == files(tmp_path / "export")

    from posegrasp.perception.evaluate import EvalConfig, evaluate

    evaluate(tmp_path / "export", SHIPPED_MODEL, tmp_path / "eval", EvalConfig(threads=1, min_mask_px=150),
             progress=False)
    csv = tmp_path / "eval" / "posegrasp_export-test.csv"
    run_trials(tmp_path / "replay", n, 0, f"bop-csv:{csv}", 1, cfg, **QUIET)
    live, replay = records(tmp_path / "live"), records(tmp_path / "replay")
    assert live == replay, {e: {k: (r.get(k), replay[e].get(k)) for k in r if r.get(k) != replay[e].get(k)}
                            for e, r in live.items()}
    assert all(r["pose_error"] is not None for r in live.values())
    assert {r["perception"] for r in read_records(tmp_path / "replay" / EPISODES).values()} == {f"bop-csv:{csv}"}

    same = compare_runs(load_run(tmp_path / "live"), load_run(tmp_path / "replay"))
    assert same["episodes"] == n and same["difference"] == 0 and same["mcnemar"]["a_only"] == 0
    assert (same["a"]["perception"], same["b"]["perception"]) == ("model", f"bop-csv:{csv}")
    run_trials(tmp_path / "oracle", n, 0, "oracle", 1, cfg, **QUIET)
    assert compare_runs(load_run(tmp_path / "oracle"), load_run(tmp_path / "replay"))["episodes"] == n


def test_bop_csv_rows_by_frame(tmp_path):
    """Rows reach the frame they name, several instances of an object included, in metres; other frames get
    nothing; the file is read once per process while it is unchanged."""
    T = np.eye(4)
    T[:3, 3] = [0.01, -0.02, 0.4]
    T2 = T.copy()
    T2[0, 3] = 0.05
    rows = [bop_results.PoseResult(0, 0, 3, 0.5, T), bop_results.PoseResult(0, 0, 3, 0.25, T2), bop_results.PoseResult(1, 1, 2, 0.9, T)]
    path = bop_results.write_results_csv(tmp_path / "r.csv", rows)
    provider = from_spec(str(path))
    obs = Observation(np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4), np.float32), np.eye(3), 0, 0)
    got = provider.estimate(obs, seed=0)
    assert [(e.obj_id, e.score) for e in got] == [(3, 0.5), (3, 0.25)]
    assert np.array_equal(got[0].T_cam_obj, T) and np.array_equal(got[1].T_cam_obj, T2)
    got[0].T_cam_obj[0, 0] = 7  # a caller changing its estimate changes no later answer
    assert provider.estimate(obs, seed=0)[0].T_cam_obj[0, 0] == 1
    assert provider.estimate(Observation(obs.rgb, obs.depth, obs.K, 0, 1), seed=0) == []
    assert [e.obj_id for e in provider.estimate(Observation(obs.rgb, obs.depth, obs.K, 1, 1), seed=0)] == [2]
    assert provider.name == f"bop-csv:{path.resolve()}"
    path.write_text(path.read_text().splitlines()[0] + "\n")  # rewritten: read again
    assert BopCsvProvider(str(path.resolve())).estimate(obs, seed=0) == []
