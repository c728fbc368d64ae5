"""The depth refinement's settings, one dataclass per stage, gathered in ``RefineConfig``.

Lengths in metres, angles in degrees. ``RefineConfig.validate`` raises ConfigError naming the bad value.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from posegrasp.errors import ConfigError
from posegrasp.perception.refine.starts import cube_rotations


@dataclass
class StartConfig:
    """Where the fits start (``perception.refine.starts``)."""

    #: Start rotations, object frame: "cube" (the cube group's 24, distinct under the symmetries) or "identity" (plain
    #: ICP).
    hypotheses: str = "cube"
    #: With a supporting plane, also lay each start on its nearest rest and fit it as turns about the normal and shifts
    #: along the plane.
    level_rests: bool = True

    def rotations(self) -> np.ndarray:
        """The start rotations Q (H, 3, 3), object frame."""
        if self.hypotheses == "cube":
            return cube_rotations()
        if self.hypotheses == "identity":
            return np.eye(3)[None]
        raise ConfigError(f"ICP hypotheses must be 'cube' or 'identity', got {self.hypotheses!r}")


@dataclass
class FitConfig:
    """The ICP steps (``perception.refine.driver``) and the points they fit."""

    #: ICP steps per start, the exact steps included: all but those come before the turns, those last.
    iterations: int = 12
    #: Last steps (at most ``iterations``) matching each point to its exact nearest model point (k-d tree) instead of
    #: the voxel grid's.
    exact_steps: int = 3
    #: Best-scoring fits per object (each turned >= 10 deg from the others) that go on to the exact steps (0: all).
    polish: int = 3
    #: Observed points per object (a random subset of its mask's valid depth pixels).
    max_points: int = 300
    #: Surface points sampled on each model, in random order (``ObjectModel``).
    model_points: int = 1500


@dataclass
class TurnConfig:
    """The turns about the plane's normal after the first steps (``perception.refine.starts.turned``)."""

    #: Turn step (deg) about the plane's normal (else the optical axis) over the object's symmetry turn about it (0: no
    #: turns).
    step_deg: float = 15.0
    #: Fits per object turned: the best of each of its best-scoring rests facing up, this many rests.
    seeds: int = 3
    #: Grid steps that fit each turned start.
    iterations: int = 10


@dataclass
class ScoreConfig:
    """The score of a fit (``perception.refine.score``)."""

    #: Distance (m) beyond which an observed point adds nothing to the fit term.
    truncation: float = 0.01
    #: Depth (m) a model point must lie in front of the seen surface, or under the plane, to be a violation.
    violation_margin: float = 0.005
    #: Weight (m) of the share of model points in seen free space plus the share beneath the plane.
    violation_weight: float = 0.01
    #: Height (m) above the plane the lowest model point may float free of charge.
    float_margin: float = 0.004
    #: Weight (m) of the floating term, (height - float_margin) / 1 cm clipped to [0, 1] (0: off).
    float_weight: float = 0.01
    #: Model points for the free-space, plane and floating terms when ranking starts before the exact steps; final
    #: scores use all.
    rank_points: int = 500


@dataclass
class SearchConfig:
    """The searches that move each object's best fits on the final score (``perception.refine.search``)."""

    #: Largest turn (deg) about the plane's normal of each object's best fit in the yaw search (0: off).
    yaw_deg: float = 15.0
    #: The yaw search's step (deg): every third step within +-yaw_deg, then one step each side of the best.
    yaw_step_deg: float = 1.0
    #: Pattern search rounds per scale (shifts along the plane and turns about its normal; 0: off).
    pattern_rounds: int = 1
    #: Fits per object the pattern search moves: its best on this many different rests.
    pattern_fits: int = 2


@dataclass
class RefineConfig:
    """Settings of the depth refinement, by stage."""

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

    def rotations(self) -> np.ndarray:
        """The start rotations Q (H, 3, 3), object frame (``StartConfig.rotations``)."""
        return self.starts.rotations()

    def validate(self) -> None:
        """Raise ConfigError on an unusable configuration."""
        f, tu, s, se = self.fit, self.turns, self.score, self.search
        self.rotations()
        if min(f.iterations, f.exact_steps, f.polish) < 0:
            raise ConfigError(f"ICP fit.iterations ({f.iterations}), fit.exact_steps ({f.exact_steps}) and fit.polish "
                             f"({f.polish}) must be >= 0")
        if tu.step_deg < 0 or tu.seeds < 1 or tu.iterations < 0:
            raise ConfigError(f"ICP turns.step_deg ({tu.step_deg}) and turns.iterations ({tu.iterations}) must be >= 0 "
                             f"and turns.seeds ({tu.seeds}) >= 1")
        if se.yaw_deg < 0 or se.yaw_step_deg <= 0:
            raise ConfigError(f"ICP search.yaw_deg ({se.yaw_deg}) must be >= 0 and search.yaw_step_deg "
                             f"({se.yaw_step_deg}) positive")
        if se.pattern_rounds < 0 or se.pattern_fits < 1:
            raise ConfigError(f"ICP search.pattern_rounds ({se.pattern_rounds}) must be >= 0 and search.pattern_fits "
                             f"({se.pattern_fits}) >= 1")
        if f.model_points < 3 or not 1 <= s.rank_points <= f.model_points:
            raise ConfigError(f"ICP fit.model_points ({f.model_points}) must be >= 3 and score.rank_points "
                             f"({s.rank_points}) within [1, fit.model_points]")
        if f.max_points < 3:
            raise ConfigError(f"ICP fit.max_points must be >= 3 (a rigid fit needs 3 points), got {f.max_points}")
        if s.truncation <= 0 or min(s.violation_margin, s.violation_weight, s.float_margin, s.float_weight) < 0:
            raise ConfigError(f"ICP score.truncation ({s.truncation}) must be positive, score.violation_margin "
                             f"({s.violation_margin}), score.violation_weight ({s.violation_weight}), "
                             f"score.float_margin ({s.float_margin}) and score.float_weight ({s.float_weight}) >= 0")
