"""Time per 640x480 RGB-D frame with 5 objects, per perception stage, on this machine's CPU.

    MUJOCO_GL=egl python bench/perception.py [--weights RUN] [--threads 2] [--repeats 20] [--json out.json]
    MUJOCO_GL=egl python bench/perception.py --scene bin --blocks 30 [--weights RUN] [--repeats 5]
    MUJOCO_GL=egl python bench/perception.py ... --baseline REF [--rounds N]  # also on REF's code, and the ratio

``--scene bin --blocks N``: the whole ``Estimator`` call (its own segmentation, the splits of merged segments, the
depth fits) on a real capture of N parts settled in the tote, from the bin-picking look straight down at its centre
(scene ``--seed``), with the shipped bin model unless ``--weights``; stages as ``EstimateResult.timings``.

The frame is a real hand-camera capture of a 5-block workcell scene; the stages after segmentation get the
5 blocks' true masks, so every run times the same work.

Without --weights the nets are built at their default (CPU) configurations with random weights
(the timing does not depend on the weight values) and saved to a temporary run directory, so the
real loading path is exercised. Stages: seg = resize, segmentation net, upsampling to 640x480,
softmax and argmax; cls = the instance classifier on the 5 objects' segments (when the run has one);
pose = crops, point sampling and the pose net on the 5 objects as one batch;
refiner = the refiner's iterations on the 5 objects; plane = the supporting plane's RANSAC fit and mask cleanup;
depth_fit = the depth fit of the 5 estimates
(``perception.depth_fit``, with the block catalogue's meshes); split = the test of the 5 masks against their fitted
models and the fits of any parts split off (``perception.split``). Prints a table and a JSON line.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

os.environ.setdefault("MUJOCO_GL", "egl")

import baseline

from posegrasp.perception import checkpoint
from posegrasp import ASSETS
from posegrasp.perception.classifier import ClassifierConfig, build_classifier
from posegrasp.perception.estimator import Estimator, EstimatorConfig
from posegrasp.perception.plane import fit_support_plane, plane_pixels
from posegrasp.perception.pose_net import PoseNetConfig, build_pose_net
from posegrasp.perception.refiner import RefinerConfig, build_refiner
from posegrasp.perception.runtime import one_blas_thread
from posegrasp.perception.seg_net import SegNetConfig, build_seg_net

OBJ_IDS = [1, 2, 3, 4, 5, 6, 7, 8]


def make_default_run(root: Path) -> Path:
    """Random-weight default nets for 8 objects saved as a run directory."""
    torch.manual_seed(0)
    seg_cfg = SegNetConfig(num_classes=len(OBJ_IDS) + 1)
    pose_cfg = PoseNetConfig(obj_ids=OBJ_IDS, symmetric=[False] * len(OBJ_IDS))
    ref_cfg = RefinerConfig(obj_ids=OBJ_IDS, symmetric=[False] * len(OBJ_IDS), emb_dim=pose_cfg.emb_dim)
    checkpoint.save(root / "seg", "seg", build_seg_net(seg_cfg), seg_cfg, None, {"step": 0})
    checkpoint.save(root / "pose", "pose", build_pose_net(pose_cfg), pose_cfg, None, {"step": 0})
    checkpoint.save(root / "refiner", "refiner", build_refiner(ref_cfg), ref_cfg, None, {"step": 0})
    cls_cfg = ClassifierConfig(obj_ids=OBJ_IDS)
    checkpoint.save(root / "cls", "cls", build_classifier(cls_cfg), cls_cfg, None, {"step": 0})
    return root


def sim_frame(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[tuple[int, np.ndarray]]]:
    """A real 640x480 hand-camera frame of the workcell (scene ``seed``, 5 blocks, all in view, at the look
    pose): RGB, depth (m), K and the 5 blocks' (obj_id, visible mask)."""
    from posegrasp.sim.camera import CameraRenderer
    from posegrasp.sim.scene import make_scene
    from posegrasp.sim.workcell import HAND_CAMERA

    wc = make_scene(seed, 5).workcell
    wc.drive_arm(wc.look_q)
    c = wc.cfg.hand_camera
    cam = CameraRenderer(wc, HAND_CAMERA, c)
    f = cam.capture()
    cam.close()
    masks = [(int(o), f.mask == k + 1) for k, o in enumerate(f.obj_ids)]
    assert all(m.any() for _, m in masks), "a block of the benchmark scene is out of view"
    return f.rgb, f.depth, f.K, masks


