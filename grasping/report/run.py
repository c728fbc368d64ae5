"""A trial run folder read into typed records: its campaign, its finished episodes and their statistics."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from posegrasp.config import from_dict
from posegrasp.errors import DatasetError
from posegrasp.grasping.record import EpisodeRecord
from posegrasp.grasping.runfolder import (CAMPAIGN, EPISODES, SUMMARY, Campaign, read_campaign, read_json_object,
                                          read_episodes, read_records)


@dataclass(frozen=True)
class Rate:
    """``success`` successes in ``n`` trials, their rate (0-1) and its Wilson 95 % interval (``stats.rate_row``)."""

    success: int
    n: int
    rate: float
    wilson95: tuple[float, float]


@dataclass(frozen=True)
class Summary:
    """The campaign statistics the report shows, as ``summary.json`` holds them (``stats.summarise``)."""

    overall: Rate  # episodes that succeeded
    grasp_success: Rate  # episodes whose block was grasped
    per_block: dict[str, Rate]  # by the target's catalogue name
    failures: dict[str, int]  # episodes by failure reason
    mean_pose_error_m: float | None  # ADD(-S) of the grasped estimates (m); None: no estimate
    mean_sim_time_s: float  # simulated seconds per episode
    data: dict = dataclasses.field(default_factory=dict)  # all of ``summary.json``: a task's own entries too

    @classmethod
    def from_json(cls, data: dict, where: str = SUMMARY) -> Summary:
        """The summary in a ``summary.json`` dict (its other keys ignored); a DatasetError naming ``where``."""
        try:
            return cls(rate_of(data, where), rate_of(data["grasp_success"], f"{where}.grasp_success"),
                       {str(b): rate_of(r, f"{where}.per_block.{b}") for b, r in data["per_block"].items()},
                       {str(f): int(k) for f, k in data["failures"].items()},
                       None if data.get("mean_pose_error_m") is None else float(data["mean_pose_error_m"]),
                       float(data["mean_sim_time_s"]), data)
        except (KeyError, TypeError, ValueError, AttributeError):
            raise DatasetError(f"{where} is corrupt (needs success, n, rate, wilson95, grasp_success, per_block, "
                            "failures and mean_sim_time_s); rerun the trials into a new --out") from None


def rate_of(data: dict, where: str) -> Rate:
    names = [f.name for f in dataclasses.fields(Rate)]
    return from_dict(Rate, {k: data[k] for k in names}, where)


@dataclass(frozen=True)
class TrialRun:
    """A trial run folder (``posegrasp trials --out``) as the report reads it."""

    path: Path
    campaign: Campaign
    episodes: list[EpisodeRecord]  # the finished episodes, by index
    summary: Summary


def read_run(run_dir: Path) -> TrialRun:
    """The run in ``run_dir`` (``campaign.json``, ``episodes.jsonl``, ``summary.json``); the summary is computed
    from the episodes when ``summary.json`` is missing (a run killed before its end). A DatasetError for a folder
    that is not a run, holds no finished episode or has a corrupt file."""
    from posegrasp.grasping.stats import summarise

    run_dir = Path(run_dir)
    for name in (EPISODES, CAMPAIGN):
        if not (run_dir / name).is_file():
            raise DatasetError(f"{run_dir} has no {name}: give a folder written by 'posegrasp trials --out'")
    if not read_records(run_dir / EPISODES):
        raise DatasetError(f"{run_dir / EPISODES} holds no finished episode: run (or resume) the trials first")
    campaign = read_campaign(run_dir)
    records = [r for _, r in sorted(read_episodes(run_dir / EPISODES).items())]
    raw, episodes = [r for r, _ in records], [e for _, e in records]
    summary = read_json_object(run_dir / SUMMARY) if (run_dir / SUMMARY).is_file() else summarise(raw)
    return TrialRun(run_dir, campaign, episodes, Summary.from_json(summary, str(run_dir / SUMMARY)))
