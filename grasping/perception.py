"""Perception providers: what the planner knows about the objects, as pose estimates in the camera frame.

The public protocol (``Provider``): a provider receives an ``Observation`` of the hand camera (RGB uint8,
depth in metres, K, image size, the capture's ids) and a seed, and returns ``Estimate``s
``(obj_id, T_cam_obj, score)``: ``T_cam_obj`` maps object-frame points (m) into the OpenCV camera frame
(x right, y down, z forward, m). Nothing of the simulator reaches it. The oracles are the exception: they
read the simulator's labels (``GroundTruthProvider``). The planner never sees simulator ground truth except
through a provider; ``perceive`` is the one place an episode asks a provider.
This module holds the protocols and the oracles (``grasping.provider_registry.make_provider`` builds any
provider from its ``--perception`` name):

- ``oracle``: the ground-truth ``T_cam_obj`` of every block with at least ``min_px`` visible mask pixels.
- ``noisy-oracle[:TRANS_M,ROT_DEG]``: the oracle plus Gaussian translation noise (sigma TRANS_M per axis)
  and a rotation about a uniformly random axis by an angle ~ |N(0, ROT_DEG)|; seeded per frame.
"""

from __future__ import annotations

import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, ClassVar, Collection, Protocol, TypeVar

import numpy as np

from posegrasp.bop import images as bop_images
from posegrasp.errors import PerceptionError, ProviderError
from posegrasp.geometry import axis_angle_R
from posegrasp.sim.camera import Frame

T_ = TypeVar("T_")


@dataclass(frozen=True)
class Estimate:
    """One detected block: catalogue id, pose in the (OpenCV) camera frame (m) and a confidence in [0, 1]."""

    obj_id: int
    T_cam_obj: np.ndarray
    score: float


