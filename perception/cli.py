"""``posegrasp train seg|pose|refiner|cls``, ``posegrasp eval``, ``posegrasp quantize`` and ``posegrasp perturb``
subcommands.

A ``--config`` TOML file may hold sections ``[seg]``, ``[pose]``, ``[refiner]``, ``[cls]`` and ``[eval]`` (with
sub-tables such as ``[pose.model]`` and ``[pose.data]``) matching the settings classes of
``perception.train_seg``, ``train_pose``, ``train_refiner``, ``train_cls`` and ``perception.evaluate``; command-line
flags override it. The old names in ``RENAMED`` (the stage and table ``refine``, the flags ``--no-refine`` and
``--no-icp``) are read as their new ones, with a notice on stderr naming the new one.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from typing import TYPE_CHECKING

from posegrasp.arguments import in_dir, nonneg_int, number, out_dir, positive_int
from posegrasp.config import load_toml, override
from posegrasp.errors import UserError, WeightsError

if TYPE_CHECKING:
    from posegrasp.perception.evaluate import EvalConfig
    from posegrasp.perception.training import StageTraining

TRAIN_STAGES = ("seg", "pose", "refiner", "cls")  #: ``train``'s stages, each a table of a training TOML
SECTIONS = (*TRAIN_STAGES, "eval")  #: the tables a training or evaluation TOML may hold
#: Old names still read, a notice naming the new one: a stage (``train``, ``perturb --stages``, a TOML table) or a flag.
RENAMED = {"refine": "refiner", "--no-refine": "--no-refiner", "--no-icp": "--no-depth-fit"}


def renamed(name: str) -> str:
    """``name``, or its new name if it is an old one (``RENAMED``), with a notice on stderr."""
    if name in RENAMED:
        print(f"posegrasp: note: '{name}' is now named '{RENAMED[name]}'", file=sys.stderr)
    return RENAMED.get(name, name)


class _RenamedFlag(argparse.Action):
    """An old ``store_true`` flag: sets its new flag's destination, with a notice."""

    def __init__(self, option_strings: list[str], dest: str, **kwargs) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, help=argparse.SUPPRESS)

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        setattr(namespace, renamed(option_string).lstrip("-").replace("-", "_"), True)


