"""Start rotations of the depth fit, and the turns and rests that level them on the supporting plane.

The fits start from R_est Q for the rotations Q of the cube group (``cube_rotations``), less those that start the
same fit under the object's symmetries (``distinct_rotations``). Given the supporting plane (unit normal n), each also
starts resting on it: moved along n until its lowest model point lies on the plane (``resting``) and turned by the
least rotation that lays its rest nearest n onto it (``level``; the rests are the faces of the model's convex hull it
stands on, ``perception.depth_fit.rests``), plus, for each rest class that no start is nearest to, the start nearest it
laid on it and turned about n (``rest_starts``). Turns about n by a step over the model's period about n
(``yaw_turns``, ``turned``) give the fits the yaw that a face seen from above does not pin down.
Rotations map the object frame into the camera frame; n is in the camera frame.
"""

from __future__ import annotations

import itertools

import numpy as np
import torch

from posegrasp.perception.depth_fit.rests import Rests
from posegrasp.perception.torch_geometry import turns_about

#: An object's symmetries: discrete rotations (S, 3, 3) and continuous axes (A, 3), object frame.
Symmetries = tuple[np.ndarray, np.ndarray]

#: No symmetry.
NO_SYMMETRY: Symmetries = (np.zeros((0, 3, 3)), np.zeros((0, 3)))

_AXES = torch.from_numpy(Rests.axes().ups)  # +x, -x, +y, -y, +z, -z


def cube_rotations() -> np.ndarray:
    """The 24 proper rotations that map the coordinate axes onto themselves, (24, 3, 3)."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            R = np.zeros((3, 3))
            R[[0, 1, 2], list(perm)] = signs
            if np.linalg.det(R) > 0:
                out.append(R)
    return np.stack(out)


def distinct_rotations(Q: np.ndarray, discrete: list[np.ndarray], axes: list[np.ndarray],
                       tol_deg: float = 1.0) -> np.ndarray:
    """The hypotheses Q (H, 3, 3) less those that start the same fit under the object's symmetries.

    With S a symmetry (S maps the model onto itself), R Q_i S places the model exactly where R Q_i
    does, so Q_j is dropped when Q_i^T Q_j = D C for a kept Q_i, D the identity or a discrete symmetry
    (4x4 or its 3x3 rotation part) and C a rotation about a continuous symmetry axis (the identity without one).
    The translation parts of the symmetries are ignored: ICP absorbs them. Q keeps its order."""
    Ds = [np.eye(3)] + [np.asarray(D)[:3, :3] for D in discrete]
    cos_tol = np.cos(np.radians(tol_deg))

    def is_symmetry(g: np.ndarray) -> bool:
        for D in Ds:
            C = D.T @ g
            if (np.trace(C) - 1) / 2 > cos_tol or any(np.asarray(a) @ C @ np.asarray(a) > cos_tol for a in axes):
                return True
        return False

    kept: list[np.ndarray] = []
    for q in Q:
        if not any(is_symmetry(k.T @ q) for k in kept):
            kept.append(q)
    return np.stack(kept)


def stacked_rests(rests: list[Rests]) -> tuple[torch.Tensor, torch.Tensor]:
    """The objects' rests as ups (O, U, 3) float32 and labels (O, U), each padded by repeating its first rest."""
    n = max(len(r.ups) for r in rests)
    pad = [np.concatenate([np.arange(len(r.ups)), np.zeros(n - len(r.ups), dtype=int)]) for r in rests]
    return (torch.from_numpy(np.stack([r.ups[i] for r, i in zip(rests, pad)])).float(),
            torch.from_numpy(np.stack([np.asarray(r.labels)[i] for r, i in zip(rests, pad)])).long())


def level(R: torch.Tensor, normal: torch.Tensor, ups: torch.Tensor | None = None) -> torch.Tensor:
    """Each rotation R (H, 3, 3) turned by the least rotation that lays the rest nearest ``normal`` (3,, unit) onto
    it: with a = R^T n and e the up of ``ups`` (H, U, 3) (each row's rests; None: the six object axes) nearest a,
    R Q with Q the turn about e x a by the angle between e and a (Q e = a, so R Q e = n)."""
    a, e, _ = _nearest_up(R, normal, ups)
    return _turned_onto(R, a, e)


def _turned_onto(R: torch.Tensor, a: torch.Tensor, e: torch.Tensor) -> torch.Tensor:
    """R (H, 3, 3) Q, Q the least turn that maps the object-frame directions e (H, 3) onto a (H, 3) (``level``)."""
    axis = torch.cross(e, a, dim=1)
    s = axis.norm(dim=1)
    return R @ turns_about(axis / s.clamp(min=1e-12)[:, None], torch.atan2(s, (e * a).sum(dim=1)))


