"""The trial report: written by every trial run, self-contained, and shown with all its images by Chromium."""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from posegrasp.grasping.config import TrialConfig
from posegrasp.grasping.report import REPORT, read_run, register, resimulate_look, write_report
from posegrasp.grasping.runfolder import EPISODES
from posegrasp.grasping.trials import run_trials
from posegrasp.errors import UserError

pytestmark = pytest.mark.slow  # a 3-episode campaign, its re-simulated frames and Chromium

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync"]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("trials")
    summary = run_trials(out, 3, seed=0, perception="oracle", workers=1, cfg=TrialConfig())
    return out, summary


def test_trials_write_a_self_contained_report(run):
    out, s = run
    page = (out / REPORT).read_text()
    assert not re.search(r"""(src|href)\s*=\s*["']?\s*(https?:)?//""", page, re.I)
    assert "http://" not in page and "https://" not in page
    assert f"<b>{s['success']}/{s['n']}</b>" in page
    lo, hi = s["wilson95"]
    assert f"{100 * lo:.1f}-{100 * hi:.1f} %" in page
    assert f"{100 * s['rate']:.1f} %" in page
    for block, row in s["per_block"].items():
        assert f"<td>{block}</td><td>{row['success']}</td><td>{row['n']}</td>" in page
    imgs = re.findall(r'<img [^>]*src="data:image/(?:png|jpeg);base64,[A-Za-z0-9+/=]+"', page)
    # plot + 2 per sample episode (3 episodes) + an overview per episode (3)
    assert len(imgs) == 1 + 2 * 3 + 3


def test_report_frame_is_the_episodes_look_capture(run):
    """Re-simulation reproduces the episode's look: the provider finds the recorded number of blocks."""
    out, _ = run
    rec = read_run(out).episodes[0]
    look = resimulate_look(out, rec)
    assert look is not None and len(look.estimates) == rec.detected
    assert look.labels.shape == look.frame.rgb.shape[:2] and look.labels.max() >= 1
    assert look.overview.ndim == 3 and look.overview.std() > 5


def test_run_folder_reads_into_typed_records(run, tmp_path):
    out, s = run
    read = read_run(out)
    lines = (out / EPISODES).read_text().splitlines()
    assert [e.to_json() for e in read.episodes] == [json.loads(line) for line in lines]
    assert (read.summary.overall.success, read.summary.overall.n) == (s["success"], s["n"])
    assert list(read.summary.per_block) == list(s["per_block"])
    bad = tmp_path / "bad"
    shutil.copytree(out, bad)
    (bad / EPISODES).write_text(re.sub(r'"n_blocks":\d+', '"n_blocks":"many"', lines[0]) + "\n")
    with pytest.raises(UserError, match="line 1.n_blocks: expected int"):
        read_run(bad)


def test_report_command_and_bad_folder(run, tmp_path):
    out, _ = run
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    (out / REPORT).unlink()
    args = parser.parse_args(["report", str(out), "--samples", "1", "--strip", "0"])
    assert args.run(args) == 0
    assert len(re.findall(r"<img ", (out / REPORT).read_text())) == 1 + 2
    with pytest.raises(UserError, match="no episodes.jsonl"):
        write_report(tmp_path)


def _chromium(tmp_path: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(CHROMIUM), *CHROMIUM_FLAGS, f"--user-data-dir={tmp_path / 'profile'}", *extra],
                          capture_output=True, text=True, timeout=120)


def test_report_loads_in_headless_chromium(run, tmp_path):
    if not CHROMIUM.exists():
        pytest.skip(reason="chromium not installed: apt-get install -y chromium (the Makefile's CI setup does)")
    out, _ = run
    write_report(out)
    url = (out / REPORT).resolve().as_uri()
    shot = tmp_path / "shot.png"
    _chromium(tmp_path, f"--screenshot={shot}", "--window-size=1200,2000", url)
    assert shot.exists(), "chromium wrote no screenshot"
    pixels = np.asarray(Image.open(shot).convert("RGB"), dtype=np.float32)
    assert pixels.shape[:2] == (2000, 1200) and pixels.std() > 20
    dom = _chromium(tmp_path, "--dump-dom", url).stdout
    n = len(re.findall(r"<img ", (out / REPORT).read_text()))
    assert f"<title>images decoded: {n}/{n}</title>" in dom
