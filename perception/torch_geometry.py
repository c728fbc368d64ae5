"""Batched rotation helpers in torch. Quaternions are (w, x, y, z)."""

from __future__ import annotations

import torch


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) quaternions (normalised here) -> (..., 3, 3) rotation matrices."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, dim=-1).reshape(*q.shape[:-1], 3, 3)


def make_transform(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) and (..., 3) -> (..., 4, 4) homogeneous transforms."""
    T = torch.zeros(*R.shape[:-2], 4, 4, dtype=R.dtype, device=R.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def turns_about(n: torch.Tensor, angles: torch.Tensor) -> torch.Tensor:
    """Rotations (S, 3, 3) by ``angles`` (S,) (rad) about the unit axis n (3,), or about each of the axes n (S, 3):
    I + sin(a) N + (1 - cos(a)) N^2, N the cross-product matrix of the axis (Rodrigues)."""
    x, y, z = n.expand(len(angles), 3).unbind(1)
    o = torch.zeros_like(x)
    N = torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=1).view(-1, 3, 3)  # N v = u x v
    return torch.eye(3, dtype=n.dtype) + torch.sin(angles)[:, None, None] * N + \
        (1 - torch.cos(angles))[:, None, None] * (N @ N)
