"""A bin-picking episode replayed from its recorded seeds (``run_episode`` with hooks that only watch): the
overview camera's tote before and after, a film of the episode from it, and the hand camera's capture of every
failed attempt with the provider's estimates. Only for the oracle providers, whose estimates cost nothing: a
model provider's network would run at every attempt again."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from posegrasp.errors import DatasetError
from posegrasp.executor import Executor, SerialExecutor
from posegrasp.grasping.record import BinPickRecord
from posegrasp.grasping.report.resim import Look
from posegrasp.grasping.runfolder import read_campaign
from posegrasp.sim.workcell import Workcell

#: Providers whose bin-picking episodes the report replays (cheap: no network).
REPLAYED = ("oracle", "noisy-oracle")
#: The film: its size (px), a frame at least every ``FILM_PERIOD_S`` simulated seconds, at most ``FILM_FRAMES``.
FILM_SIZE, FILM_PERIOD_S, FILM_FRAMES = (320, 240), 0.25, 120


def replayable(perception: str) -> bool:
    """Does the report replay bin-picking episodes of the provider ``perception`` (``REPLAYED``)?"""
    return perception.split(":", 1)[0] in REPLAYED


@dataclass
class BinReplay:
    """A replayed bin-picking episode: overview images (uint8 RGB) of the tote before the first and after the
    last attempt, the film's frames (``FILM_SIZE``) each ``period_s`` simulated seconds, and the look of each
    failed attempt by its index."""

    before: np.ndarray
    after: np.ndarray
    film: list[np.ndarray]
    period_s: float
    failed: dict[int, Look] = field(default_factory=dict)


class _Film:
    """``on_step`` hook: the overview camera, a frame each ``period_s`` simulated seconds from the first step."""

    def __init__(self, period_s: float):
        self.period_s, self.frames, self.wc, self.cam, self.next_t = period_s, [], None, None, 0.0

    def __call__(self, wc: Workcell) -> None:
        if self.cam is None:
            from posegrasp.sim.camera import CameraRenderer
            from posegrasp.sim.workcell import OVERVIEW_CAMERA

            c = dataclasses.replace(wc.cfg.overview_camera, width=FILM_SIZE[0], height=FILM_SIZE[1])
            self.wc, self.cam = wc, CameraRenderer.from_config(wc, OVERVIEW_CAMERA, c, wc.cfg.render)
            self.next_t = wc.data.time
        if wc.data.time >= self.next_t - 1e-9 and len(self.frames) < FILM_FRAMES:
            self.frames.append(self.cam.rgb())
            self.next_t += self.period_s

    def last(self) -> np.ndarray:
        """The overview now (after the episode)."""
        return self.cam.rgb()


def replay_bin_episode(run_dir: Path, rec: BinPickRecord) -> BinReplay | None:
    """Bin-picking episode ``rec`` of the run in ``run_dir`` replayed from its seeds (None: it never moved the
    arm). A DatasetError when the replay's record differs from ``rec`` (the code changed since the run)."""
    from posegrasp.catalog import catalog_by_id
    from posegrasp.grasping.episode import EpisodeTask, run_episode
    from posegrasp.grasping.perception import PerceptionError, perceive
    from posegrasp.grasping.provider_registry import make_provider
    from posegrasp.sim.camera import Frame

    campaign = read_campaign(run_dir)
    task = EpisodeTask(rec.seed, rec.episode, rec.perception, campaign.config, campaign.T_gripper_cam)
    failed = {a.attempt for a in rec.attempts if a.outcome != "success"}
    frames: dict[int, Frame] = {}
    film = _Film(max(FILM_PERIOD_S, rec.sim_time / FILM_FRAMES))

    def keep(wc: Workcell, frame: Frame, im_id: int) -> None:
        if im_id in failed:
            frames[im_id] = frame

    try:
        again, _ = run_episode(task, on_capture=keep, on_step=film)
        if again.to_json() != rec.to_json():
            raise DatasetError(f"episode {rec.episode} of {run_dir} does not replay to its record: the code changed "
                               "since the run; rerun the trials")
        if film.cam is None:
            return None
        provider, objects = make_provider(rec.perception, film.wc.cfg.objects), film.wc.cfg.objects
        looks = {}
        for a, frame in sorted(frames.items()):
            seed = _seed(task, a)
            try:
                ests = perceive(provider, frame, seed, task.index, a, known_ids=catalog_by_id(objects),
                                timeout_s=task.cfg.perception_timeout_s)
            except PerceptionError:
                ests = []
            looks[a] = Look(frame, ests, np.asarray(frame.mask), np.zeros((1, 1, 3), np.uint8), objects)
        return BinReplay(film.frames[0], film.last(), film.frames, film.period_s, looks)
    finally:
        if film.cam is not None:
            film.cam.close()


def _seed(task, attempt: int) -> int:
    """The perception seed of ``attempt`` (as ``bin_picking.empty_tote`` draws it)."""
    from posegrasp.grasping.episode import episode_draws, further_seed

    return episode_draws(task)[2] if attempt == 0 else further_seed(task, attempt)


def _replay_task(item: tuple[Path, BinPickRecord]) -> BinReplay | None:
    """``replay_bin_episode(*item)``: a plain function of one argument, as executors take."""
    return replay_bin_episode(*item)


def replay_bin_episodes(run_dir: Path, episodes: Sequence[BinPickRecord],
                        executor: Executor | None = None) -> dict[int, BinReplay | None]:
    """``replay_bin_episode`` of each episode, by episode index, run by ``executor`` or in this process."""
    done = (executor or SerialExecutor()).imap(_replay_task, [(run_dir, r) for r in episodes])
    return {episodes[i].episode: r for i, r in done}