#: The settings its commands read, for the settings page (``posegrasp.settings_doc``).
SETTINGS = (
    dict(title="Training: segmentation net", target="posegrasp.perception.train_seg:SegTrainConfig", table="seg",
         command="`posegrasp train seg --config FILE`, table `[seg]`",
         note="The shipped model's settings: `assets/perception/train_cpu.toml`."),
    dict(title="Training: pose net", target="posegrasp.perception.train_pose:PoseTrainConfig", table="pose",
         command="`posegrasp train pose --config FILE`, table `[pose]`"),
    dict(title="Training: refiner", target="posegrasp.perception.train_refiner:RefinerTrainConfig", table="refiner",
         command="`posegrasp train refiner --config FILE`, table `[refiner]`"),
    dict(title="Training: instance classifier", target="posegrasp.perception.train_cls:ClsTrainConfig", table="cls",
         command="`posegrasp train cls --config FILE`, table `[cls]`"),
    dict(title="Evaluation", target="posegrasp.perception.evaluate:EvalConfig", table="eval",
         command="`posegrasp eval --config FILE`, table `[eval]`",
         note="The command's flags (`--no-depth-fit`, `--gt-masks`, ...) override the file."),
    dict(title="Estimator", target="posegrasp.perception.estimator:EstimatorConfig", table=None,
         command="Python: `Estimator(weights, EstimatorConfig(...))`",
         note="Nested settings are dataclasses too: "
              "`EstimatorConfig(depth_fit=DepthFitConfig(search=SearchConfig(pattern_rounds=0)))` "
              "([real camera](../real_camera.md))."),
)


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``train``, ``eval``, ``quantize`` and ``perturb`` subcommands."""
    p = subparsers.add_parser("train", help="train the segmentation net, the pose net, the refiner or the classifier",
                              description="Train one stage of the perception network on a BOP dataset.")
    p.add_argument("stage", choices=TRAIN_STAGES, type=renamed,
                   help="which network to train (refiner: after pose; cls: the instance classifier, after seg)")
    p.add_argument("--data", required=True, type=in_dir("--data"), help="BOP dataset root")
    p.add_argument("--out", required=True, type=out_dir(), help="run directory (RUN/<stage> holds the checkpoint)")
    p.add_argument("--config", type=Path, help="TOML file with [seg] / [pose] / [refiner] / [cls] sections")
    p.add_argument("--steps", type=positive_int("--steps"), help="total optimisation steps (overrides the config)")
    p.add_argument("--seed", type=nonneg_int("--seed"), help="random seed (overrides the config)")
    p.add_argument("--resume", action="store_true", help="continue the checkpoint in RUN/<stage>")
    p.add_argument("--init", type=Path, help="seg, pose and cls: start from these weights (a run or its stage folder)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(run=run_train, resume_hint="run the same command with --resume to continue")

    e = subparsers.add_parser("eval", help="evaluate a trained run (or any perception provider) on a BOP split",
                              description="mPA/mIoU, ADD, ADD-S, AUC, accuracies, curves, BOP results CSV.")
    e.add_argument("--data", required=True, type=in_dir("--data"), help="BOP dataset root")
    e.add_argument("--weights", type=in_dir("--weights"),
                   help="run directory with seg/, pose/ [, refiner/, cls/] (or --perception SPEC)")
    e.add_argument("--split", help="split to evaluate (default: test)")
    e.add_argument("--out", type=out_dir(), help="report directory (default: WEIGHTS/eval_<split>)")
    e.add_argument("--config", type=Path, help="TOML file with an [eval] section")
    e.add_argument("--gt-masks", action="store_true", help="use ground-truth masks (pose stage only)")
    e.add_argument("--no-refiner", action="store_true", help="ablation: no refiner (the learned pose refinement)")
    e.add_argument("--no-cls", action="store_true", help="ablation: no instance classifier (the paper's pipeline)")
    e.add_argument("--no-depth-fit", action="store_true",
                   help="ablation: no depth fit (ICP from rotation hypotheses)")
    e.add_argument("--no-refine", "--no-icp", action=_RenamedFlag)
    e.add_argument("--no-plane", action="store_true",
                   help="ablation: no supporting-plane prior (mask cleanup, depth fit)")
    e.add_argument("--no-guided", action="store_true",
                   help="ablation: class-map outlines not snapped to colour edges (guided filter)")
    e.add_argument("--no-split", action="store_true", help="ablation: merged segments not split by the fitted models")
    e.add_argument("--no-type-check", action="store_true",
                   help="ablation: a part's type is the classifier's alone, not checked by fits of its likely types")
    e.add_argument("--no-int8", action="store_true",
                   help="the seg net and classifiers in float, also where the run has int8 ranges")
    e.add_argument("--max-images", type=positive_int("--max-images"), help="evaluate at most this many images")
    e.add_argument("--threads", type=positive_int("--threads"), help="torch CPU threads (default 2; the grasp "
                   "trials' estimator runs 1, and its scores can differ in the last digits with more)")
    e.add_argument("--min-mask-px", type=nonneg_int("--min-mask-px"),
                   help="drop detections whose mask has fewer pixels at 640x480 (150: as the grasp trials' model "
                        "provider; default 0)")
    e.add_argument("--no-progress", action="store_true", help="no progress bar")
    e.set_defaults(run=run_eval)

    q = subparsers.add_parser("quantize",
                              help="measure a run's int8 ranges: its seg net and classifiers then run in int8",
                              description="Runs the seg net and the classifiers (on the true segments) on a "
                                          "dataset's images and writes each net's activation ranges (int8.json) beside "
                                          "its weights; eval and trials then run those nets in int8 (the seg net in "
                                          "about 0.6 of its float time; eval --no-int8: float).")
    q.add_argument("--weights", required=True, type=in_dir("--weights"),
                   help="run directory with seg/, pose/ [, cls/]: int8.json is written (or replaced) in seg/ and cls*/")
    q.add_argument("--data", required=True, type=in_dir("--data"),
                   help="BOP dataset root with images like the run's inputs (its training data will do)")
    q.add_argument("--split", default="train_pbr", help="split to read (default: train_pbr)")
    q.add_argument("--images", type=positive_int("--images"), default=32,
                   help="images, spread evenly over the split (default 32)")
    q.add_argument("--force", action="store_true", help="replace an int8.json that 'posegrasp quantize' did not write")
    q.add_argument("--no-progress", action="store_true", help="no progress bar")
    q.set_defaults(run=run_quantize)

    d = subparsers.add_parser("perturb", help="write a deliberately degraded copy of a run (seeded weight noise)",
                              description="For sensitivity studies: run trials with model:OUT and compare.")
    d.add_argument("--weights", required=True, type=in_dir("--weights"),
                   help="run directory with seg/, pose/ [, refiner/, cls/]")
    d.add_argument("--out", required=True, type=out_dir(), help="new run directory")
    d.add_argument("--rel-sigma", required=True, type=number("--rel-sigma", 0), help="noise std as a fraction of each tensor's std")
    d.add_argument("--stages", default="pose", help="comma-separated stages to perturb (default: pose)")
    d.add_argument("--seed", type=nonneg_int("--seed"), default=0, help="noise seed")
    d.set_defaults(run=run_perturb)


def training_stages() -> dict[str, type[StageTraining]]:
    """The ``StageTraining`` of each ``posegrasp train`` stage (imported when asked for: they import torch)."""
    from posegrasp.perception.train_cls import ClsTraining
    from posegrasp.perception.train_pose import PoseTraining
    from posegrasp.perception.train_refiner import RefinerTraining
    from posegrasp.perception.train_seg import SegTraining

    return {t.name: t for t in (SegTraining, PoseTraining, RefinerTraining, ClsTraining)}


def run_train(args: argparse.Namespace) -> int:
    """Handler of ``posegrasp train``."""
    from posegrasp.perception.checkpoint import stage_dir

    training = training_stages()[args.stage]
    cfg = load_toml(training.config, args.config, args.stage, SECTIONS, renamed_sections=RENAMED)
    if args.init is not None:
        if not training.fine_tunes:
            raise UserError("--init is only for 'train seg', 'train pose' and 'train cls' (fine-tuning)")
        cfg = override(cfg, init=str(args.init))
    result = training.train(args.data, args.out, cfg, steps=args.steps, seed=args.seed, resume=args.resume,
                            progress=not args.no_progress)
    checkpoint = stage_dir(args.out, args.stage)  # RUN/<stage>, or a resumed run's folder of the stage's old name
    print(json.dumps({"stage": args.stage, "checkpoint": str(checkpoint), **result}, default=str))
    return 0


def eval_settings(args: argparse.Namespace) -> EvalConfig:
    """``posegrasp eval``'s settings: the ``[eval]`` table of ``--config``, then the flags."""
    from posegrasp.perception.evaluate import EvalConfig

    cfg = load_toml(EvalConfig, args.config, "eval", SECTIONS, renamed_sections=RENAMED)
    return override(cfg, split=args.split, max_images=args.max_images, min_mask_px=args.min_mask_px,
                    threads=args.threads,
                    masks="gt" if args.gt_masks else None, refiner_iterations=0 if args.no_refiner else None,
                    classify=False if args.no_cls else None, depth_fit=False if args.no_depth_fit else None,
                    plane=False if args.no_plane else None,
                    guided=False if args.no_guided else None, split_merged=False if args.no_split else None,
                    type_check=False if args.no_type_check else None, int8=False if args.no_int8 else None)


