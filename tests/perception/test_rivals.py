"""Rival fits (``perception.depth_fit.rivals``): one part posed as several types, the trailing types dropped."""

import numpy as np
import pytest
import torch

from posegrasp import bop
from posegrasp.bop import models as bop_models
from posegrasp.errors import ConfigError
from posegrasp.perception.depth_fit import DepthFitConfig, FitConfig, ObjectModel, fit_poses
from posegrasp.perception.runtime import torch_threads
from posegrasp.perception.depth_fit.rivals import Rivals


def test_a_rival_trailing_its_part_by_more_than_the_margin_loses():
    # objects 0, 1, 2 show part 5, object 3 part 8, object 4 part 5 but has no rows left
    rivals = Rivals(part=[5, 5, 5, 8, 5], cost=[0.0, 0.0005, 0.003, 0.0, 0.0])
    obj = torch.tensor([0, 0, 1, 2, 3])
    score = torch.tensor([0.004, 0.002, 0.0027, 0.001, 0.009])
    # bests plus costs: 0.002, 0.0032, 0.004, 0.009 (alone in its part); the lead of part 5: 0.002
    assert rivals.losers(score, obj, 0.001).tolist() == [False, True, True, False, False]
    assert rivals.losers(score, obj, 0.0015).tolist() == [False, False, True, False, False]
    assert rivals.losers(score, obj, float("inf")).tolist() == [False] * 5
    assert rivals.rows(score, obj, 0.001).tolist() == [True, True, False, False, True]
    assert rivals.take([3, 1]) == Rivals([8, 5], [0.0, 0.0005])
    with pytest.raises(ConfigError, match="2 parts for 3 costs"):
        Rivals([0, 1], [0.0, 0.0, 0.0])


def _one_part_as_each_type(tiny_bop):
    """The tiny dataset's first frame, one of its parts' observed points, and the part posed (at its true pose) as
    each of the set's types: estimates, models and the one observed array, for ``fit_poses``."""
    rec = next(iter(bop.iter_scene_images(tiny_bop, "train")))
    depth, K = rec.load_depth(), rec.camera.K
    g = rec.instances[0]
    vs, us = np.nonzero(rec.load_mask(g.gt_index) & (depth > 0))
    z = depth[vs, us].astype(np.float64)
    obs = np.stack([(us - K[0, 2]) * z / K[0, 0], (vs - K[1, 2]) * z / K[1, 1], z], axis=1)[::2]
    infos = bop.load_models_info(tiny_bop)
    types = sorted(infos)
    models = [ObjectModel.of_mesh(bop_models.load_model(tiny_bop, o), infos[o].symmetry_rotations(), DepthFitConfig(),
                                  seed=o) for o in types]
    return depth, K, g.obj_id, types, [g.T_cam_obj] * len(types), models, [obs] * len(types)


def test_the_types_a_part_is_not_are_dropped_and_its_own_fits_as_without_rivals(tiny_bop):
    """A part posed as each type of the set: without margins every type is fitted as it is without rivals; with
    margins 0 only the best type is fitted to the end (the part's own), the others report score inf and their
    estimates, the same on one torch thread as on several; a cost on the own type
    large enough hands the part to another."""
    depth, K, true, types, estimates, models, observed = _one_part_as_each_type(tiny_bop)
    cfg = DepthFitConfig(fit=FitConfig(polish=2))
    alone = fit_poses(estimates, models, observed, depth, K, cfg)
    part = [0] * len(types)
    free = fit_poses(estimates, models, observed, depth, K, cfg, rivals=Rivals(part, [0.0] * len(types)))
    for (T, s), (T1, s1) in zip(free, alone):
        np.testing.assert_allclose(T, T1, atol=1e-5)
        assert s == pytest.approx(s1, abs=1e-6)
    own = types.index(true)
    assert int(np.argmin([s for _, s in alone])) == own
    runs = []
    for threads in (1, len(types)):
        with torch_threads(threads):
            runs.append(fit_poses(estimates, models, observed, depth, K, cfg,
                                  rivals=Rivals(part, [0.0] * len(types), 0.0, 0.0)))
    strict = runs[0]
    assert [np.isfinite(s) for _, s in strict] == [o == own for o in range(len(types))]
    assert all(np.array_equal(T, T1) and s == s1 for (T, s), (T1, s1) in zip(*runs))
    np.testing.assert_allclose(strict[own][0], alone[own][0], atol=1e-5)
    assert all(np.array_equal(T, est) for o, ((T, s), est) in enumerate(zip(strict, estimates)) if o != own)
    cost = [1.0 if o == own else 0.0 for o in range(len(types))]
    handed = fit_poses(estimates, models, observed, depth, K, cfg, rivals=Rivals(part, cost, 0.0, 0.0))
    assert not np.isfinite(handed[own][1]) and sum(np.isfinite(s) for _, s in handed) == 1
