"""Trial campaigns end to end on the real simulator: success, determinism, resume, noise, statistics, CLI."""

from __future__ import annotations

import io
import json
import shutil

import pytest
from rich.console import Console

from helpers import PICK_PLACE_ORACLE, refused, run_cli, success_floor
from posegrasp.grasping.config import TrialConfig
from posegrasp.grasping.stats import wilson
from posegrasp.grasping.runfolder import EPISODES
from posegrasp.grasping.trials import Display, run_trials


@pytest.fixture(scope="module")
def oracle_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("oracle")
    return out, run_trials(out, 10, seed=0, perception="oracle", workers=2, cfg=TrialConfig())


@pytest.fixture(scope="module")
def serial_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("serial")
    console = Console(file=io.StringIO())
    run_trials(out, 4, seed=0, perception="oracle", workers=1, cfg=TrialConfig(), display=Display(console, False))
    assert "episodes succeeded" in console.file.getvalue()  # the summary is printed ...
    assert "trials oracle" not in console.file.getvalue()  # ... but no progress line
    return out


@pytest.mark.slow
def test_ten_oracle_episodes_meet_the_documented_floor(oracle_run):
    out, summary = oracle_run
    lines = (out / EPISODES).read_text().splitlines()
    recs = [json.loads(line) for line in lines]
    assert [r["episode"] for r in recs] == list(range(10))
    assert sum(r["outcome"] == "success" for r in recs) >= success_floor(*PICK_PLACE_ORACLE, 10)  # 8
    assert summary["success"] == sum(r["outcome"] == "success" for r in recs)
    lo, hi = summary["wilson95"]
    assert lo <= summary["rate"] <= hi
    for r in recs:
        assert 1 <= r["n_blocks"] <= 5 and len(r["blocks"]) == r["n_blocks"]
        if r["outcome"] == "success":
            assert r["grasped"] and r["placed"] and r["place_error"] <= 0.025
            assert r["pose_error"]["err"] < 2e-3  # oracle: only the calibrated mount's error remains
        assert sum(r["phases"].values()) == pytest.approx(r["sim_time"], abs=1e-3)
    assert (out / "timings.jsonl").exists() and (out / "summary.json").exists()


@pytest.mark.slow
def test_same_seed_same_lines_for_one_and_two_workers(oracle_run, serial_run):
    two = (oracle_run[0] / EPISODES).read_text().splitlines()[:4]
    one = (serial_run / EPISODES).read_text().splitlines()
    assert one == two


@pytest.mark.slow
def test_resume_after_a_kill_gives_the_same_file(serial_run, tmp_path):
    full = (serial_run / EPISODES).read_bytes()
    out = tmp_path / "resumed"
    shutil.copytree(serial_run, out)
    lines = full.decode().splitlines(keepends=True)
    (out / EPISODES).write_text(lines[2] + lines[0] + lines[3][:37])  # out of order, and a torn last line
    console = Console(file=io.StringIO())
    summary = run_trials(out, 4, seed=0, perception="oracle", workers=1, cfg=TrialConfig(), display=Display(console))
    assert summary["wall"]["episodes_run"] == 2
    assert "trials pick-place oracle  success" in console.file.getvalue()  # the progress line of a non-terminal console
    assert (out / EPISODES).read_bytes() == full


@pytest.mark.slow
def test_resume_refuses_a_different_campaign(serial_run, tmp_path):
    from posegrasp.errors import UserError

    out = tmp_path / "other"
    shutil.copytree(serial_run, out)
    with pytest.raises(UserError, match="different campaign"):
        run_trials(out, 4, seed=1, perception="oracle", workers=1, cfg=TrialConfig())


@pytest.mark.slow
def test_large_pose_noise_fails_more_than_small(tmp_path):
    small = run_trials(tmp_path / "small", 6, seed=3, perception="noisy-oracle:0.002,1", workers=1, cfg=TrialConfig())
    large = run_trials(tmp_path / "large", 6, seed=3, perception="noisy-oracle:0.03,30", workers=1, cfg=TrialConfig())
    assert large["mean_pose_error_m"] > 5 * small["mean_pose_error_m"]
    assert large["n"] - large["success"] > small["n"] - small["success"]
    assert large["failures"].get("pose error", 0) >= 1


@pytest.mark.parametrize("k, n, lo, hi", [
    (0, 10, 0.0, 0.277541),  # z^2/n / (1 + z^2/n)
    (10, 10, 0.722459, 1.0),
    (5, 10, 0.236590, 0.763410),
    (98, 100, 0.929987, 0.994498),
])
def test_wilson_interval_matches_hand_computation(k, n, lo, hi):
    assert wilson(k, n) == pytest.approx((lo, hi), abs=2e-6)


@pytest.mark.parametrize("args, words", [
    (["trials", "--episodes", "0"], "--episodes must be a positive integer"),
    (["trials", "--perception", "psychic"], "unknown perception"),
    (["trials", "--perception", "noisy-oracle:lots"], "TRANS_M,ROT_DEG"),
    (["trials", "--workers", "zero"], "--workers"),
    (["calibrate", "--poses", "2"], "at least 3"),
])
@pytest.mark.slow
def test_bad_input_is_one_line(tmp_path, args, words):
    if args[0] == "trials":
        args = [*args, "--out", str(tmp_path / "o")]
    else:
        args = [*args, "--out", str(tmp_path / "c.json")]
    r = run_cli(*args)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and words in lines[0] and "Traceback" not in r.stderr, r.stderr


def test_missing_calibration_is_one_line(capsys, tmp_path):
    cfg = tmp_path / "t.toml"
    cfg.write_text(f'hand_eye = "{tmp_path / "nowhere.json"}"\n')
    refused(capsys, ["trials", "--episodes", "1", "--config", cfg, "--out", tmp_path / "o"], "calibrate")
