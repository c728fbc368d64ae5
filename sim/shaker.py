"""A shaker stage under the tote: parts that lie against its walls are shaken off them, as a flexible feeder does.

The tote stands on a stage that moves in world x and y: two slide joints on the tote's attachment frame, each held
at its set point by a stiff, damped spring (a servo): between shakes the tote stays within a fraction of a millimetre
of its place (a 0.1 kg part hitting it at 1 m/s moves it at most ``p / (m w)``, about 0.3 mm, for a few hundredths of
a second); shaken, it moves with real velocity, so the floor's friction acts on the parts as a moving floor's does.

A shake is a sawtooth along a horizontal unit vector ``u`` (``Shaker.offset``), ``cycles`` times:

- the jerk: the set point jumps by ``stroke`` along ``u``; the spring accelerates the tote at up to
  ``stiffness * stroke / m`` (about 200 m/s^2 with the defaults and a 2.8 kg tote), far above what the floor's friction can give a
  part (``mu g``, about 9 m/s^2), so the parts slide: they stay behind, moving by up to ``stroke`` along ``-u``
  relative to the tote, off the wall that ``u`` points at;
- the ease back: the set point returns to zero along a smoothstep over ``ease_time`` (peak acceleration
  ``6 stroke / ease_time^2``, well under ``mu g``), so the parts ride with the floor and keep their new places.

Parts against the opposite wall are pushed along by it; no part moves toward the wall ``u`` points at.
"""

from __future__ import annotations

from dataclasses import field

import mujoco
import numpy as np
from dm_control import mjcf

from posegrasp.config import settings, within

STAGE_MEMORY = "256M"  #: MuJoCo's arena (``size/memory``) of a workcell whose tote stands on the stage
JOINTS = ("shake_x", "shake_y")  #: the stage's slide joints (world x, world y), on the tote's attachment frame


@settings
class ShakerConfig:
    """The stage's servo and the shake's sawtooth."""

    #: Spring stiffness (N/m) holding the tote at the stage's set point, per axis.
    stiffness: float = field(default=30000.0, metadata=within(100.0, 1e7))
    #: Damping (N s/m) of the stage, per axis (about 0.7 of critical for a 3 kg tote with the default stiffness).
    damping: float = field(default=400.0, metadata=within(0.0, 1e6))
    #: The set point's jump (m) at each jerk.
    stroke: float = field(default=0.02, metadata=within(0.001, 0.1))
    #: Time (s) the set point stays at the stroke after a jerk (the tote arrives, the parts stop sliding) ...
    jerk_time: float = field(default=0.15, metadata=within(0.01, 2.0))
    #: ... and the time (s) it takes back to zero, smoothly, the parts riding along.
    ease_time: float = field(default=0.5, metadata=within(0.05, 5.0))
    #: Jerks per shake.
    cycles: int = field(default=4, metadata=within(1, 20))
    #: Time (s) the parts are given to come to rest after the last cycle.
    settle_time: float = field(default=0.4, metadata=within(0.0, 5.0))


def add_shaker(frame: mjcf.Element, root: mjcf.RootElement, cfg: ShakerConfig) -> None:
    """Put the tote's attachment ``frame`` (in the workcell ``root``) on the stage: its slide joints and no contact
    between the tote and the world's static geoms (its floor is sunk in the table)."""
    for name, axis in zip(JOINTS, ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0))):
        frame.add("joint", name=name, type="slide", axis=axis, stiffness=cfg.stiffness, damping=cfg.damping,
                  springref=0.0)
    root.contact.add("exclude", name="tote_table", body1="world", body2=frame)
    # the tote, a body now, joins every part touching it in one constraint island: the solver's working memory
    # grows with the island (MuJoCo's default arena overflowed with 12 parts and 1234 constraint rows)
    root.size.memory = STAGE_MEMORY


class Shaker:
    """The stage of a compiled workcell model: its set point (``model.qpos_spring`` of its joints) and the shake."""

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, cfg: ShakerConfig):
        self.model, self.data, self.cfg = model, data, cfg
        joints = [model.joint(_joint_name(model, j)) for j in JOINTS]
        self.qadr = np.array([j.qposadr[0] for j in joints])
        self.dadr = np.array([j.dofadr[0] for j in joints])

    @staticmethod
    def of(model: mujoco.MjModel, data: mujoco.MjData, cfg: ShakerConfig) -> "Shaker | None":
        """The model's stage, or None where the tote stands still (no stage joints)."""
        return Shaker(model, data, cfg) if _joint_name(model, JOINTS[0]) else None

    def set_point(self, xy: np.ndarray) -> None:
        """Move the stage's set point to ``xy`` (m, world x and y, from the tote's place), waking the tote where it
        sleeps (MuJoCo's sleeping islands: a dof's velocity written as -0.0 wakes its island, changing nothing)."""
        self.model.qpos_spring[self.qadr] = xy
        v = self.data.qvel[self.dadr]
        self.data.qvel[self.dadr] = np.where(v == 0.0, -0.0, v)

    @property
    def duration(self) -> float:
        """Seconds (simulated) a shake takes, the parts' settling included."""
        c = self.cfg
        return c.cycles * (c.jerk_time + c.ease_time) + c.settle_time

    def offset(self, u: np.ndarray, t: float) -> np.ndarray:
        """The set point (m, world x and y) ``t`` seconds into a shake along the unit vector ``u`` (world xy; the
        parts slide along ``-u``): ``cycles`` times ``stroke * u`` for ``jerk_time``, then back to zero along a
        smoothstep ``1 - s^2 (3 - 2 s)``, ``s = t' / ease_time``, over ``ease_time``; zero once the cycles are over."""
        c = self.cfg
        i, r = divmod(max(t, 0.0), c.jerk_time + c.ease_time)
        if i >= c.cycles:
            return np.zeros(2)
        s = min(max(r - c.jerk_time, 0.0) / c.ease_time, 1.0)
        return (1.0 - s * s * (3.0 - 2.0 * s)) * c.stroke * np.asarray(u, float)[:2]


def _joint_name(model: mujoco.MjModel, joint: str) -> str:
    """The compiled name of the stage's ``joint`` ("tote/shake_x/": dm-control's name for a joint of an
    attachment frame), or "" where the model has none."""
    return next((n for n in (model.joint(i).name for i in range(model.njnt)) if n.startswith(f"tote/{joint}")), "")
