"""Pool workers die with their parent, whatever kills it, and never write after it: SIGKILL lands on the parent
only (not its process group) of a 2-worker datagen and a 2-worker trials run; 5 s later no worker is alive,
nothing in ``--out`` changed, and a resumed run gives the bytes of an uninterrupted one."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest
from helpers import cli
from test_datagen import file_hashes

from posegrasp.datagen.config import load_datagen_config
from posegrasp.datagen.generate import generate_dataset, is_complete
from posegrasp.grasping.config import TrialConfig
from posegrasp.grasping.runfolder import EPISODES
from posegrasp.grasping.trials import Display, run_trials

TINY_TOML = """
blocks = [2, 3]
[workcell.hand_camera]
width = 80
height = 60
"""


def children(pid: int) -> dict[int, str]:
    """Processes whose parent is ``pid``: their command lines."""
    out = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            if int(fields[1]) == pid:
                out[int(stat.parent.name)] = (stat.parent / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except (OSError, IndexError, ValueError):
            continue
    return out


def alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, dead but not yet reaped by its new parent, counts as dead)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def listing(root: Path) -> dict[str, tuple[int, int]]:
    """Every file under ``root``: (size, mtime in ns)."""
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns) for p in root.rglob("*") if p.is_file()}


def kill_parent_when(proc: subprocess.Popen, ready, what: str) -> dict[int, str]:
    """Wait until ``ready()`` with two pool workers (forked or spawned: not multiprocessing's resource tracker) up,
    SIGKILL the parent alone; its children before the kill."""
    t0 = time.monotonic()
    while True:
        assert proc.poll() is None, f"{what} ended before the kill: {proc.stderr.read().decode()}"
        assert time.monotonic() - t0 < 240, f"{what}: never ready"
        kids = children(proc.pid)
        if sum("resource_tracker" not in c for c in kids.values()) >= 2 and ready():
            break
        time.sleep(0.01)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    return kids


def assert_orphans_gone_and_nothing_written(kids: dict[int, str], out: Path) -> None:
    before = listing(out)
    time.sleep(5.0)
    left = [f"{pid}: {cmd}" for pid, cmd in kids.items() if alive(pid)]
    for pid in kids:  # clean up whatever the assertion below reports
        if alive(pid):
            os.kill(pid, signal.SIGKILL)
    assert not left, f"workers outlived their parent: {left}"
    assert listing(out) == before, "files were written after the parent was killed"


@pytest.fixture(scope="module")
def tiny_toml(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("cfg") / "tiny.toml"
    p.write_text(TINY_TOML)
    return p


@pytest.mark.slow
def test_datagen_workers_die_with_their_parent(tmp_path, tiny_toml):
    out = tmp_path / "killed"
    # 8 scenes: tiny ones finish fast, so with fewer the pool's results may all be written within one poll
    args = ["datagen", "--out", str(out), "--scenes", "8", "--views", "3", "--seed", "5", "--workers", "2",
            "--config", str(tiny_toml), "--no-progress"]
    proc = subprocess.Popen(cli(*args), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    try:
        kids = kill_parent_when(proc, lambda: is_complete(out, "train_pbr", 0), "datagen")
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert not all(is_complete(out, "train_pbr", s) for s in range(8)), "the run finished before it was killed"
    assert_orphans_gone_and_nothing_written(kids, out)
    generate_dataset(out, 8, 3, 5, load_datagen_config(tiny_toml), workers=1)  # resumed
    ref = tmp_path / "reference"
    generate_dataset(ref, 8, 3, 5, load_datagen_config(tiny_toml), workers=1)
    assert file_hashes(out) == file_hashes(ref)


@pytest.mark.slow
def test_trials_workers_die_with_their_parent(tmp_path):
    out = tmp_path / "killed"
    args = ["trials", "--out", str(out), "--episodes", "2", "--seed", "4", "--workers", "2", "--perception", "oracle",
            "--no-progress"]
    proc = subprocess.Popen(cli(*args), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    lines = lambda: (out / EPISODES).read_text().count("\n") if (out / EPISODES).exists() else 0  # noqa: E731
    try:
        kids = kill_parent_when(proc, lambda: lines() >= 1, "trials")
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert_orphans_gone_and_nothing_written(kids, out)
    ref = tmp_path / "reference"
    run_trials(ref, 2, seed=4, perception="oracle", workers=1, cfg=TrialConfig(), display=Display(progress=False))
    run_trials(out, 2, seed=4, perception="oracle", workers=1, cfg=TrialConfig(), display=Display(progress=False))
    assert (out / EPISODES).read_bytes() == (ref / EPISODES).read_bytes()


@pytest.mark.slow
def test_a_pool_keeps_its_workers_inside_a_with_block_and_ends_them_after():
    from posegrasp.executor import PoolExecutor

    with PoolExecutor(2) as ex:
        first = {pid for _, pid in ex.imap(_pid_after_a_moment, range(6))}
        second = {pid for _, pid in ex.imap(_pid_after_a_moment, range(6))}
        assert len(first) == 2 and second == first  # the same two warm processes served both calls
    deadline = time.time() + 10
    while time.time() < deadline and any(_alive(p) for p in first):
        time.sleep(0.1)
    assert not any(_alive(p) for p in first)
    assert {pid for _, pid in PoolExecutor(2).imap(_pid_after_a_moment, range(2))}.isdisjoint(first)


def test_pool_workers_render_on_their_share_of_the_cores_unless_told(monkeypatch):
    from posegrasp.executor import RENDER_THREADS_ENV, PoolExecutor, render_threads

    monkeypatch.delenv(RENDER_THREADS_ENV, raising=False)
    share = str((os.cpu_count() or 1) // 2 if (os.cpu_count() or 1) >= 4 else 0)
    assert render_threads(2) == int(share) and render_threads(os.cpu_count() or 1) == 0
    assert {v for _, v in PoolExecutor(2).imap(os.getenv, [RENDER_THREADS_ENV] * 2)} == {share}
    monkeypatch.setenv(RENDER_THREADS_ENV, "3")
    assert {v for _, v in PoolExecutor(1).imap(os.getenv, [RENDER_THREADS_ENV])} == {"3"}


def test_datagen_forks_its_workers_until_its_process_renders():
    """``posegrasp datagen``'s process loads no torch and opens no GL display (dm_control's renderer is imported
    switched off), so its workers are forked, with its modules; while it runs a second thread, and once it renders,
    they are spawned."""
    import sys

    code = ("import threading; from posegrasp.datagen import cli, generate; from posegrasp import executor, gl; "
            "print(executor.fork_is_safe()); e = threading.Event(); t = threading.Thread(target=e.wait); t.start(); "
            "print(executor.fork_is_safe()); e.set(); t.join(); gl.make_current(); print(executor.fork_is_safe())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["True", "False", "False"]


def _pid_after_a_moment(_: int) -> int:
    time.sleep(0.2)  # long enough for both workers to take tasks
    return os.getpid()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.mark.slow
@pytest.mark.parametrize("where", ["consumer", "waiting"])
def test_ctrl_c_ends_the_pool_at_once_without_a_thread_traceback(where, monkeypatch, request):
    """Ctrl-C inside the caller's loop, or while it waits for a result: the running tasks (a minute long) are not
    waited for, and no thread of the pool reports an exception (a future cancelled under the manager thread of a
    broken pool raises InvalidStateError there)."""
    import threading

    from posegrasp.executor import PoolExecutor

    errors: list[str] = []
    monkeypatch.setattr(threading, "excepthook", lambda a: errors.append(f"{a.thread.name}: {a.exc_type.__name__}"))
    # Ctrl-C raises KeyboardInterrupt here even when the test runner was started with SIGINT ignored
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    request.addfinalizer(lambda: signal.signal(signal.SIGINT, previous))
    t0 = time.monotonic()
    pids: list[int] = []
    with pytest.raises(KeyboardInterrupt):
        with PoolExecutor(2) as ex:
            for _, pid in ex.imap(_pid_then_sleep, range(12)):  # task 0 answers at once, the rest sleep
                pids.append(pid)
                if where == "consumer":
                    raise KeyboardInterrupt
                threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGINT)).start()
    assert time.monotonic() - t0 < 30, "the running tasks were waited for"
    assert errors == []
    assert not _alive(pids[0])


def _pid_then_sleep(i: int) -> int:
    if i:
        time.sleep(60)
    return os.getpid()