@dataclass(frozen=True)
class Observation:
    """One capture of the hand camera, as a provider sees it.

    rgb: (H, W, 3) uint8. depth: (H, W) float32, metres along the optical axis in the sensor's 0.1 mm steps
    (``DEPTH_SCALE``), 0 where the sensor gave no reading. K: (3, 3) pinhole intrinsics (pixels) of the OpenCV camera. scene_id, im_id: the capture's
    ids in a BOP export of the campaign (``--export-captures``): the episode index, and the capture within
    the episode (0: the look at the pick area; 1: stack's look at the base).
    """

    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    scene_id: int = 0
    im_id: int = 0

    @property
    def height(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def width(self) -> int:
        return int(self.rgb.shape[1])


#: ``Observation.im_id`` of each capture an episode makes (which a task takes: ``Task.looks``).
PICK_LOOK, BASE_LOOK = 0, 1


class Provider(Protocol):
    """The public protocol: turns an observation into pose estimates; ``seed`` makes any randomness
    repeatable (the same observation and seed must give the same estimates)."""

    name: str

    def estimate(self, obs: Observation, seed: int) -> list[Estimate]: ...


class GroundTruthProvider(Protocol):
    """A privileged provider (the oracles): reads the simulator's labels of the captured ``Frame``."""

    name: str

    def estimate_truth(self, frame: Frame, seed: int) -> list[Estimate]: ...


@dataclass(frozen=True)
class SetProvider:
    """A provider built from the models of the object set ``objects`` (``""``: the shipped blocks) and the settings
    TOML file ``settings`` (an absolute path; None: the defaults), named ``KIND[:settings]`` as on the command line."""

    objects: str = ""
    settings: str | None = None
    kind: ClassVar[str] = ""

    @property
    def name(self) -> str:
        return self.kind + (f":{self.settings}" if self.settings else "")

    @staticmethod
    def settings_file(args: str | None) -> str | None:
        """The absolute path of the settings file a spec's ARGS name (None without one)."""
        return str(Path(args).expanduser().resolve()) if args else None


def reads_labels(provider: Provider | GroundTruthProvider) -> bool:
    """Is ``provider`` an oracle, reading the capture's labels (no RGB-D) rather than an ``Observation``?"""
    return hasattr(provider, "estimate_truth")


#: The hand camera's depth unit (mm): like a depth sensor's integer output, the depth a provider sees comes in steps
#: of 0.1 mm (the unit of the training data's and of ``--export-captures``'s depth PNGs, so an export holds exactly
#: the depth the live providers see).
DEPTH_SCALE = 0.1


def observation(frame: Frame, scene_id: int = 0, im_id: int = 0) -> Observation:
    """What a provider may see of a captured ``frame``: its RGB image, its depth in ``DEPTH_SCALE`` steps,
    intrinsics, and the capture's ids."""
    return Observation(frame.rgb, bop_images.quantise_depth(frame.depth, DEPTH_SCALE), frame.K, scene_id, im_id)


#: Bounds of a usable estimate: rotation orthonormality and determinant (``ROT_TOL``), translation norm (m).
ROT_TOL, MAX_TRANSLATION_M = 1e-3, 5.0
#: Most estimates a provider may return for one capture (more is a runaway detector, not a scene).
MAX_ESTIMATES = 1000


def perceive(provider: Provider | GroundTruthProvider, frame: Frame, seed: int, scene_id: int = 0,
             im_id: int = 0, known_ids: Collection[int] | None = None, timeout_s: float | None = None
             ) -> list[Estimate]:
    """The provider's checked estimates for the captured ``frame``: the oracles read its labels, every other
    provider gets its ``Observation`` only and at most ``timeout_s`` wall seconds (None: no limit).

    Raises:
        PerceptionError: the provider raised, ran out of time, or returned anything but a list of estimates with
            ``obj_id`` in ``known_ids`` (None: any), a finite rigid 4x4 ``T_cam_obj`` within ``MAX_TRANSLATION_M``
            of the camera, and a finite score.
    """
    name = str(getattr(provider, "name", type(provider).__name__))
    try:
        if reads_labels(provider):
            out = provider.estimate_truth(frame, seed)
        else:
            obs = observation(frame, scene_id, im_id)
            out = call_with_timeout(lambda: provider.estimate(obs, seed), timeout_s)
    except PerceptionError as e:
        raise PerceptionError(f"provider {name!r} {e}") from None
    except Exception as e:  # anything a provider raises fails this episode only
        raise PerceptionError(f"provider {name!r} raised {type(e).__name__}: {_one_line(e)}") from None
    return checked_estimates(out, known_ids, f"provider {name!r}")


def _one_line(e: BaseException, limit: int = 200) -> str:
    text = " ".join(str(e).split()) or "(no message)"
    return text if len(text) <= limit else text[:limit - 3] + "..."


def checked_estimates(out: object, known_ids: Collection[int] | None = None, who: str = "provider"
                      ) -> list[Estimate]:
    """``out`` as a list of ``Estimate``s (any items with ``obj_id``, ``T_cam_obj``, ``score`` attributes), or a
    one-line ``PerceptionError`` naming ``who`` and the first thing wrong (see ``perceive``)."""
    if not isinstance(out, (list, tuple)):
        raise PerceptionError(f"{who} returned {type(out).__name__}, not a list of Estimate")
    if len(out) > MAX_ESTIMATES:
        raise PerceptionError(f"{who} returned {len(out)} estimates for one capture, over {MAX_ESTIMATES}")
    ests = []
    for i, e in enumerate(out):
        where = f"{who} estimate {i}"
        if not all(hasattr(e, a) for a in ("obj_id", "T_cam_obj", "score")):
            raise PerceptionError(f"{where} is a {type(e).__name__}, not an Estimate (obj_id, T_cam_obj, score)")
        obj_id, score = e.obj_id, e.score
        if isinstance(obj_id, (bool, np.bool_)) or not isinstance(obj_id, (int, np.integer)):
            raise PerceptionError(f"{where}: obj_id {obj_id!r} is not an integer")
        if known_ids is not None and int(obj_id) not in known_ids:
            raise PerceptionError(f"{where}: obj_id {int(obj_id)} is not in the object set "
                                  f"(ids {', '.join(str(k) for k in sorted(known_ids))})")
        try:
            T = np.array(e.T_cam_obj, dtype=np.float64)
            score = float(score)
        except (TypeError, ValueError):
            raise PerceptionError(f"{where}: T_cam_obj or score is not numeric") from None
        problem = _pose_problem(T) or (None if np.isfinite(score) else f"score {score} is not finite")
        if problem:
            raise PerceptionError(f"{where} (obj_id {int(obj_id)}): {problem}")
        ests.append(Estimate(int(obj_id), T, score))
    return ests


def _pose_problem(T: np.ndarray) -> str | None:
    """What makes ``T`` no usable ``T_cam_obj`` (4x4, finite, rigid, last row 0 0 0 1, metres), or None."""
    if T.shape != (4, 4):
        return f"T_cam_obj has shape {T.shape}, not (4, 4)"
    if not np.isfinite(T).all():
        return "T_cam_obj has a NaN or infinite entry"
    if np.abs(T[3] - (0, 0, 0, 1)).max() > ROT_TOL:
        return f"T_cam_obj's last row is {np.round(T[3], 6).tolist()}, not [0, 0, 0, 1]"
    R = T[:3, :3]
    dev, det = float(np.abs(R.T @ R - np.eye(3)).max()), float(np.linalg.det(R))
    if dev > ROT_TOL or abs(det - 1) > ROT_TOL:
        return f"T_cam_obj's rotation is not orthonormal with det +1 (|R^T R - I| = {dev:.3g}, det {det:.4g})"
    dist = float(np.linalg.norm(T[:3, 3]))
    if dist > MAX_TRANSLATION_M:
        hint = " (millimetres? T_cam_obj is in metres)" if dist < 1000 * MAX_TRANSLATION_M else ""
        return f"T_cam_obj's translation is {dist:.4g} m from the camera, over {MAX_TRANSLATION_M:g} m{hint}"
    return None


class _Expired(BaseException):
    """Raised in the main thread by the timer's signal (a BaseException, so a provider's ``except Exception``
    cannot swallow it)."""


def call_with_timeout(fn: Callable[[], T_], timeout_s: float | None) -> T_:
    """``fn()``, or a ``PerceptionError`` once it has run ``timeout_s`` wall seconds (None or 0: no limit).

    In a process's main thread on a POSIX system (pool workers, a serial campaign) a SIGALRM timer interrupts
    ``fn`` (any timer already set is put back afterwards, less the time spent). Elsewhere ``fn`` runs in a daemon
    thread that is waited for ``timeout_s``; one that hangs is left running in the background."""
    if not timeout_s:
        return fn()
    if hasattr(signal, "setitimer") and threading.current_thread() is threading.main_thread():
        return _alarm_call(fn, timeout_s)
    box: dict[str, object] = {}

    def run() -> None:
        try:
            box["out"] = fn()
        except BaseException as e:  # handed to the caller's thread
            box["err"] = e

    worker = threading.Thread(target=run, daemon=True, name="perception")
    worker.start()
    worker.join(timeout_s)
    if worker.is_alive():
        raise _late(timeout_s)
    if "err" in box:
        raise box["err"]  # type: ignore[misc]
    return box["out"]  # type: ignore[return-value]


def _late(timeout_s: float) -> PerceptionError:
    return PerceptionError(f"did not answer within {timeout_s:g} s (TrialConfig.perception_timeout_s)")


def _alarm_call(fn: Callable[[], T_], timeout_s: float) -> T_:
    """``call_with_timeout`` with a SIGALRM interval timer (main thread only)."""
    def expire(signum, frame) -> None:
        raise _Expired

    t0 = time.monotonic()
    old_handler = signal.signal(signal.SIGALRM, expire)
    old_delay, old_interval = signal.setitimer(signal.ITIMER_REAL, timeout_s)
    try:
        try:
            return fn()
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
    except _Expired:  # (also when it fired on the way out: the provider took about the whole time)
        raise _late(timeout_s) from None
    finally:
        signal.signal(signal.SIGALRM, old_handler)
        if old_delay:  # someone else's timer: put it back, less the time spent here
            signal.setitimer(signal.ITIMER_REAL, max(old_delay - (time.monotonic() - t0), 1e-3), old_interval)


def visible_enough(pixels: int, shape: tuple[int, int], min_px: int) -> bool:
    """Does a mask of ``pixels`` in an image of ``shape`` (H, W) hold at least ``min_px`` pixels at 640x480?"""
    return pixels >= min_px * (shape[0] * shape[1]) / (640 * 480)


@dataclass(frozen=True)
class OracleProvider:
    """Ground truth for the blocks visible in the frame (at least ``min_px`` mask pixels at 640x480)."""

    min_px: int = 150
    name: str = "oracle"
    latency_s = 0.0  # seconds a look waits for it (``grasping.latency``): the simulator's labels, no computation

    def estimate_truth(self, frame: Frame, seed: int) -> list[Estimate]:
        counts = np.bincount(frame.mask.ravel(), minlength=len(frame.obj_ids) + 1)
        return [Estimate(int(frame.obj_ids[k - 1]), frame.T_cam_obj[k - 1].copy(), float(min(1.0, counts[k] / 5000)))
                for k in range(1, len(frame.obj_ids) + 1) if visible_enough(counts[k], frame.mask.shape, self.min_px)]


@dataclass(frozen=True)
class NoisyOracleProvider:
    """The oracle with seeded Gaussian translation noise (m, per axis) and random-axis rotation noise (deg)."""

    trans_m: float = 0.005
    rot_deg: float = 5.0
    min_px: int = 150
    latency_s = 0.0  # as the oracle's

    @property
    def name(self) -> str:
        return f"noisy-oracle:{self.trans_m:g},{self.rot_deg:g}"

    def estimate_truth(self, frame: Frame, seed: int) -> list[Estimate]:
        rng = np.random.default_rng(seed)
        out = []
        for e in OracleProvider(self.min_px).estimate_truth(frame, seed):
            axis = rng.normal(size=3)
            angle = np.deg2rad(abs(rng.normal(0.0, self.rot_deg))) if self.rot_deg > 0 else 0.0
            dt = rng.normal(0.0, self.trans_m, size=3) if self.trans_m > 0 else np.zeros(3)
            T = e.T_cam_obj.copy()
            T[:3, :3] = axis_angle_R(axis, angle) @ T[:3, :3]
            T[:3, 3] += dt
            out.append(Estimate(e.obj_id, T, e.score))
        return out


def oracle_from_spec(args: str | None) -> OracleProvider:
    """The oracle for ``--perception oracle`` (``args``: the text after ``oracle:``, which must be empty)."""
    if args:
        raise ProviderError(f"perception 'oracle' takes no parameters, got 'oracle:{args}'")
    return OracleProvider()


def noisy_oracle_from_spec(args: str | None) -> NoisyOracleProvider:
    """The noisy oracle for ``--perception noisy-oracle[:TRANS_M,ROT_DEG]`` (``args``: the text after the colon)."""
    if not args:
        return NoisyOracleProvider()
    try:
        t, r = (float(v) for v in args.split(","))
    except ValueError:
        raise ProviderError(f"noisy-oracle parameters {args!r} are not TRANS_M,ROT_DEG, "
                            "e.g. noisy-oracle:0.005,5") from None
    if not (0 <= t <= 0.2 and 0 <= r <= 180):
        raise ProviderError(f"noisy-oracle noise {args!r} out of range: TRANS_M in [0, 0.2] m, ROT_DEG in [0, 180]")
    return NoisyOracleProvider(t, r)
