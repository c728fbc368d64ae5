"""The ways a rigid model rests on a plane, as the plane's upward normal in the object frame.

A body of uniform density rests on a face F of its convex hull when the foot of its centre of mass along F's
normal lies inside F; resting on F, the plane's upward normal is u = -n_F in the object frame. These are
``trimesh.poses.compute_stable_poses`` with ``sigma=0`` (the exact centre of mass, nothing sampled). A box has the
six axes; an L-block also stands as an inverted V on the ends of its two bars (u = -(1, 0, 1) / sqrt 2), a
triangular prism lies on each of its three sides (u at 120 deg steps about its axis), a brick leans on a long side's
studs (u 36 deg off its -z axis). The depth fit lays its resting starts on the nearest of these
(``perception.depth_fit.starts.level``): an object axis would put those poses 30-45 deg off.

Two rests are one for the fit when a symmetry of the model maps one up onto the other: S u_i = u_j for a discrete
symmetry S (or the identity), or (S u_i) . c = u_j . c for a continuous symmetry axis c (a turn about c then maps
S u_i onto u_j). ``labels`` numbers these classes, so a lying cylinder's 48 hull sides are one rest class.
"""

from __future__ import annotations

from dataclasses import dataclass

from posegrasp.errors import DatasetError
import numpy as np


@dataclass(frozen=True)
class Rests:
    """ups (U, 3): unit object-frame directions of the plane's upward normal, one per stable face, most likely first
    (``axes()``: +x, -x, +y, -y, +z, -z); labels (U,) int: the class of each under the model's symmetries."""

    ups: np.ndarray
    labels: np.ndarray

    def __post_init__(self) -> None:
        ups, labels = np.asarray(self.ups, dtype=np.float64), np.asarray(self.labels)
        if ups.ndim != 2 or ups.shape[1] != 3 or len(ups) == 0 or labels.shape != (len(ups),):
            raise ValueError(f"Rests needs ups (U, 3) with U >= 1 and labels (U,), got {ups.shape} and {labels.shape}")
        if not np.allclose(np.linalg.norm(ups, axis=1), 1.0, atol=1e-6):
            raise ValueError(f"Rests ups must be unit vectors, got norms {np.linalg.norm(ups, axis=1)}")

    @classmethod
    def axes(cls, discrete: np.ndarray = np.zeros((0, 3, 3)), axes: np.ndarray = np.zeros((0, 3))) -> Rests:
        """The six object axes as rests, a box's, labelled by the symmetries (``of_mesh``; none: each its own class)."""
        ups = np.concatenate([np.eye(3), -np.eye(3)], axis=1).reshape(6, 3)
        return cls(ups, up_classes(ups, discrete, axes))

    @classmethod
    def of_mesh(cls, mesh, discrete: np.ndarray, axes: np.ndarray, tol_deg: float = 2.0) -> Rests:
        """The stable rests of a closed ``trimesh.Trimesh`` (object frame, any unit), labelled by its symmetries:
        discrete rotations (S, 3, 3) and continuous axes (A, 3), object frame (``bop.ObjectInfo``'s). Ups within
        ``tol_deg`` of each other under a symmetry share a label."""
        import trimesh

        T, _ = trimesh.poses.compute_stable_poses(mesh, sigma=0.0, n_samples=1, threshold=0.0)
        if len(T) == 0:
            raise DatasetError("the mesh has no stable rest: is it a closed solid?")
        ups = T[:, 2, :3] / np.linalg.norm(T[:, 2, :3], axis=1, keepdims=True)  # R^T e_z, R the rest's rotation
        return cls(ups, up_classes(ups, discrete, axes, tol_deg))


def up_classes(ups: np.ndarray, discrete: np.ndarray, axes: np.ndarray, tol_deg: float = 2.0) -> np.ndarray:
    """Labels (U,) of the unit directions ups (U, 3): the index of the first up that a symmetry (discrete rotations
    (S, 3, 3), continuous axes (A, 3)) maps within ``tol_deg`` of it (module doc)."""
    cos_tol, sin_tol = np.cos(np.radians(tol_deg)), np.sin(np.radians(tol_deg))
    images = np.concatenate([np.eye(3)[None], np.asarray(discrete, dtype=np.float64).reshape(-1, 3, 3)]) @ ups.T
    axes = np.asarray(axes, dtype=np.float64).reshape(-1, 3)  # images (S + 1, 3, U): S u_i in column i
    labels = np.arange(len(ups))
    for j in range(len(ups)):
        for i in range(j):
            if labels[i] != i:
                continue
            same = (images[:, :, i] @ ups[j] > cos_tol).any() or \
                any((np.abs(images[:, :, i] @ c - ups[j] @ c) < sin_tol).any() for c in axes)
            if same:
                labels[j] = i
                break
    return labels
