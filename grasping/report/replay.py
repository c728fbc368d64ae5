"""An episode replayed whole from its recorded seeds (``run_episode`` with hooks that only watch): the overview
camera's scene before and after, a film of the episode from it, and the hand camera's captures the page asks for
(bin picking: those of the failed attempts) with the provider's estimates. Only for the oracle providers, whose
estimates cost nothing: a model provider's network would run at every capture again."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

from posegrasp.errors import DatasetError
from posegrasp.executor import Executor, SerialExecutor
from posegrasp.grasping.record import EpisodeRecord
from posegrasp.grasping.report.figures import Look
from posegrasp.sim.workcell import Workcell

if TYPE_CHECKING:
    from posegrasp.grasping.episode import EpisodeJob

#: Providers whose episodes the report replays whole (cheap: no network).
REPLAYED = ("oracle", "noisy-oracle")
#: The film: its size (px), a frame at least every ``FILM_PERIOD_S`` simulated seconds, at most ``FILM_FRAMES``.
FILM_SIZE, FILM_PERIOD_S, FILM_FRAMES = (320, 240), 0.25, 120


def replayable(perception: str) -> bool:
    """Does the report replay episodes of the provider ``perception`` whole (``REPLAYED``)?"""
    return perception.split(":", 1)[0] in REPLAYED


@dataclass
class Replay:
    """A replayed episode: overview images (uint8 RGB) of the scene before the first and after the last move,
    the film's frames (``FILM_SIZE``) each ``period_s`` simulated seconds, and the looks kept, by ``im_id``."""

    before: np.ndarray
    after: np.ndarray
    film: list[np.ndarray]
    period_s: float
    looks: dict[int, Look] = field(default_factory=dict)


class _Film:
    """``on_step`` hook: the overview camera, a frame each ``period_s`` simulated seconds from the first step."""

    def __init__(self, period_s: float):
        self.period_s, self.frames, self.wc, self.cam, self.next_t = period_s, [], None, None, 0.0

    def __call__(self, wc: Workcell) -> None:
        if self.cam is None:
            from posegrasp.sim.camera import CameraRenderer
            from posegrasp.sim.workcell import OVERVIEW_CAMERA

            c = dataclasses.replace(wc.cfg.overview_camera, width=FILM_SIZE[0], height=FILM_SIZE[1])
            self.wc, self.cam = wc, CameraRenderer(wc, OVERVIEW_CAMERA, c, wc.cfg.render)
            self.next_t = wc.data.time
        if wc.data.time >= self.next_t - 1e-9 and len(self.frames) < FILM_FRAMES:
            self.frames.append(self.cam.rgb())
            self.next_t += self.period_s

    def last(self) -> np.ndarray:
        """The overview now (after the episode)."""
        return self.cam.rgb()


#: ``seed_of(job, im_id)``: the perception seed the episode drew for its capture ``im_id``.
SeedOf = Callable[["EpisodeJob", int], int]


def replay_episode(job: EpisodeJob, rec: EpisodeRecord, keep: frozenset[int], seed_of: SeedOf) -> Replay | None:
    """Episode ``rec`` (of the campaign ``job`` runs) replayed from its seeds, its captures ``keep`` perceived
    again (None: it never moved the arm). A DatasetError when the replay's record differs from ``rec`` (the code
    changed since the run)."""
    from posegrasp.catalog import catalog_by_id
    from posegrasp.grasping.episode import run_episode
    from posegrasp.grasping.perception import PerceptionError, perceive
    from posegrasp.grasping.provider_registry import make_provider
    from posegrasp.sim.camera import Frame

    frames: dict[int, Frame] = {}
    film = _Film(max(FILM_PERIOD_S, rec.sim_time / FILM_FRAMES))

    def kept(wc: Workcell, frame: Frame, im_id: int, *_) -> None:
        if im_id in keep:
            frames[im_id] = frame

    try:
        again, _ = run_episode(job, on_capture=kept, on_step=film)
        if again.to_json() != rec.to_json():
            raise DatasetError(f"episode {rec.episode} does not replay to its record: the code changed since the "
                               "run; rerun the trials")
        if film.cam is None:
            return None
        provider, objects = make_provider(rec.perception, film.wc.cfg.objects), film.wc.cfg.objects
        looks = {}
        for im_id, frame in sorted(frames.items()):
            try:
                ests = perceive(provider, frame, seed_of(job, im_id), job.index, im_id,
                                known_ids=catalog_by_id(objects), timeout_s=job.cfg.perception_timeout_s)
            except PerceptionError:
                ests = []
            looks[im_id] = Look(frame, ests, np.asarray(frame.mask), np.zeros((1, 1, 3), np.uint8), objects)
        return Replay(film.frames[0], film.last(), film.frames, film.period_s, looks)
    finally:
        if film.cam is not None:
            film.cam.close()


def _replay(item: tuple[EpisodeJob, EpisodeRecord, frozenset[int], SeedOf]) -> Replay | None:
    """``replay_episode(*item)``: a plain function of one argument, as executors take."""
    return replay_episode(*item)


def replay_episodes(jobs: Sequence[tuple[EpisodeJob, EpisodeRecord, frozenset[int]]], seed_of: SeedOf,
                    executor: Executor | None = None) -> dict[int, Replay | None]:
    """``replay_episode`` of each (job, record, captures to keep), by episode index, run by ``executor`` or in this
    process."""
    done = (executor or SerialExecutor()).imap(_replay, [(*j, seed_of) for j in jobs])
    return {jobs[i][1].episode: r for i, r in done}
