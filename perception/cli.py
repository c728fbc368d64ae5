"""``posegrasp train seg|pose|refine``, ``posegrasp eval`` and ``posegrasp perturb`` subcommands.

A ``--config`` TOML file may hold sections ``[seg]``, ``[pose]``, ``[refine]``, ``[cls]`` and ``[eval]`` (with
sub-tables such as ``[pose.model]`` and ``[pose.data]``) matching the config dataclasses of
``perception.train_seg``, ``train_pose``, ``train_refine``, ``train_cls`` and ``perception.evaluate``; command-line
flags override it.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from typing import TYPE_CHECKING

from posegrasp.arguments import in_dir, nonneg_int, number, out_dir, positive_int
from posegrasp.config import load_toml, override
from posegrasp.errors import UserError, WeightsError

if TYPE_CHECKING:
    from posegrasp.perception.training import StageTraining

TRAIN_STAGES = ("seg", "pose", "refine", "cls")  #: ``train``'s stages, each a table of a training TOML
SECTIONS = (*TRAIN_STAGES, "eval")  #: the tables a training or evaluation TOML may hold


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``train``, ``eval`` and ``perturb`` subcommands."""
    p = subparsers.add_parser("train", help="train the segmentation net, the pose net or the refiner",
                              description="Train one stage of the perception network on a BOP dataset.")
    p.add_argument("stage", choices=TRAIN_STAGES,
                   help="which network to train (cls: the instance classifier, after seg)")
    p.add_argument("--data", required=True, type=in_dir("--data"), help="BOP dataset root")
    p.add_argument("--out", required=True, type=out_dir(), help="run directory (RUN/<stage> holds the checkpoint)")
    p.add_argument("--config", type=Path, help="TOML file with [seg] / [pose] / [refine] sections")
    p.add_argument("--steps", type=positive_int("--steps"), help="total optimisation steps (overrides the config)")
    p.add_argument("--seed", type=nonneg_int("--seed"), help="random seed (overrides the config)")
    p.add_argument("--resume", action="store_true", help="continue the checkpoint in RUN/<stage>")
    p.add_argument("--init", type=Path, help="seg, pose and cls: start from these weights (a run or its stage folder)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(run=run_train, resume_hint="run the same command with --resume to continue")

    e = subparsers.add_parser("eval", help="evaluate a trained run on a BOP split",
                              description="mPA/mIoU, ADD, ADD-S, AUC, accuracies, curves, BOP results CSV.")
    e.add_argument("--data", required=True, type=in_dir("--data"), help="BOP dataset root")
    e.add_argument("--weights", required=True, type=in_dir("--weights"), help="run directory with seg/, pose/ [, refine/]")
    e.add_argument("--split", help="split to evaluate (default: test)")
    e.add_argument("--out", type=out_dir(), help="report directory (default: WEIGHTS/eval_<split>)")
    e.add_argument("--config", type=Path, help="TOML file with an [eval] section")
    e.add_argument("--gt-masks", action="store_true", help="use ground-truth masks (pose stage only)")
    e.add_argument("--no-refine", action="store_true", help="ablation: skip refinement")
    e.add_argument("--no-cls", action="store_true", help="ablation: no instance classifier (the paper's pipeline)")
    e.add_argument("--no-icp", action="store_true", help="ablation: no depth refinement (ICP from rotation hypotheses)")
    e.add_argument("--no-plane", action="store_true", help="ablation: no supporting-plane prior (mask cleanup, ICP)")
    e.add_argument("--no-guided", action="store_true",
                   help="ablation: class-map outlines not snapped to colour edges (guided filter)")
    e.add_argument("--no-split", action="store_true", help="ablation: merged segments not split by the fitted models")
    e.add_argument("--max-images", type=positive_int("--max-images"), help="evaluate at most this many images")
    e.add_argument("--threads", type=positive_int("--threads"), help="torch CPU threads (default 2; the grasp "
                   "trials' estimator runs 1, and its scores can differ in the last digits with more)")
    e.add_argument("--min-mask-px", type=nonneg_int("--min-mask-px"),
                   help="drop detections whose mask has fewer pixels at 640x480 (150: as the grasp trials' model "
                        "provider; default 0)")
    e.add_argument("--no-progress", action="store_true", help="no progress bar")
    e.set_defaults(run=run_eval)

    d = subparsers.add_parser("perturb", help="write a deliberately degraded copy of a run (seeded weight noise)",
                              description="For sensitivity studies: run trials with model:OUT and compare.")
    d.add_argument("--weights", required=True, type=in_dir("--weights"), help="run directory with seg/, pose/ [, refine/]")
    d.add_argument("--out", required=True, type=out_dir(), help="new run directory")
    d.add_argument("--rel-sigma", required=True, type=number("--rel-sigma", 0), help="noise std as a fraction of each tensor's std")
    d.add_argument("--stages", default="pose", help="comma-separated stages to perturb (default: pose)")
    d.add_argument("--seed", type=nonneg_int("--seed"), default=0, help="noise seed")
    d.set_defaults(run=run_perturb)


def training_stages() -> dict[str, type[StageTraining]]:
    """The ``StageTraining`` of each ``posegrasp train`` stage (imported when asked for: they import torch)."""
    from posegrasp.perception.train_cls import ClsTraining
    from posegrasp.perception.train_pose import PoseTraining
    from posegrasp.perception.train_refine import RefineTraining
    from posegrasp.perception.train_seg import SegTraining

    return {t.name: t for t in (SegTraining, PoseTraining, RefineTraining, ClsTraining)}


def run_train(args: argparse.Namespace) -> int:
    """Handler of ``posegrasp train``."""
    training = training_stages()[args.stage]
    cfg = load_toml(training.config, args.config, section=args.stage, sections=SECTIONS)
    if args.init is not None:
        if not training.fine_tunes:
            raise UserError("--init is only for 'train seg', 'train pose' and 'train cls' (fine-tuning)")
        cfg = override(cfg, init=str(args.init))
    result = training.train(args.data, args.out, cfg, steps=args.steps, seed=args.seed, resume=args.resume,
                            progress=not args.no_progress)
    print(json.dumps({"stage": args.stage, "checkpoint": str(args.out / args.stage), **result}, default=str))
    return 0


def run_eval(args: argparse.Namespace) -> int:
    """Handler of ``posegrasp eval``."""
    from posegrasp.bop.check import require_valid
    from posegrasp.perception.evaluate import EvalConfig, evaluate

    cfg = load_toml(EvalConfig, args.config, section="eval", sections=SECTIONS)
    cfg = override(cfg, split=args.split, max_images=args.max_images, min_mask_px=args.min_mask_px,
                   threads=args.threads,
                   masks="gt" if args.gt_masks else None, refine_iterations=0 if args.no_refine else None,
                   classify=False if args.no_cls else None, icp=False if args.no_icp else None,
                   plane=False if args.no_plane else None,
                   guided=False if args.no_guided else None, split_merged=False if args.no_split else None)
    out = args.out or out_dir("--weights")(str(args.weights / f"eval_{cfg.split}"))
    require_valid(args.data, cfg.split, cfg.max_images or None, scoring=True, progress=not args.no_progress)
    report = evaluate(args.data, args.weights, out, cfg, progress=not args.no_progress)
    summary = {"out": str(out), "segmentation": (report["segmentation"] or {}).get("mIoU"),
               **{k: report["overall"][k] for k in ("ADD-S_AUC", "ADD_AUC", "ADD(-S)_acc_0.1d")},
               "bop19": report["bop19"], "time_per_image_s": report["time_per_image_s"]}
    print(json.dumps(summary))
    return 0


def run_perturb(args: argparse.Namespace) -> int:
    """Handler of ``posegrasp perturb``."""
    from posegrasp.perception.checkpoint import STAGES, perturb_run

    stages = tuple(s.strip() for s in args.stages.split(",") if s.strip())
    bad = [s for s in stages if s not in STAGES]
    if bad or not stages:
        raise UserError(f"--stages {args.stages!r}: name one or more of {', '.join(STAGES)}")
    if not (args.weights / "pose").is_dir():
        raise WeightsError(f"--weights {args.weights} holds no pose/ checkpoint")
    if args.out.exists() and any(args.out.iterdir()):
        raise UserError(f"--out {args.out} is not empty: choose a new folder")
    print(perturb_run(args.weights, args.out, args.rel_sigma, stages, args.seed))
    return 0
