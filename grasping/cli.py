"""``posegrasp trials`` (grasp-and-place campaigns) and ``posegrasp calibrate`` (hand-eye calibration)."""

from __future__ import annotations

import argparse
import dataclasses

from posegrasp.arguments import nonneg_int, out_dir, out_file, positive_int, workers_arg
from posegrasp.errors import UserError


#: Sanity bound of ``--episodes``: beyond it a typo, not a campaign.
MAX_EPISODES = 10_000_000

#: The settings its commands read, for the settings page (``posegrasp.settings_doc``).
SETTINGS = (
    dict(title="Grasp trials", target="posegrasp.grasping.config:TrialConfig", table="",
         command="`posegrasp trials --config FILE`"),
    dict(title="Training-free estimator", target="posegrasp.perception.depth_icp:DepthIcpConfig", table="depth_icp",
         command="`posegrasp trials --perception depth-icp:FILE`, table `[depth_icp]`"),
    dict(title="Point pair features", target="posegrasp.perception.ppf:PpfConfig", table="ppf",
         command="`posegrasp trials --perception ppf:FILE` (and `eval --perception ppf:FILE`), table `[ppf]`"),
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("trials", help="grasp-and-place trials with a perception provider; resumable")
    p.add_argument("--episodes", type=positive_int("--episodes", MAX_EPISODES), default=200, help="number of episodes (default 200)")
    p.add_argument("--seed", type=nonneg_int("--seed"), default=0, help="campaign seed: episode i draws from (seed, i) only")
    p.add_argument("--perception", default="oracle",
                   help="oracle (default) | noisy-oracle[:TRANS_M,ROT_DEG] | model[:RUN]: the learned network, "
                        "the shipped weights without RUN | py:MODULE_OR_FILE:FACTORY[:ARGS] or an installed "
                        "NAME[:ARGS]: your own estimator | bop-csv:RESULTS.csv: a BOP results file's estimates "
                        "for the --export-captures frames (docs/estimators.md)")
    p.add_argument("--workers", type=workers_arg, default=2, help="worker processes (default 2), or 'ray'")
    p.add_argument("--out", type=out_dir(), help="output folder (episodes.jsonl, summary.json); required unless "
                                                  "--captures-only")
    p.add_argument("--config", default=None, help="trial settings TOML (grasping.config.TrialConfig layout)")
    p.add_argument("--task", type=_task_arg, default=None,
                   help="pick-place (default) | kitting (upright, at the kit's yaw) | stack (on a base block) | "
                        "bin-pick (empty a tote or a pile into an out-box); docs/trials.md says which to use when")
    p.add_argument("--scene", type=_scene_arg, default=None,
                   help="table (the default of the table tasks) | bin: parts heaped in a tote | pile: the same heap "
                        "on the table; bin and pile go with --task bin-pick, which takes bin unless told")
    p.add_argument("--blocks", type=positive_int("--blocks"), default=None,
                   help="blocks per scene (default: 1-5 on the table, 12 in a bin or pile, at most 30 there)")
    p.add_argument("--objects", default=None,
                   help="object set folder to draw objects from (default: the shipped blocks; docs/objects.md)")
    p.add_argument("--hand", type=_hand_arg, default=None,
                   help="3-finger (default) | 2-finger: the Jaco2's KG-2 hand, two fingers facing each other, which "
                        "reaches parts lying against a tote's walls | suction: a vacuum cup (bin picking only) | "
                        "hybrid: the 2-finger hand with a cup between its fingers (docs/workcell.md)")
    p.add_argument("--place", choices=("out-box", "tray"), default=None,
                   help="bin-pick: where picked parts go: out-box (default: dropped) | tray: set down in a slot of "
                        "their type at its pose, judged within 3 mm and 3 deg (docs/trials.md)")
    p.add_argument("--sweep-noise", action="store_true",
                   help="run noisy-oracle campaigns at increasing noise and plot success against pose error")
    p.add_argument("--noise", type=_noise_arg, default=None,
                   help="with --sweep-noise, its levels: rotation (0-45 deg) | translation (0-2 cm) | both (default)")
    p.add_argument("--export-captures", type=out_dir("--export-captures"), metavar="DIR",
                   help="also write every frame the robot perceives as a BOP test split with ground truth "
                        "(scene = episode, im 0 the pick look, 1 stack's look at the base), for any BOP method; "
                        "replay its results with --perception bop-csv:RESULTS.csv (docs/estimators.md)")
    p.add_argument("--captures-only", action="store_true",
                   help="with --export-captures: only drive to the looks and capture, no grasps (no --out)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(run=run_trials_cmd, resume_hint="run the same command again to resume")

    c = sub.add_parser("calibrate", help="hand-eye calibration of the hand camera with a ChArUco board")
    c.add_argument("--out", required=True, type=out_file("--out", (".json",)), help="output JSON file with T_gripper_cam")
    c.add_argument("--poses", type=positive_int("--poses"), default=12, help="number of arm poses viewing the board (>= 3)")
    c.add_argument("--seed", type=nonneg_int("--seed"), default=0, help="seed of the viewpoints")
    c.add_argument("--config", default=None, help="workcell TOML file (default: assets/workcell.toml)")
    c.add_argument("--force", action="store_true", help="replace --out even if this command did not write it")
    c.set_defaults(run=run_calibrate_cmd)


def _task_arg(text: str) -> str:
    from posegrasp.grasping.tasks import TASKS

    if text not in TASKS:
        raise UserError(f"--task {text!r} is not a task; choose one of: {', '.join(TASKS)}")
    return text


#: The ``--scene`` choices: the table tasks' scene, and bin picking's (``sim.clutter.CLUTTER_KINDS``).
SCENES = ("table", "bin", "pile")


def _scene_arg(text: str) -> str:
    if text not in SCENES:
        raise UserError(f"--scene {text!r} is not a scene; choose one of: {', '.join(SCENES)}")
    return text


def with_scene(cfg, scene: str | None, blocks: int | None):
    """``cfg`` (a ``TrialConfig``) with ``--scene`` and ``--blocks``, as its task takes them (``Task.with_scene``)."""
    from posegrasp.grasping.tasks import get_task

    return get_task(cfg.task).with_scene(cfg, scene, blocks)


def _hand_arg(text: str) -> str:
    from posegrasp.sim.config import HANDS

    if text not in HANDS:
        raise UserError(f"--hand {text!r} is not a hand; choose one of: {', '.join(HANDS)}")
    return text


def _noise_arg(text: str) -> str:
    from posegrasp.grasping.trials import SWEEPS

    if text not in SWEEPS:
        raise UserError(f"--noise {text!r} is not a sweep; choose one of: {', '.join(SWEEPS)}")
    return text


def run_trials_cmd(args: argparse.Namespace) -> int:
    from posegrasp.grasping.config import load_trial_config
    from posegrasp.grasping.tasks import with_set
    from posegrasp.grasping.trials import SWEEPS, Display, run_trials, sweep_noise

    cfg = with_set(load_trial_config(args.config), args.objects)
    if args.hand:
        cfg = dataclasses.replace(cfg, scene=dataclasses.replace(
            cfg.scene, workcell=dataclasses.replace(cfg.scene.workcell, hand=args.hand)))
    if args.task:
        cfg = dataclasses.replace(cfg, task=args.task)
    cfg = with_scene(cfg, args.scene, args.blocks)
    if args.place:
        if cfg.task != "bin-pick":
            raise UserError("--place says where bin picking puts the parts: use it with --task bin-pick")
        cfg = dataclasses.replace(cfg, bin_pick=dataclasses.replace(cfg.bin_pick, place=args.place))
    if args.noise is not None and not args.sweep_noise:
        raise UserError(f"--noise {args.noise} sets the levels of --sweep-noise; add --sweep-noise, or use "
                        "--perception noisy-oracle:TRANS_M,ROT_DEG for one noisy campaign")
    out, export = args.out, args.export_captures
    if args.captures_only or export:
        _check_export_args(args)
    if args.captures_only:
        from posegrasp.grasping.captures import export_captures
        from posegrasp.grasping.trials import campaign_settings

        cfg, mount = campaign_settings(args.episodes, cfg)
        export_captures(export, args.episodes, args.seed, args.workers, cfg, mount, progress=not args.no_progress)
        return 0
    if out is None:
        raise UserError("--out is required: the run folder (episodes.jsonl, summary.json)")
    if args.sweep_noise:
        sweep_noise(out, args.episodes, args.seed, args.workers, cfg, SWEEPS[args.noise or "both"],
                    progress=not args.no_progress)
        print(f"noise sweep -> {out / 'sweep.png'}")
    else:
        run_trials(out, args.episodes, args.seed, args.perception, args.workers, cfg,
                   Display(progress=not args.no_progress), export=export)
    return 0


def _check_export_args(args: argparse.Namespace) -> None:
    """``--export-captures`` and ``--captures-only`` go with one campaign and a folder of their own."""
    if args.captures_only and args.export_captures is None:
        raise UserError("--captures-only needs --export-captures DIR (the folder the captures go to)")
    if args.captures_only and args.out is not None:
        raise UserError("--captures-only runs no episodes and writes no run folder: drop --out")
    if args.sweep_noise:
        raise UserError("--export-captures is for one campaign, not --sweep-noise (its campaigns share the captures)")
    if args.out is not None and args.out.resolve() == args.export_captures.resolve():
        raise UserError(f"--export-captures {args.export_captures} is the --out folder: give it a folder of its own")


def run_calibrate_cmd(args: argparse.Namespace) -> int:
    from posegrasp.grasping.calibration import CalibrationConfig, calibrate, save_hand_eye
    from posegrasp.outputs import check_out_file
    from posegrasp.sim.config import load_workcell_config

    if args.poses < 3:
        raise UserError(f"--poses must be at least 3 (10 or more for an accurate result), got {args.poses}")
    out = check_out_file(args.out, "calibrate", [args.config] if args.config else [], args.force,
                         what="a hand-eye calibration")
    wcfg = load_workcell_config(args.config)
    result = calibrate(wcfg, dataclasses.replace(CalibrationConfig(), n_poses=args.poses), args.seed)
    try:
        save_hand_eye(out, result)
    except OSError as e:
        raise UserError(f"cannot write {out}: {e.strerror}") from None
    print(f"hand-eye calibration from {result.n_views} views: error vs the true mount "
          f"{1000 * result.trans_error_m:.2f} mm, {result.rot_error_deg:.3f} deg -> {out}")
    return 0
