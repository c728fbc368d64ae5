"""Rival fits: one observed part posed as several types, of which one is right.

The objects of a frame's fit that show the same ``part`` compete. Twice, once all objects' fits are ranked (after the
first grid steps, with ``steps_margin``; after the turns, with ``turns_margin``), an object whose best ranked score
plus its ``cost`` trails the best of its part by more than the margin is fitted no further and reports no fit (score
inf):

    drop o   if   min_h s_h + cost_o > min_{o' of o's part} (min_h s_h + cost_o') + margin      (h: o's fits)

The ranking scores match the observed points to the model's points rather than its surface, so they lie a little
above the final scores, for every type of a part alike; the costs are the type check's -weight ln p
(``perception.type_check``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from posegrasp.errors import ConfigError


@dataclass(frozen=True)
class Rivals:
    """For the O objects of one fit: the part each shows (O,) (objects of one part are rivals), each one's cost (O,)
    (m) added to its scores when rivals are compared, and the margins (m) beyond which a rival is dropped after the
    first grid steps and after the turns."""

    part: list[int]
    cost: list[float]
    steps_margin: float = float("inf")
    turns_margin: float = float("inf")

    def __post_init__(self) -> None:
        if len(self.part) != len(self.cost):
            raise ConfigError(f"Rivals: {len(self.part)} parts for {len(self.cost)} costs; give one of each per object")

    def take(self, objects: list[int]) -> Rivals:
        """The rivals among ``objects`` (indices), in that order."""
        return Rivals([self.part[o] for o in objects], [self.cost[o] for o in objects], self.steps_margin,
                      self.turns_margin)

    def losers(self, score: torch.Tensor, obj: torch.Tensor, margin: float) -> torch.Tensor:
        """The objects (bool (O,)) whose best score among the rows ``score`` (H,) of objects ``obj`` (H,), plus their
        cost, trails the best of their part by more than ``margin`` (m); an object without rows is no loser."""
        best = torch.full((len(self.part),), torch.inf, dtype=torch.float64)
        cost = best.scatter_reduce(0, obj, score.double(), "amin").numpy() + np.asarray(self.cost, dtype=np.float64)
        part = np.asarray(self.part)
        lead = np.full(part.max() + 1 if len(part) else 0, np.inf)
        np.minimum.at(lead, part, cost)
        return torch.from_numpy(np.isfinite(cost) & (cost > lead[part] + margin))

    def rows(self, score: torch.Tensor, obj: torch.Tensor, margin: float) -> torch.Tensor:
        """The rows (bool (H,)) of the objects that are no ``losers``."""
        return ~self.losers(score, obj, margin)[obj]
