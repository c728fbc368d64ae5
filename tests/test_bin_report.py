"""The report of a bin-picking run: its statistics, the attempt table, the failed attempts' captures, the tote
before and after and the episode's film, replayed from the records and shown by Chromium."""

from __future__ import annotations

import base64
import io
import json
import re

import pytest
from PIL import Image

from posegrasp.grasping.report import REPORT, read_run, write_report
from posegrasp.grasping.episode import EpisodeJob
from posegrasp.grasping.report.replay import FILM_FRAMES, FILM_SIZE, replay_episode
from posegrasp.grasping.runfolder import read_campaign
from posegrasp.grasping.tasks import get_task
from posegrasp.grasping.tasks.bin_pick.record import BinPickRecord
from posegrasp.grasping.tasks.bin_pick.report import perception_seed
from posegrasp.grasping.runfolder import EPISODES, SUMMARY
from posegrasp.grasping.trials import run_trials
from test_bin_pick import _cfg
from test_report import CHROMIUM, _chromium

pytestmark = pytest.mark.slow  # a bin-picking episode, replayed, and Chromium


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("bin")
    summary = run_trials(out, 1, seed=0, perception="oracle", workers=1, cfg=_cfg(4))
    return out, summary


def _images(page: str) -> dict[str, list[bytes]]:
    """The page's embedded images by their alt text."""
    out: dict[str, list[bytes]] = {}
    for alt, b64 in re.findall(r'<img [^>]*alt="([^"]+)"[^>]*src="data:image/\w+;base64,([A-Za-z0-9+/=]+)"', page):
        out.setdefault(alt, []).append(base64.b64decode(b64))
    return out


def test_the_bin_pick_report_shows_statistics_attempts_tote_and_film(run):
    out, s = run
    b = s["bin_pick"]
    page = (out / REPORT).read_text()
    assert "http://" not in page and "https://" not in page
    assert "episodes succeeded" not in page and "attempt success <b>" in page  # the task's own verdict heads the page
    for a in (b["attempts"], b["grasps"]):
        assert f"{a['success']}/{a['n']} = {100 * a['rate']:.1f} %" in page
    assert f"{b['parts_removed']}/{b['parts_present']}" in page
    rec = read_run(out).episodes[0]
    assert isinstance(rec, BinPickRecord) and rec.attempts
    for at in rec.attempts:  # a row per attempt: index, target, ..., outcome
        assert re.search(rf"<tr><td>{at.attempt}</td><td>[^<]+</td>(<td>[^<]*</td>){{2}}<td>{at.outcome}</td>", page)
    imgs = _images(page)
    n_failed = sum(at.outcome != "success" for at in rec.attempts)
    assert len(imgs.get("failed attempt", [])) == n_failed
    assert len(imgs["tote before"]) == len(imgs["tote after"]) == 1
    film = Image.open(io.BytesIO(imgs["episode film"][0]))
    assert film.format == "GIF" and film.size == FILM_SIZE and 1 < film.n_frames <= FILM_FRAMES
    film.seek(0)
    first = film.convert("RGB").tobytes()
    film.seek(film.n_frames - 1)
    assert film.convert("RGB").tobytes() != first  # the arm moved


def test_the_replay_reproduces_the_episode_and_its_failed_captures(run):
    out, _ = run
    rec = read_run(out).episodes[0]
    c = read_campaign(out)
    job = EpisodeJob(get_task("bin-pick"), rec.seed, rec.episode, rec.perception, c.config, c.T_gripper_cam)
    failed = frozenset(at.attempt for at in rec.attempts if at.outcome != "success")
    rp = replay_episode(job, rec, failed, perception_seed)  # raises when the replay's record differs from the record
    assert rp is not None and rp.before.shape == rp.after.shape == (FILM_SIZE[1], FILM_SIZE[0], 3)
    assert sorted(rp.looks) == sorted(failed)
    for at in rec.attempts:
        if at.attempt in rp.looks:
            assert len(rp.looks[at.attempt].estimates) >= at.detected
    lines = (out / EPISODES).read_text()
    assert json.loads(lines.splitlines()[0]) == rec.to_json()
    assert "bin_pick" in json.loads((out / SUMMARY).read_text())


def test_the_bin_pick_report_plays_in_headless_chromium(run, tmp_path):
    if not CHROMIUM.exists():
        pytest.skip(reason="chromium not installed: apt-get install -y chromium (the Makefile's CI setup does)")
    out, _ = run
    write_report(out)
    url = (out / REPORT).resolve().as_uri()
    dom = _chromium(tmp_path, "--dump-dom", url).stdout
    n = len(re.findall(r"<img ", (out / REPORT).read_text()))
    assert f"<title>images decoded: {n}/{n}</title>" in dom
    assert re.search(r'<img class="?film"? alt="episode film"', dom)
    assert "<th>attempt</th><th>target</th><th>visible fraction</th>" in dom