def print_eval_summary(out: Path, report: dict) -> None:
    """``posegrasp eval``'s one line of JSON on stdout: the main scores of ``report``, written into ``out``."""
    summary = {"out": str(out), "segmentation": (report["segmentation"] or {}).get("mIoU"),
               **{k: report["overall"][k] for k in ("ADD-S_AUC", "ADD_AUC", "ADD(-S)_acc_0.1d")},
               "bop19": report["bop19"], "time_per_image_s": report["time_per_image_s"]}
    print(json.dumps(summary))


def run_eval(args: argparse.Namespace) -> int:
    """Handler of ``posegrasp eval --weights RUN`` (``--perception SPEC``: ``grasping.provider_eval``)."""
    from posegrasp.bop.check import require_valid
    from posegrasp.perception.evaluate import evaluate

    if args.weights is None:
        raise UserError("eval needs --weights RUN (a trained run) or --perception SPEC (a perception provider)")
    cfg = eval_settings(args)
    out = args.out or out_dir("--weights")(str(args.weights / f"eval_{cfg.split}"))
    require_valid(args.data, cfg.split, cfg.max_images or None, scoring=True, progress=not args.no_progress)
    report = evaluate(args.data, args.weights, out, cfg, progress=not args.no_progress)
    print_eval_summary(out, report)
    return 0


def run_quantize(args: argparse.Namespace) -> int:
    """Handler of ``posegrasp quantize``."""
    from posegrasp.bop.check import require_valid
    from posegrasp.perception.calibrate import calibrate

    require_valid(args.data, args.split, args.images, progress=not args.no_progress)
    for path in calibrate(args.weights, args.data, args.split, args.images, not args.no_progress, args.force):
        print(path)
    return 0


def run_perturb(args: argparse.Namespace) -> int:
    """Handler of ``posegrasp perturb``."""
    from posegrasp.perception.checkpoint import STAGES, perturb_run

    stages = tuple(renamed(s.strip()) for s in args.stages.split(",") if s.strip())
    bad = [s for s in stages if s not in STAGES]
    if bad or not stages:
        raise UserError(f"--stages {args.stages!r}: name one or more of {', '.join(STAGES)}")
    if not (args.weights / "pose").is_dir():
        raise WeightsError(f"--weights {args.weights} holds no pose/ checkpoint")
    if args.out.exists() and any(args.out.iterdir()):
        raise UserError(f"--out {args.out} is not empty: choose a new folder")
    print(perturb_run(args.weights, args.out, args.rel_sigma, stages, args.seed))
    return 0
