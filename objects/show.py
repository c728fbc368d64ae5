"""A picture of an object set: each object's model, its convex collision pieces and its symmetry axes.

One panel per object (matplotlib, 3D, object frame, millimetres): the model as a light grey surface, each
collision piece as a coloured translucent hull, each continuous symmetry axis as a solid black line and each
discrete symmetry's rotation axis as a dashed line labelled with its order (``n`` for a turn by ``360 / n`` deg).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from posegrasp.geometry import make_T, quat_to_R
from posegrasp.io import write_bytes
from posegrasp.outputs import mark_image
from posegrasp.objset import ObjectSet, SetObject


def _axis_and_order(T: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """A discrete symmetry's rotation axis (unit), a point on it (m) and its order n (angle = 2 pi k / n)."""
    R, t = T[:3, :3], T[:3, 3]
    w, V = np.linalg.eig(R)
    axis = np.real(V[:, np.argmin(np.abs(w - 1))])
    angle = float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))
    point = np.linalg.lstsq(np.eye(3) - R, t, rcond=None)[0]  # a fixed point: (I - R) p = t
    return axis / np.linalg.norm(axis), point, max(2, int(round(2 * np.pi / max(angle, 1e-9))))


def _piece_mesh(p: dict):
    """A collision piece as a trimesh (m): a convex ``mesh``'s hull, or a ``box`` / ``cylinder`` primitive."""
    import trimesh

    if p["type"] == "mesh":
        return trimesh.convex.convex_hull(np.asarray(p["vertices"]))
    T = make_T(quat_to_R(np.asarray(p["quat"], np.float64)), np.asarray(p["pos"], np.float64))
    if p["type"] == "box":
        return trimesh.creation.box(extents=2 * np.asarray(p["size"]), transform=T)
    return trimesh.creation.cylinder(radius=p["size"][0], height=2 * p["size"][1], sections=32, transform=T)


def _panel(ax, o: SetObject) -> None:
    from matplotlib import colormaps
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    mm = 1000.0
    ax.add_collection3d(Poly3DCollection(o.vertices[o.faces] * mm, facecolor=(0.75, 0.75, 0.75, 0.25),
                                         edgecolor=(0.4, 0.4, 0.4, 0.08), linewidth=0.2))
    cmap = colormaps["tab20"]
    for i, p in enumerate(o.collision):
        hull = _piece_mesh(p)
        c = cmap(i % 20)
        ax.add_collection3d(Poly3DCollection(hull.triangles * mm, facecolor=(*c[:3], 0.35), edgecolor=(*c[:3], 0.8),
                                             linewidth=0.3))
    r = o.diameter * mm * 0.6
    for a, c in o.symmetries_continuous:
        seg = np.stack([c - a * r / mm, c + a * r / mm]) * mm
        ax.plot(*seg.T, color="black", linewidth=2.0)
    drawn: list[np.ndarray] = []
    for T in o.symmetries_discrete:
        a, p, n = _axis_and_order(np.asarray(T))
        if any(abs(abs(a @ d) - 1) < 1e-6 for d in drawn):
            continue
        drawn.append(a)
        seg = np.stack([p - a * r / mm, p + a * r / mm]) * mm
        ax.plot(*seg.T, color="black", linestyle="--", linewidth=1.0)
        ax.text(*seg[1], str(n), fontsize=7)
    lim = o.diameter * mm * 0.6
    ax.set(xlim=(-lim, lim), ylim=(-lim, lim), zlim=(-lim, lim), xlabel="x mm", ylabel="y mm", zlabel="z mm")
    ax.set_box_aspect((1, 1, 1))
    sym = f"{len(o.symmetries_discrete)} discrete" + (f", {len(o.symmetries_continuous)} continuous"
                                                       if o.symmetries_continuous else "")
    pieces = f"{len(o.collision)} piece{'s' if len(o.collision) != 1 else ''}"
    ax.set_title(f"{o.obj_id} {o.name}: {o.mass * 1000:.0f} g, {pieces}\nsymmetries: {sym}"
                 + ("\n! " + "; ".join(w.split(":")[0] for w in o.warnings) if o.warnings else ""), fontsize=8)
    ax.tick_params(labelsize=6)


def draw_set(objset: ObjectSet, out: Path, cols: int = 4) -> Path:
    """Draw every object of ``objset`` into one PNG at ``out`` (written atomically)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(objset.objects)
    cols = min(cols, n)
    rows = -(-n // cols)
    fig = plt.figure(figsize=(3.6 * cols, 4.0 * rows))
    for i, o in enumerate(objset.objects):
        _panel(fig.add_subplot(rows, cols, i + 1, projection="3d"), o)
    fig.subplots_adjust(left=0.02, right=0.96, bottom=0.03, top=1 - 0.5 / (4.0 * rows), wspace=0.25, hspace=0.3)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, metadata={"Software": None})
    plt.close(fig)
    return write_bytes(out, mark_image(buf.getvalue(), "objects show"))
