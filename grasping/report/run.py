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
class BinPickSummary:
    """Bin picking's summary (``summary.json``'s ``bin_pick``, ``tasks.bin_pick.bin_metrics``)."""

    percent_cleared: float | None  # mean over the episodes (%)
    percent_cleared_ci95: tuple[float, float] | None  # its Student-t 95 % interval (None: under 2 episodes)
    episodes_cleared: int
    parts_present: int
    parts_removed: int
    attempts: Rate  # attempts that put their part alone into the out-box
    grasps: Rate | None  # those of the attempts that went for a part (None: a summary written before it was kept)
    sim_hours: float
    picks_per_sim_hour: float | None
    attempt_failures: dict[str, int]  # attempts by failure reason
    episode_ends: dict[str, int]  # episodes by how they ended ("cleared" or a failure reason)
    per_type: dict[str, Rate]  # attempts by the target's part type
    per_visibility: dict[str, Rate]  # attempts by the target's visible fraction (``VISIBILITY_BINS``)

    @classmethod
    def from_json(cls, data: dict, where: str) -> BinPickSummary:
        """The ``bin_pick`` block ``data``; a DatasetError naming ``where``."""
        try:
            pc = data["percent_cleared"]
            return cls(None if pc["mean"] is None else float(pc["mean"]),
                       None if pc["ci95"] is None else (float(pc["ci95"][0]), float(pc["ci95"][1])),
                       int(data["episodes_cleared"]), int(data["parts_present"]), int(data["parts_removed"]),
                       _rate(data["attempts"], f"{where}.attempts"),
                       _rate(data["grasps"], f"{where}.grasps") if "grasps" in data else None, float(data["sim_hours"]),
                       None if data["picks_per_sim_hour"] is None else float(data["picks_per_sim_hour"]),
                       {str(f): int(k) for f, k in data["attempt_failures"].items()},
                       {str(f): int(k) for f, k in data["episode_ends"].items()},
                       {str(t): _rate(r, f"{where}.per_type.{t}") for t, r in data["per_type"].items()},
                       {str(b): _rate(r, f"{where}.per_visibility.{b}") for b, r in data["per_visibility"].items()})
        except (KeyError, TypeError, ValueError, AttributeError, IndexError):
            raise DatasetError(f"{where} is corrupt (needs the keys of bin picking's summary); rerun the trials "
                               "into a new --out") from None


@dataclass(frozen=True)
class Summary:
    """The campaign statistics the report shows, as ``summary.json`` holds them (``stats.summarise``)."""

    overall: Rate  # episodes that succeeded
    grasp_success: Rate  # episodes whose block was grasped
    per_block: dict[str, Rate]  # by the target's catalogue name
    failures: dict[str, int]  # episodes by failure reason
    mean_pose_error_m: float | None  # ADD(-S) of the grasped estimates (m); None: no estimate
    mean_sim_time_s: float  # simulated seconds per episode
    bin_pick: BinPickSummary | None = None  # bin picking's own statistics (None: another task)

    @classmethod
    def from_json(cls, data: dict, where: str = SUMMARY) -> Summary:
        """The summary in a ``summary.json`` dict (its other keys ignored); a DatasetError naming ``where``."""
        try:
            return cls(_rate(data, where), _rate(data["grasp_success"], f"{where}.grasp_success"),
                       {str(b): _rate(r, f"{where}.per_block.{b}") for b, r in data["per_block"].items()},
                       {str(f): int(k) for f, k in data["failures"].items()},
                       None if data.get("mean_pose_error_m") is None else float(data["mean_pose_error_m"]),
                       float(data["mean_sim_time_s"]),
                       BinPickSummary.from_json(data["bin_pick"], f"{where}.bin_pick") if "bin_pick" in data else None)
        except (KeyError, TypeError, ValueError, AttributeError):
            raise DatasetError(f"{where} is corrupt (needs success, n, rate, wilson95, grasp_success, per_block, "
                            "failures and mean_sim_time_s); rerun the trials into a new --out") from None


def _rate(data: dict, where: str) -> Rate:
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
