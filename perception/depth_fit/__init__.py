"""The depth fit: each pose estimate fitted to its observed depth points by ICP from several starts, scored
against the depth image.

The pose net's translations are good but its rotations often sit on a near-symmetry of a block (a brick turned 90 deg
or an arch upside down covers almost the same points), so this stage, like PoseCNN's and DenseFusion's "+ICP", fits
each object's model to its observed points from H starts and keeps the fit with the lowest score. Its stages, in the
order ``fit_poses`` (``driver``) runs them, all objects of a frame as one batch (its rows shared out over torch's
threads in the compiled kernels, ``kernels``):

1. Starts (``starts``, ``StartConfig``): R_est Q for the 24 rotations Q of the cube group, less those that start the
   same fit under the object's symmetries. Given the supporting plane, each also starts moved along its normal n to
   rest on it and laid on the model's rest nearest n (``rests``: the faces of its convex hull it stands on); those
   starts are held: each step fits them as a turn about n and a shift along the plane, and sets them back resting.
2. Grid steps (``grids``, ``icp``): ``iterations - exact_steps`` times, each observed point p_i is matched to a
   nearest model point m_j under (R_h, t_h), looked up in a voxel grid, and (R_h, t_h) <- Kabsch(m_j -> p_i).
3. Turns (``TurnConfig``): the best fit of each of an object's ``seeds`` best-scoring rests facing up is turned about
   n through its centre by every ``step_deg`` of the turn that maps the model onto itself about n, and each is fitted
   ``iterations`` more grid steps: seen from above, a resting face fits its points at almost any yaw.
4. Exact steps: the ``polish`` best fits per object take ``exact_steps`` steps with the exact nearest model points.
5. Searches (``search``, ``SearchConfig``): each object's best fit turned about n (the yaw search), then its best
   fits on ``pattern_fits`` rests moved along the plane and turned about n by a pattern search on the score.

The score (``score``, ``ScoreConfig``) is the mean truncated distance of the observed points to the model, plus
weighted shares of model points in seen free space and beneath the plane, plus a term for a model floating above its
support: the plane, or the seen surface of a neighbouring object it may lie on (``FitContext.supports``). The
context of a frame (observed points, weights, depth, K, plane, the objects' models) is a ``FitContext`` (``context``);
each object's shape an ``ObjectModel``. Points are camera-frame metres; K is the 3x3 intrinsic matrix.
"""

from posegrasp.perception.depth_fit.config import (DepthFitConfig, FitConfig, ScoreConfig, SearchConfig, StartConfig,
                                                   TurnConfig)
from posegrasp.perception.depth_fit.driver import fit_pose, fit_poses
from posegrasp.perception.depth_fit.grids import NearestGrid
from posegrasp.perception.depth_fit.model import ObjectModel
from posegrasp.perception.depth_fit.starts import cube_rotations, distinct_rotations

__all__ = ["DepthFitConfig", "FitConfig", "NearestGrid", "ObjectModel", "ScoreConfig", "SearchConfig", "StartConfig",
           "TurnConfig", "cube_rotations", "distinct_rotations", "fit_pose", "fit_poses"]
