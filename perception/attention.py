"""Attention modules of the pose network over per-point features (B, C, N).

PAM and CAM follow DANet (Fu et al. 2019) with a learned scale ``gamma`` initialised to 0, so both
start as the identity; GFEM is the paper's global feature extraction (a conv, then average pooling).
"""

from __future__ import annotations

import torch
from torch import nn


class PAM(nn.Module):
    """Position attention: every point becomes a softmax-weighted sum of all points' values.

    V1 = conv(Vi), V2 = conv(Vi) with C // reduction channels, V3 = conv(Vi) with C channels;
    M = softmax over j of V1_i . V2_j (N x N); Vo_i = gamma * sum_j M_ij V3_j + Vi_i.
    """

    def __init__(self, channels: int, reduction: int = 8):
        super().__init__()
        inner = max(channels // reduction, 1)
        self.query = nn.Conv1d(channels, inner, 1)
        self.key = nn.Conv1d(channels, inner, 1)
        self.value = nn.Conv1d(channels, channels, 1)
        self.gamma = nn.Parameter(torch.zeros(1))

    def attention(self, x: torch.Tensor) -> torch.Tensor:
        """M (B, N, N), rows sum to 1."""
        q = self.query(x)  # (B, C', N)
        k = self.key(x)  # (B, C', N)
        return torch.softmax(torch.bmm(q.transpose(1, 2), k), dim=-1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = torch.bmm(self.value(x), self.attention(x).transpose(1, 2))  # (B, C, N)
        return self.gamma * out + x


class CAM(nn.Module):
    """Channel attention (no convolutions): energy = X X^T, A = softmax(rowmax(energy) - energy),
    out = gamma * (A X) + X."""

    def __init__(self) -> None:
        super().__init__()
        self.gamma = nn.Parameter(torch.zeros(1))

    def attention(self, x: torch.Tensor) -> torch.Tensor:
        """A (B, C, C)."""
        energy = torch.bmm(x, x.transpose(1, 2))  # (B, C, C)
        return torch.softmax(energy.amax(dim=-1, keepdim=True) - energy, dim=-1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.gamma * torch.bmm(self.attention(x), x) + x  # (B, C, N)


class GFEM(nn.Module):
    """Global feature extraction: 1x1 conv (C -> out_channels) + ReLU, average-pooled over the
    points and repeated per point: (B, C, N) -> (B, out_channels, N)."""

    def __init__(self, channels: int, out_channels: int):
        super().__init__()
        self.conv = nn.Conv1d(channels, out_channels, 1)

    def pooled(self, x: torch.Tensor) -> torch.Tensor:
        """The global feature (B, out_channels, 1)."""
        return torch.relu(self.conv(x)).mean(dim=2, keepdim=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.pooled(x).expand(-1, -1, x.shape[2])