def bin_frame(seed: int, blocks: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A real 640x480 hand-camera frame of ``blocks`` parts settled in the tote (scene ``seed``), from the bin-picking
    look: RGB, depth (m, in the 0.1 mm steps a provider sees) and K."""
    import dataclasses

    from posegrasp.bop.images import quantise_depth
    from posegrasp.grasping.config import TrialConfig
    from posegrasp.grasping.perception import DEPTH_SCALE
    from posegrasp.grasping.targets import look_down_q
    from posegrasp.grasping.tasks import with_set
    from posegrasp.grasping.tasks.bin_pick.scene import area_of, bin_scene
    from posegrasp.sim.camera import CameraRenderer
    from posegrasp.sim.workcell import HAND_CAMERA

    cfg = with_set(TrialConfig(task="bin-pick"))
    clutter = dataclasses.replace(cfg.bin_pick.clutter, parts=(blocks, blocks))
    cfg = dataclasses.replace(cfg, bin_pick=dataclasses.replace(cfg.bin_pick, clutter=clutter))
    wc = bin_scene(cfg, seed, blocks)
    wc.drive_arm(look_down_q(wc.cfg, area_of(wc, cfg.bin_pick).tote.center, wc.cfg.look_height, "look_height"))
    cam = CameraRenderer(wc, HAND_CAMERA, wc.cfg.hand_camera)
    f = cam.capture()
    cam.close()
    return f.rgb, quantise_depth(f.depth, DEPTH_SCALE), f.K


def bench_whole(est: Estimator, frame: tuple[np.ndarray, np.ndarray, np.ndarray], repeats: int, warmup: int
                ) -> dict[str, dict[str, float]]:
    """Stage timings (``EstimateResult.timings``) and the total of whole ``Estimator`` calls on ``frame``."""
    times: dict[str, list[float]] = {}
    for i in range(warmup + repeats):
        t0 = time.perf_counter()
        res = est(*frame)
        total = time.perf_counter() - t0
        if i >= warmup:
            for k, v in {**res.timings, "total": total}.items():
                times.setdefault(k, []).append(v)
    return {k: {"median_ms": 1000 * statistics.median(v), "mean_ms": 1000 * statistics.fmean(v),
                "min_ms": 1000 * min(v)} for k, v in times.items()}


def bench(est: Estimator, repeats: int, warmup: int) -> dict[str, dict[str, float]]:
    """Stage timings of ``est`` (built with the catalogue's meshes, for the depth fit) on ``sim_frame()``."""
    rgb, depth, K, masks = sim_frame()
    masks = [(o, m) for o, m in masks if o in est.obj_ids]
    labels = np.zeros(rgb.shape[:2], dtype=np.int64)  # the 5 blocks' true class map as the seg net's
    for o, m in masks:
        labels[m] = o
    times: dict[str, list[float]] = {"seg": [], "plane": [], "cls": [], "pose": [], "refiner": [], "depth_fit": [],
                                     "split": [], "guided": [], "total": []}
    for i in range(warmup + repeats):
        t0 = time.perf_counter()
        _, prob = est.segment(rgb)
        t05 = time.perf_counter()
        plane = fit_support_plane(depth, K, est.seed, est.plane_cfg)
        plane_pixels(plane, depth, K, labels > 0, est.plane_cfg.mask_tol)
        t1 = time.perf_counter()
        if est.classifier is not None:
            est.classify(rgb, depth, K, labels, plane)
        t15 = time.perf_counter()
        dets, stages = est.estimate(rgb, depth, K, masks, plane=plane)
        assert len(dets) == len(masks)
        t19 = time.perf_counter()
        est.split_merged(rgb, depth, K, dets, prob, plane, labels)
        t195 = time.perf_counter()
        est.snap_outlines(rgb, labels, dets)
        t2 = time.perf_counter()
        if i >= warmup:
            times["seg"].append(t05 - t0)
            times["plane"].append(t1 - t05)
            times["cls"].append(t15 - t1)
            for k in ("pose", "refiner", "depth_fit"):
                times[k].append(stages[k])
            times["split"].append(t195 - t19)
            times["guided"].append(t2 - t195)
            times["total"].append(t2 - t0)
    return {k: {"median_ms": 1000 * statistics.median(v), "mean_ms": 1000 * statistics.fmean(v),
                "min_ms": 1000 * min(v)} for k, v in times.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--weights", type=Path, help="run directory (default: random default-config nets)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--json", type=Path, help="also write the JSON result here")
    ap.add_argument("--scene", choices=("table", "bin"), default="table",
                    help="table: 5 blocks, true masks after segmentation; bin: whole calls on a tote of --blocks parts")
    ap.add_argument("--blocks", type=int, default=30, help="parts in the tote (--scene bin)")
    ap.add_argument("--seed", type=int, default=0, help="the tote's scene seed (--scene bin)")
    ap.add_argument("--no-int8", action="store_true", help="the seg net and classifiers in float, also where the run "
                    "has int8 ranges (int8.json)")
    baseline.add_arguments(ap)
    args = ap.parse_args(argv)
    if args.baseline:
        return baseline.compare(__file__, sys.argv[1:] if argv is None else argv, args.baseline,
                                "stages.total.median_ms", False, args.rounds, args.baseline_script)
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        bin_model = ASSETS / "perception" / "model_bin"
        weights = args.weights or (bin_model if args.scene == "bin" else make_default_run(Path(tmp)))
        float_only = {"int8": False} if args.no_int8 else {}  # (a baseline's code may predate the setting)
        est = Estimator(weights, EstimatorConfig(models=ASSETS / "blocks", **float_only))  # meshes: the depth fit
        cfg = {"seg_input_size": list(est.seg_cfg.input_size), "seg_width": est.seg_cfg.width,
               "num_points": est.pose_points, "crop_size": est.pose_crop,
               "backbone_width": est.pose_cfg.backbone_width,
               "attention": [est.pose_cfg.use_pam, est.pose_cfg.use_cam, est.pose_cfg.use_gfem],
               "refiner_iterations": est.refiner_cfg.iterations if est.refiner_cfg else 0,
               "int8": getattr(est, "int8_nets", [])}
        if args.scene == "bin":
            frame = baseline.shared_input(f"bin_{args.seed}_{args.blocks}.npz", lambda: bin_frame(args.seed, args.blocks))
            res = bench_whole(est, frame, args.repeats, args.warmup)
        else:
            with one_blas_thread():  # as in the Estimator's own methods, for the plane's fit called here
                res = bench(est, args.repeats, args.warmup)
    objects = args.blocks if args.scene == "bin" else 5
    out = {"frame": "640x480", "scene": args.scene, "objects": objects, "threads": args.threads,
           "torch": torch.__version__, "cpu": platform.processor() or platform.machine(),
           "weights": str(weights if args.scene == "bin" else args.weights or "random default"), "config": cfg,
           "stages": res}
    try:
        from rich.console import Console
        from rich.table import Table

        t = Table(title=f"perception, 640x480, {args.scene}, {objects} objects, {args.threads} threads (ms per frame)")
        for c in ("stage", "median", "mean", "min"):
            t.add_column(c, justify="right")
        for k, v in res.items():
            t.add_row(k, f"{v['median_ms']:.1f}", f"{v['mean_ms']:.1f}", f"{v['min_ms']:.1f}")
        Console(stderr=True).print(t)
    except ImportError:
        pass
    print(json.dumps(out))
    if args.json:
        from posegrasp.io import write_json

        write_json(args.json, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
