"""The one reader of input files (``posegrasp.inputs``) and the one rule for output paths (``posegrasp.outputs``,
``posegrasp.lock``): each hostile case is one line naming the path, at once, with nothing changed on disk."""

from __future__ import annotations

import json
import os
import socket
import struct
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from posegrasp import inputs
from posegrasp.errors import UserError
from posegrasp.lock import folder_lock
from posegrasp.outputs import Record, check_out_file, mark_image, mark_json, written_by


def _make(kind: str, p: Path) -> None:
    if kind == "fifo":
        os.mkfifo(p)
    elif kind == "folder":
        p.mkdir()
    elif kind == "socket":
        s = socket.socket(socket.AF_UNIX)
        s.bind(p.name)
        s.close()
    elif kind == "devzero":
        p.symlink_to("/dev/zero")
    elif kind == "loop":
        p.symlink_to(p.name)
    else:
        p.symlink_to("nowhere")


@pytest.mark.parametrize("kind, words", [("fifo", "FIFO"), ("folder", "folder"), ("socket", "socket"),
                                         ("devzero", "character device"), ("loop", "link loop"),
                                         ("broken", "broken link")])
def test_only_regular_files_are_read_and_only_the_missing_are_missing(tmp_path, monkeypatch, kind, words):
    monkeypatch.chdir(tmp_path)
    p = tmp_path / "camera.json"
    _make(kind, p)
    t0 = time.monotonic()
    with pytest.raises(UserError, match=words) as e:
        inputs.read_json(p)
    assert time.monotonic() - t0 < 1 and "does not exist" not in str(e.value)
    with pytest.raises(UserError, match="does not exist"):
        inputs.read_json(tmp_path / "none.json")


def test_sizes_nesting_keys_and_numbers_are_bounded(tmp_path):
    big = tmp_path / "big.json"
    big.write_bytes(b"")
    os.truncate(big, inputs.LIMITS["json"] + 1)
    with pytest.raises(UserError, match="more than a json file may be"):
        inputs.read_json(big)
    for text, words in (("[" * 100000 + "]" * 100000, "nested more than"), ('{"a": 1, "a": 2}', "appears twice"),
                        ('{"score": 1e400}', "not finite"), ('{"x": NaN}', "valid JSON"),
                        ('{"s": "' + "[" * 1000 + '"}', None)):
        if words is None:
            assert inputs.parse_json(text, "t") == {"s": "[" * 1000}  # brackets inside a string do not nest
            continue
        with pytest.raises(UserError, match=words):
            inputs.parse_json(text, "t")
    with pytest.raises(UserError, match="TOML nested more than"):
        inputs.parse_toml("a = " + "[" * 2000 + "]" * 2000, "t")
    assert inputs.parse_toml('a = "[[[["  # [[[\nb = [[1]]', "t") == {"a": "[[[[", "b": [[1]]}


def _png(w: int, h: int) -> bytes:
    data = cv2.imencode(".png", np.zeros((4, 4), np.uint8))[1].tobytes()
    body = b"IHDR" + struct.pack(">II", w, h) + data[24:29]
    return data[:8] + struct.pack(">I", 13) + body + struct.pack(">I", zlib.crc32(body)) + data[33:]


