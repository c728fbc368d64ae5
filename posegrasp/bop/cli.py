"""``posegrasp dataset check|show|merge``: validate any BOP dataset, draw one of its images with its labels, or merge
several into one."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from posegrasp.arguments import nonneg_int, number, out_file, positive_int
from posegrasp.errors import DatasetError, UserError


def register(sub: argparse._SubParsersAction) -> None:
    d = sub.add_parser("dataset", help="check or draw a BOP dataset")
    dsub = d.add_subparsers(dest="dataset_command", required=True, parser_class=type(d))
    c = dsub.add_parser("check", help="validate a BOP dataset and print a summary (exit 1 when invalid, with the "
                        "first problem on stderr)")
    c.add_argument("dir", help="dataset root (holding models/, camera.json and split folders)")
    c.add_argument("--split", default=None, help="only this split (default: every split found)")
    c.add_argument("--depth-tol-mm", type=number("--depth-tol-mm", 0, open_lo=True), default=5.0,
                   help="max median depth-to-model distance (mm)")
    c.add_argument("--max-images", type=positive_int("--max-images"), default=None, help="check at most N images per scene")
    c.set_defaults(run=run_check)
    s = dsub.add_parser("show", help="draw one image with masks, 3D boxes and axes next to its depth")
    s.add_argument("dir", help="dataset root")
    s.add_argument("--scene", type=nonneg_int("--scene"), required=True, help="scene id")
    s.add_argument("--im", type=nonneg_int("--im"), required=True, help="image id")
    s.add_argument("--out", required=True, type=out_file("--out", (".png", ".jpg", ".jpeg")),
                   help="output image (.png, or .jpg)")
    s.add_argument("--split", default=None, help="split (default: the only one present)")
    s.add_argument("--force", action="store_true", help="replace --out even if this command did not write it")
    s.set_defaults(run=run_show)
    m = dsub.add_parser("merge", help="write a new BOP root holding the scenes of several, renumbered (to train on "
                        "them together)")
    m.add_argument("out", help="the new dataset root (must not exist)")
    m.add_argument("sources", nargs="+", help="dataset roots, each ROOT or ROOT:SPLIT (default: its only split); "
                   "all with the same models and camera.json")
    m.add_argument("--split", default="train_pbr", help="the merged split's name (default train_pbr)")
    m.set_defaults(run=run_merge)


def run_check(args: argparse.Namespace) -> int:
    from posegrasp.bop.check import CheckOptions, check_dataset, print_report

    opts = CheckOptions(depth_tol_mm=args.depth_tol_mm, max_images=args.max_images)
    report = check_dataset(args.dir, args.split, opts, progress=True)
    print_report(report, args.dir)
    if not report.ok:
        print(f"posegrasp: error: {args.dir}: {len(report.problems)} problem(s), the first: {report.problems[0]}",
              file=sys.stderr)
    return 0 if report.ok else 1


def run_show(args: argparse.Namespace) -> int:
    from posegrasp.bop.check import find_splits
    from posegrasp.bop.show import show_image
    from posegrasp.io import write_image
    from posegrasp.outputs import check_out_file

    root = Path(args.dir)
    if not root.is_dir():
        raise DatasetError(f"dataset folder {root} does not exist")
    split = args.split
    if split is None:
        splits = find_splits(root)
        if len(splits) != 1:
            raise DatasetError(f"{root} has splits {splits or 'none'}; choose one with --split")
        split = splits[0]
    check_out_file(args.out, "dataset show", force=args.force, sealed=[root])
    panel = show_image(root, split, args.scene, args.im)
    try:
        write_image(args.out, panel, mark="dataset show")
    except OSError as e:
        raise UserError(f"cannot write {args.out}: {e.strerror or e}") from None
    print(f"scene {args.scene} image {args.im} -> {args.out}")
    return 0


def run_merge(args: argparse.Namespace) -> int:
    from posegrasp.bop.merge import merge_datasets, parse_source

    n = merge_datasets(args.out, [parse_source(s) for s in args.sources], args.split)
    print(f"{n} scenes from {len(args.sources)} datasets -> {args.out}/{args.split}")
    return 0
