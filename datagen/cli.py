"""``posegrasp datagen``: write a synthetic BOP dataset (``posegrasp dataset check|show`` inspect it)."""

from __future__ import annotations

import argparse
import dataclasses
import re

from posegrasp.arguments import nonneg_int, out_dir, positive_int, workers_arg
from posegrasp.errors import UserError

#: The settings its commands read, for the settings page (``posegrasp.settings_doc``).
SETTINGS = (
    dict(title="Dataset generation", target="posegrasp.datagen.config:DatagenConfig", table="",
         command="`posegrasp datagen --config FILE`", note="The defaults, commented: `datagen/datagen.toml`."),
)


def parse_blocks(text: str) -> tuple[int, int]:
    """``"5"`` -> (5, 5); ``"3-8"`` -> (3, 8); a one-line error for anything else."""
    m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", text)
    if not m:
        raise UserError(f"--blocks {text!r} must be a count N or a range MIN-MAX, e.g. 5 or 3-8")
    lo, hi = int(m.group(1)), int(m.group(2) or m.group(1))
    if lo < 1 or hi < lo:
        raise UserError(f"--blocks {text!r} must satisfy 1 <= MIN <= MAX")
    return lo, hi


#: Sanity bounds of ``--scenes`` and ``--views`` (per scene): beyond them a typo, not a dataset.
MAX_SCENES, MAX_VIEWS = 1_000_000, 10_000


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("datagen", help="generate a randomised synthetic RGB-D dataset in BOP format (resumable)")
    p.add_argument("--out", required=True, type=out_dir(), help="dataset folder (created; an existing one is completed)")
    p.add_argument("--scenes", type=positive_int("--scenes", MAX_SCENES), default=10, help="simulated scenes (one BOP scene each)")
    p.add_argument("--views", type=positive_int("--views", MAX_VIEWS), default=25, help="hand-camera views per scene")
    p.add_argument("--seed", type=nonneg_int("--seed"), default=0, help="dataset seed (same seed and settings, same bytes)")
    p.add_argument("--workers", type=workers_arg, default=None, help="worker processes (default: one per core), or 'ray'")
    p.add_argument("--split", choices=("train_pbr", "test"), default="train_pbr", help="BOP split to write")
    p.add_argument("--resolution", default=None, help="image WIDTHxHEIGHT (default from the config: 640x480)")
    p.add_argument("--config", default=None, help="generation settings TOML (defaults: datagen/datagen.toml)")
    p.add_argument("--rgb-format", choices=("png", "jpg"), default=None, help="colour images (default: jpg for train_pbr, png for test)")
    p.add_argument("--scene", default=None,
                   help="scene kind: table (blocks apart), pile (a heap) or bin (a heap in a tote); default table")
    p.add_argument("--blocks", default=None,
                   help="objects per scene: N or MIN-MAX (default 3-8 on the table, 12 in a pile or bin)")
    p.add_argument("--objects", default=None,
                   help="object set folder to draw objects from (default: the shipped blocks; docs/objects.md)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(run=run_datagen, resume_hint="run the same command again to resume")


def load_config(args: argparse.Namespace):
    """The generation settings: TOML file (or defaults), overridden by the command-line flags."""
    from posegrasp.datagen.config import load_datagen_config, validate
    from posegrasp.config import override
    from posegrasp.sim.cli import parse_resolution
    from posegrasp.sim.config import with_objects

    cfg = load_datagen_config(args.config)
    cfg = dataclasses.replace(cfg, workcell=with_objects(cfg.workcell, args.objects))
    if args.resolution:
        w, h = parse_resolution(args.resolution)
        wc = cfg.workcell
        cfg = dataclasses.replace(cfg, workcell=dataclasses.replace(wc, hand_camera=dataclasses.replace(
            wc.hand_camera, width=w, height=h)))
    cfg = override(cfg, rgb_format=args.rgb_format, scene=args.scene)
    if args.blocks:
        counts = parse_blocks(args.blocks)
        if cfg.scene == "table":
            cfg = override(cfg, blocks=counts)
        else:
            cfg = dataclasses.replace(cfg, clutter=dataclasses.replace(cfg.clutter, parts=counts))
    return validate(cfg)


def run_datagen(args: argparse.Namespace) -> int:
    from posegrasp.datagen.generate import generate_dataset
    from posegrasp.errors import SceneUnsettled, UserError

    out = args.out
    try:
        s = generate_dataset(out, args.scenes, args.views, args.seed, load_config(args), split=args.split,
                             workers=args.workers, progress=not args.no_progress)
    except SceneUnsettled as e:  # the scenes written before it are complete: a rerun resumes after them
        raise UserError(str(e)) from None
    v = s["views"]
    if s["generated_scenes"] == 0:
        print(f"{out}: all {s['scenes']} scenes already complete; nothing to do")
    else:
        fps = s["generated_images"] / max(s["seconds"], 1e-9)
        print(f"wrote {s['generated_images']} images in {s['generated_scenes']} scenes in {s['seconds']:.1f} s "
              f"({fps:.1f} frames/s) -> {out}/{args.split}")
    print(f"dataset: {s['images']} images, {s['instances']} instances; viewpoints: {v['candidates']} drawn, "
          f"{v['out_of_reach']} out of reach, {v['unreachable']} failed IK, {v['blocked']} blocked by the scene")
    return 0
