"""Batched DenseFusion loss: ADD / ADD-S distances, confidence term, refiner loss."""

import numpy as np
import pytest
import torch

from posegrasp.perception import metrics
from posegrasp.perception.losses import PoseTargets, point_distances, pose_loss, refiner_loss
from posegrasp.perception.torch_geometry import quat_to_rotmat
from posegrasp.geometry import quat_to_R

torch.set_num_threads(1)


def test_quat_matches_numpy():
    q = torch.tensor([[0.9, 0.1, -0.3, 0.2]], dtype=torch.float64)
    np.testing.assert_allclose(quat_to_rotmat(q)[0].numpy(), quat_to_R(q[0].numpy()), atol=1e-12)


def _setup(B=3, N=20, M=50, seed=0):
    g = torch.Generator().manual_seed(seed)
    model = torch.rand(B, M, 3, generator=g, dtype=torch.float64) * 0.1 - 0.05
    q = torch.randn(B, 4, generator=g, dtype=torch.float64)
    R = quat_to_rotmat(q)
    t = torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64) + 0.01 * torch.randn(B, 3, generator=g, dtype=torch.float64)
    target = model @ R.transpose(1, 2) + t[:, None]
    points = target[:, :N] + 0.001 * torch.randn(B, N, 3, generator=g, dtype=torch.float64)
    return model, q, R, t, target, points


def test_distances_match_metrics():
    model, q, R, t, target, points = _setup()
    q_e = q + 0.2
    R_e = quat_to_rotmat(q_e)
    t_e = t + 0.01
    pred = (model @ R_e.transpose(1, 2) + t_e[:, None])[:, None]  # (B, 1, M, 3)
    sym = torch.tensor([False, True, True])
    d = point_distances(pred, target, sym)[:, 0]
    for b in range(3):
        args = (R_e[b].numpy(), t_e[b].numpy(), R[b].numpy(), t[b].numpy(), model[b].numpy())
        ref = metrics.add(*args) if b == 0 else metrics.adds(*args, direction="est_to_gt")
        assert d[b].item() == pytest.approx(ref, abs=1e-12)


def test_pose_loss_perfect_and_gradients():
    model, q, R, t, target, points = _setup()
    B, N = points.shape[:2]
    pred_q = q[:, None].expand(B, N, 4) / q.norm(dim=1)[:, None, None]
    pred_t = (t[:, None] - points).clone().requires_grad_(True)
    conf = torch.full((B, N), 0.5, dtype=torch.float64, requires_grad=True)
    out = pose_loss(pred_q, pred_t, conf, PoseTargets(points, model, target, torch.tensor([False, True, False])))
    assert out.dis.abs().max() < 1e-12
    assert out.loss.item() == pytest.approx(-0.015 * np.log(0.5), rel=1e-9)
    out.loss.backward()
    assert conf.grad is not None and pred_t.grad is not None
    # the refiner inputs are the points and targets in the estimate's frame: model points themselves
    torch.testing.assert_close(out.new_target, model, atol=1e-12, rtol=0)
    torch.testing.assert_close(out.T[:, :3, 3], t, atol=1e-12, rtol=0)


def test_symmetric_loss_ignores_symmetry():
    # a cylinder-like ring symmetric about z: rotating the estimate about z costs nothing under ADD-S
    ang = torch.linspace(0, 2 * np.pi, 73, dtype=torch.float64)[:-1]
    model = torch.stack([0.03 * ang.cos(), 0.03 * ang.sin(), torch.zeros_like(ang)], 1)[None]
    target = model + torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64)
    qz = torch.tensor([[np.cos(np.pi / 12), 0, 0, np.sin(np.pi / 12)]], dtype=torch.float64)  # 30 deg
    pred = (model @ quat_to_rotmat(qz).transpose(1, 2) + torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64))
    sym = point_distances(pred[:, None], target, torch.tensor([True]))
    asym = point_distances(pred[:, None], target, torch.tensor([False]))
    assert sym.item() < 1e-12 and asym.item() > 0.01
    out = refiner_loss(qz, torch.zeros(1, 3, dtype=torch.float64), target[:, :5], model, target,
                       torch.tensor([True]))
    assert out.dis.shape == (1,)


def test_min_symmetry_loss_is_zero_at_every_symmetric_pose_and_not_at_a_near_symmetry():
    from posegrasp.perception.losses import min_symmetry_targets

    # a 60 x 30 x 20 mm box; its true symmetries: 180 deg about z (and x, y); a 90 deg turn about z is not one
    g = torch.Generator().manual_seed(0)
    model = (torch.rand(1, 200, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([0.06, 0.03, 0.02])
    flip_z = torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=torch.float64))
    quarter_z = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    t = torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64)
    target = model + t
    sym_targets = torch.stack([model[0], model[0] @ flip_z.T])[None] + t  # (1, S=2, M, 3)
    pred = torch.stack([model[0] @ R.T + t for R in (torch.eye(3, dtype=torch.float64), flip_z, quarter_z)])[None]
    tgt = min_symmetry_targets(pred, sym_targets)
    add_min = (pred - tgt).norm(dim=-1).mean(dim=-1)[0]  # (P,)
    assert add_min[0] < 1e-12 and add_min[1] < 1e-12 and add_min[2] > 0.01
    # ADD-S, by contrast, barely sees the quarter turn
    adds = point_distances(pred, target, torch.tensor([True]))[0]
    assert adds[2] < 0.5 * add_min[2]
    # in pose_loss: min over symmetries where discrete, ADD-S where continuous
    q = torch.tensor([[[0.0, 0.0, 0.0, 1.0]]], dtype=torch.float64)  # 180 deg about z
    pts = target[:, :1]
    truth = PoseTargets(pts, model, target, torch.tensor([True]), sym_targets, torch.tensor([False]))
    out = pose_loss(q, t - pts, torch.ones(1, 1, dtype=torch.float64), truth)
    assert out.dis[0] < 1e-12