def rest_starts(R: torch.Tensor, obj: torch.Tensor, normal: torch.Tensor, ups: torch.Tensor, labels: torch.Tensor,
                symmetries: list[Symmetries], turn_deg: float = 60.0) -> tuple[torch.Tensor, torch.Tensor]:
    """The levelled starts of the hypotheses R (H, 3, 3) of objects obj (H,) with rests ups (O, U, 3), labels (O, U)
    and ``symmetries`` (O of them): each ``level``led onto its nearest rest, and for each rest class of an object that
    none of them reaches, the hypothesis nearest a rest of that class laid on it and turned about the normal by every
    ``turn_deg`` (``yaw_turns``): its yaw is a guess. Returns the rotations (H', 3, 3) and the row of R each came
    from (H',)."""
    a, e, k = _nearest_up(R, normal, ups[obj])
    out, src = [_turned_onto(R, a, e)], [torch.arange(len(R))]
    obj_, k_, labels_ = obj.numpy(), k.numpy(), labels.numpy()
    for o in np.unique(obj_).tolist():
        rows = np.flatnonzero(obj_ == o)
        missed = np.setdiff1d(labels_[o], labels_[o][k_[rows]])  # the rest classes none of them reaches
        if len(missed) == 0:
            continue
        cos = (a[torch.from_numpy(rows)] @ ups[o].to(a.dtype).T).numpy()  # (rows, U)
        for c in missed.tolist():
            in_c = np.flatnonzero(labels_[o] == c)
            j = int(cos[:, in_c].max(axis=1).argmax())  # the start nearest a rest of class c, and that rest
            best, u = int(rows[j]), int(in_c[cos[j, in_c].argmax()])
            Rl = level(R[best][None], normal, ups[o, u][None, None])
            psi = yaw_turns(Rl[0].double().numpy(), normal.double().numpy(), turn_deg, *symmetries[o])
            out.append(turns_about(normal.to(R.dtype), torch.from_numpy(psi).to(R.dtype)) @ Rl)
            src.append(torch.full((len(psi),), best))
    return torch.cat(out), torch.cat(src)


def _nearest_up(R: torch.Tensor, normal: torch.Tensor, ups: torch.Tensor | None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The normal in each object frame, a = R^T n (H, 3), the up of ``ups`` (H, U, 3) nearest it (H, 3) and its
    index (H,) (``level``)."""
    a = R.transpose(1, 2) @ normal.to(R.dtype)  # (H, 3)
    if ups is None:
        ups = _AXES.to(R.dtype).expand(len(R), 6, 3)
    k = (ups.to(R.dtype) @ a[:, :, None])[..., 0].argmax(dim=1)  # (H,)
    return a, ups[torch.arange(len(R)), k].to(R.dtype), k


def resting(R: torch.Tensor, t: torch.Tensor, hull: torch.Tensor, obj: torch.Tensor, plane: torch.Tensor
            ) -> tuple[torch.Tensor, torch.Tensor]:
    """The translations t (H, 3) moved along the plane's normal until the lowest model point under R (H, 3, 3) lies
    on the plane (4,: n . x + d = 0, n unit), and that point's height (H,) above the object origin: ``lowest`` over
    the hull vertices (O, V, 3) of objects obj (H,)."""
    low = lowest(R, hull, obj, plane[:3])
    return t - (low + t @ plane[:3] + plane[3])[:, None] * plane[:3], low


def lowest(R: torch.Tensor, hull: torch.Tensor, obj: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """min_j h_j . (R^T n) (H,): the lowest model point's height along ``normal`` n (3,, unit) above the object
    origin, for rotations R (H, 3, 3) of objects obj (H,) with hull vertices h (O, V, 3) (``ObjectModel.hull``, any
    padding a repeated vertex). A linear function's least value over the points is taken at a vertex of their convex
    hull, so the vertices give the model points' minimum at a fraction of the work."""
    return (hull[obj] @ (R.transpose(1, 2) @ normal)[:, :, None])[..., 0].min(dim=1).values  # (H, V) -> (H,)


def up_face(R: torch.Tensor, normal: torch.Tensor | np.ndarray, ups: torch.Tensor | None = None) -> torch.Tensor:
    """Which rest (H,) lies nearest ``normal`` (3,, camera frame) under each rotation R (H, 3, 3): the face an object
    resting on a plane with that normal shows the camera. ups (H, U, 3): each row's rests, the index into them; None:
    the axes +x, -x, +y, -y, +z, -z, 0-5."""
    return _nearest_up(R, torch.as_tensor(normal), ups)[2]


def yaw_turns(R: np.ndarray, normal: np.ndarray, step_deg: float, discrete: np.ndarray, axes: np.ndarray
              ) -> np.ndarray:
    """The angles (rad) to turn an object at rotation R (3, 3) about ``normal`` (3,, camera frame) by: every
    ``step_deg`` (rounded to divide it evenly) of 360 deg / n, n the number of the object's symmetries about that
    axis (the identity and each discrete rotation D (S, 3, 3) that fixes the axis a = R^T normal, object frame);
    only 0 when a continuous symmetry axis (A, 3) lies along a."""
    a = R.T @ (normal / np.linalg.norm(normal))
    if len(axes) and np.max(np.abs(np.asarray(axes) @ a)) > np.cos(np.radians(2.0)):
        return np.zeros(1)
    n = 1 + int(np.sum(np.linalg.norm(np.asarray(discrete).reshape(-1, 3, 3) @ a - a, axis=1) < 0.02))
    period = 2 * np.pi / n
    k = max(1, int(round(np.degrees(period) / step_deg)))
    return np.arange(k) * (period / k)


def turned(R: torch.Tensor, obj: torch.Tensor, normal: np.ndarray, step_deg: float, symmetries: list[Symmetries]
           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each rotation R (H, 3, 3) of object obj (H,) turned about ``normal`` by its ``yaw_turns``: (H', 3, 3), their
    objects (H',) and the row of R each came from (H',)."""
    Rd = R.double()
    psi = [yaw_turns(Rh, normal, step_deg, *symmetries[o]) for Rh, o in zip(Rd.numpy(), obj.tolist())]
    source = torch.repeat_interleave(torch.tensor([len(x) for x in psi]))
    out = turns_about(torch.from_numpy(normal).double(), torch.from_numpy(np.concatenate(psi))) @ Rd[source]
    return out.float(), obj[source], source