def test_image_headers_and_damage_are_refused_quietly(capfd):
    with pytest.raises(UserError, match="claims 100000x100000 px"):
        inputs.decode_image(_png(100000, 100000), "x.png")
    jpg = cv2.imencode(".jpg", (np.random.default_rng(0).random((48, 64, 3)) * 255).astype(np.uint8))[1].tobytes()
    assert inputs.image_size(jpg) == (64, 48)
    with pytest.raises(UserError, match="truncated or corrupt"):
        inputs.decode_image(jpg[:len(jpg) // 2] + b"\xff\xd9", "cut.jpg")
    assert capfd.readouterr().err == "", "the codec's own message reached the terminal"


def test_an_output_file_replaces_only_its_own_command_s(tmp_path):
    mine, theirs = tmp_path / "cmp.json", tmp_path / "notes.json"
    mine.write_text(json.dumps(mark_json({"a": 1}, "compare")))
    theirs.write_text('{"a": 1}')
    assert written_by(mine) == "posegrasp compare" and check_out_file(mine, "compare") == mine
    with pytest.raises(UserError, match="not a file written by 'posegrasp compare'"):
        check_out_file(theirs, "compare")
    assert check_out_file(theirs, "compare", force=True) == theirs
    run = tmp_path / "run"
    run.mkdir()
    (run / "campaign.json").write_text(json.dumps(mark_json({}, "compare")))
    with pytest.raises(UserError, match="is an input"):
        check_out_file(run / "campaign.json", "compare", [run], force=True)
    with pytest.raises(UserError, match="inside"):
        check_out_file(run / "new.png", "dataset show", sealed=[run])
    png = tmp_path / "v.png"
    png.write_bytes(mark_image(cv2.imencode(".png", np.zeros((4, 4), np.uint8))[1].tobytes(), "dataset show"))
    assert written_by(png) == "posegrasp dataset show" and cv2.imread(str(png)) is not None
    (tmp_path / "ln.json").symlink_to(mine)
    with pytest.raises(UserError, match="is a link"):
        check_out_file(tmp_path / "ln.json", "compare")


def test_a_folder_is_known_by_its_record_s_content_and_a_lock_link_is_not_followed(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "metrics.json").write_text('{"mine": 1}')
    with pytest.raises(UserError, match="not written by this command"):
        with folder_lock(out, owns=(Record("metrics.json", ("data", "split")),)):
            pass
    (out / "metrics.json").write_text('{"data": "ds", "split": "test", "x": NaN}')
    with folder_lock(out, owns=(Record("metrics.json", ("data", "split")),)):
        pass
    victim = tmp_path / "victim"
    victim.write_text("keep")
    (out / ".posegrasp.lock").symlink_to(victim)
    with pytest.raises(UserError, match="lock file is a link"):
        with folder_lock(out):
            pass
    assert victim.read_text() == "keep"


#: A plug-in whose ``estimate`` forks a child that sleeps (holding the campaign's pipe open), writes the child's pid
#: into the file ``obs`` names, then exits with status 3 (ARGS ``exit``) or sleeps (``hang``).
FORKER = """
import os, time
from pathlib import Path

class Forker:
    name = "forker"

    def __init__(self, then):
        self.then = then

    def estimate(self, obs, seed):
        pid = os.fork()
        if pid == 0:
            time.sleep(3600)
            os._exit(0)
        Path(obs).write_text(str(pid))
        if self.then == "exit":
            os._exit(3)
        time.sleep(3600)

def make(args=None):
    return Forker(args)
"""


def _forker(tmp_path: Path, then: str) -> str:
    (tmp_path / "forker.py").write_text(FORKER)
    return f"py:{tmp_path / 'forker.py'}:make:{then}"


def _running(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/status").read_text().split("State:")[1].split()[0] not in ("Z", "X")
    except (OSError, IndexError):
        return False


def _ends(pid: int) -> bool:
    """Whether the process ``pid`` ends within 5 s."""
    deadline = time.monotonic() + 5
    while _running(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    return not _running(pid)


def test_a_plugin_that_exits_is_reported_as_exited_and_what_it_forked_ends(tmp_path):
    from posegrasp.errors import PerceptionError
    from posegrasp.grasping.provider_registry import make_provider

    p = make_provider(_forker(tmp_path, "exit"), "", 60)
    t0 = time.monotonic()
    with pytest.raises(PerceptionError, match="exited with status 3"):
        p.estimate(str(tmp_path / "pid"), 0)
    assert time.monotonic() - t0 < 10, "an exited plug-in was waited for as a slow one"
    assert _ends(int((tmp_path / "pid").read_text())), "the plug-in's forked child outlived it"



CAMPAIGN = """
import sys
from posegrasp.grasping.provider_registry import make_provider
make_provider(sys.argv[1], "", 0).estimate(sys.argv[2], 0)
"""


def test_a_campaign_killed_with_sigkill_takes_what_the_plugin_forked_with_it(tmp_path):
    import signal
    import subprocess
    import sys

    pid_file = tmp_path / "pid"
    campaign = subprocess.Popen([sys.executable, "-c", CAMPAIGN, _forker(tmp_path, "hang"), str(pid_file)])
    deadline = time.monotonic() + 60
    while not (pid_file.exists() and pid_file.read_text()) and time.monotonic() < deadline:
        time.sleep(0.05)
    campaign.send_signal(signal.SIGKILL)
    campaign.wait(10)
    assert _ends(int(pid_file.read_text())), "the plug-in's forked child outlived the campaign"
