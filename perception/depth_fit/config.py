"""The depth fit's settings, one ``@settings`` class per stage, gathered in ``DepthFitConfig``.

Lengths in metres, angles in degrees. A value out of its range, or settings that do not fit together, raise a
ConfigError naming the setting and the value when the settings are built.
"""

from __future__ import annotations

from dataclasses import field

import numpy as np

from posegrasp.config import settings, within
from posegrasp.errors import ConfigError
from posegrasp.perception.depth_fit.starts import cube_rotations

#: ``StartConfig.hypotheses``' values.
HYPOTHESES = ("cube", "identity")


@settings
class StartConfig:
    """Where the fits start (``perception.depth_fit.starts``)."""

    #: Start rotations, object frame: "cube" (the cube group's 24, distinct under the symmetries) or "identity" (plain
    #: ICP).
    hypotheses: str = "cube"
    #: With a supporting plane, also lay each start on its nearest rest and fit it as turns about the normal and shifts
    #: along the plane.
    level_rests: bool = True

    def __post_init__(self) -> None:
        if self.hypotheses not in HYPOTHESES:
            raise ConfigError(f"StartConfig.hypotheses = {self.hypotheses!r}: use 'cube' or 'identity'")

    def rotations(self) -> np.ndarray:
        """The start rotations Q (H, 3, 3), object frame."""
        return cube_rotations() if self.hypotheses == "cube" else np.eye(3)[None]


@settings
class FitConfig:
    """The ICP steps (``perception.depth_fit.driver``) and the points they fit."""

    #: ICP steps per start, the exact steps included: all but those come before the turns, those last.
    iterations: int = field(default=12, metadata=within(0, 1000))
    #: Last steps (at most ``iterations``) matching each point to its exact nearest model point (``grids``' buckets)
    #: instead of the voxel grid's.
    exact_steps: int = field(default=3, metadata=within(0, 1000))
    #: Best-scoring fits per object (each turned >= 10 deg from the others) that go on to the exact steps (0: all).
    polish: int = field(default=3, metadata=within(0, 100000))
    #: Observed points per object (a random subset of its mask's valid depth pixels; a rigid fit needs 3).
    max_points: int = field(default=300, metadata=within(3, 10000000))
    #: Surface points sampled on each model, in random order (``ObjectModel``).
    model_points: int = field(default=1500, metadata=within(3, 10000000))


@settings
class TurnConfig:
    """The turns about the plane's normal after the first steps (``perception.depth_fit.starts.turned``)."""

    #: Turn step (deg) about the plane's normal (else the optical axis) over the object's symmetry turn about it (0: no
    #: turns).
    step_deg: float = field(default=15.0, metadata=within(0, 360))
    #: Fits per object turned: the best of each of its best-scoring rests facing up, this many rests.
    seeds: int = field(default=3, metadata=within(1, 100000))
    #: Grid steps that fit each turned start.
    iterations: int = field(default=10, metadata=within(0, 1000))


@settings
class ScoreConfig:
    """The score of a fit (``perception.depth_fit.score``)."""

    #: Distance (m) beyond which an observed point adds nothing to the fit term.
    truncation: float = field(default=0.01, metadata=within(1e-6, 10))
    #: Depth (m) a model point must lie in front of the seen surface, or under the plane, to be a violation.
    violation_margin: float = field(default=0.005, metadata=within(0, 10))
    #: Weight (m) of the share of model points in seen free space plus the share beneath the plane.
    violation_weight: float = field(default=0.01, metadata=within(0, 100))
    #: Height (m) above the plane the lowest model point may float free of charge.
    float_margin: float = field(default=0.004, metadata=within(0, 10))
    #: Weight (m) of the floating term, (height - float_margin) / 1 cm clipped to [0, 1] (0: off).
    float_weight: float = field(default=0.01, metadata=within(0, 100))
    #: Model points for the free-space, plane and floating terms when ranking starts before the exact steps (at most
    #: ``fit.model_points``); final scores use all.
    rank_points: int = field(default=500, metadata=within(1, 10000000))


@settings
class SearchConfig:
    """The searches that move each object's best fits on the final score (``perception.depth_fit.search``)."""

    #: Largest turn (deg) about the plane's normal of each object's best fit in the yaw search (0: off).
    yaw_deg: float = field(default=15.0, metadata=within(0, 180))
    #: The yaw search's step (deg): every third step within +-yaw_deg, then one step each side of the best.
    yaw_step_deg: float = field(default=1.0, metadata=within(0.001, 180))
    #: Pattern search rounds per scale (shifts along the plane and turns about its normal; 0: off).
    pattern_rounds: int = field(default=1, metadata=within(0, 1000))
    #: Fits per object the pattern search moves: its best on this many different rests.
    pattern_fits: int = field(default=2, metadata=within(1, 100000))


@settings
class DepthFitConfig:
    """Settings of the depth fit, by stage."""

    #: Start rotations and the resting starts.
    starts: StartConfig = field(default_factory=StartConfig)
    #: ICP steps and point counts.
    fit: FitConfig = field(default_factory=FitConfig)
    #: Turns about the plane's normal after the first steps.
    turns: TurnConfig = field(default_factory=TurnConfig)
    #: Terms and weights of the score.
    score: ScoreConfig = field(default_factory=ScoreConfig)
    #: Final yaw and pattern searches.
    search: SearchConfig = field(default_factory=SearchConfig)

    def __post_init__(self) -> None:
        if self.score.rank_points > self.fit.model_points:
            raise ConfigError(f"score.rank_points = {self.score.rank_points} exceeds fit.model_points = "
                              f"{self.fit.model_points}: rank on at most the model's points")

    def rotations(self) -> np.ndarray:
        """The start rotations Q (H, 3, 3), object frame (``StartConfig.rotations``)."""
        return self.starts.rotations()
