"""Time per 640x480 RGB-D frame with 5 objects, per perception stage, on this machine's CPU.

    python bench/perception.py [--weights RUN] [--threads 2] [--repeats 20] [--json out.json]

Without --weights the nets are built at their default (CPU) configurations with random weights
(the timing does not depend on the weight values) and saved to a temporary run directory, so the
real loading path is exercised. Stages: seg = resize, segmentation net, upsampling to 640x480,
softmax and argmax; cls = the instance classifier on the 5 objects' segments (when the run has one);
pose = crops, point sampling and the pose net on the 5 objects as one batch;
refine = the refiner's iterations on the 5 objects; plane = the supporting plane's RANSAC fit and mask cleanup;
icp = the depth refinement of the 5 estimates
(``perception.icp``, with the block catalogue's meshes). Prints a table and a JSON line.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from perception import checkpoint  # noqa: E402
from posegrasp import ASSETS  # noqa: E402
from perception.classifier import ClassifierConfig, build_classifier  # noqa: E402
from perception.plane import fit_support_plane, plane_pixels  # noqa: E402
from perception.inference import Estimator  # noqa: E402
from perception.pose_net import PoseNetConfig, build_pose_net  # noqa: E402
from perception.refiner import RefinerConfig, build_refiner  # noqa: E402
from perception.seg_net import SegNetConfig, build_seg_net  # noqa: E402

OBJ_IDS = [1, 2, 3, 4, 5, 6, 7, 8]


def make_default_run(root: Path) -> Path:
    """Random-weight default nets for 8 objects saved as a run directory."""
    torch.manual_seed(0)
    seg_cfg = SegNetConfig(num_classes=len(OBJ_IDS) + 1)
    pose_cfg = PoseNetConfig(obj_ids=OBJ_IDS, symmetric=[False] * len(OBJ_IDS))
    ref_cfg = RefinerConfig(obj_ids=OBJ_IDS, symmetric=[False] * len(OBJ_IDS), emb_dim=pose_cfg.emb_dim)
    checkpoint.save(root / "seg", "seg", build_seg_net(seg_cfg), seg_cfg, None, {"step": 0})
    checkpoint.save(root / "pose", "pose", build_pose_net(pose_cfg), pose_cfg, None, {"step": 0})
    checkpoint.save(root / "refine", "refine", build_refiner(ref_cfg), ref_cfg, None, {"step": 0})
    cls_cfg = ClassifierConfig(obj_ids=OBJ_IDS)
    checkpoint.save(root / "cls", "cls", build_classifier(cls_cfg), cls_cfg, None, {"step": 0})
    return root


def synthetic_frame(n_objects: int = 5, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, list]:
    """640x480 frame: random colours, a table plane at ~0.5 m, n blobs of ~60x50 px as objects."""
    rng = np.random.default_rng(seed)
    h, w = 480, 640
    rgb = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
    depth = np.full((h, w), 0.55, np.float32) + rng.normal(0, 0.001, (h, w)).astype(np.float32)
    K = np.array([[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]])
    masks = []
    yy, xx = np.mgrid[:h, :w]
    for i in range(n_objects):
        cy, cx = 120 + 60 * (i % 3), 120 + 100 * i
        m = ((yy - cy) / 25.0) ** 2 + ((xx - cx) / 30.0) ** 2 <= 1.0
        depth[m] = 0.52
        masks.append((OBJ_IDS[i], m))
    return rgb, depth, K, masks


def bench(weights: Path, repeats: int, warmup: int) -> dict[str, dict[str, float]]:
    est = Estimator(weights, models=ASSETS / "blocks")  # the catalogue's meshes, for the depth refinement
    if est.refine_iterations == 0 and est.refiner is not None:
        est.refine_iterations = est.refiner_cfg.iterations
    rgb, depth, K, masks = synthetic_frame()
    masks = [(o, m) for o, m in masks if o in est.obj_ids]
    labels = np.zeros(rgb.shape[:2], dtype=np.int64)  # the 5 objects as the seg net's class map
    for o, m in masks:
        labels[m] = o
    times: dict[str, list[float]] = {"seg": [], "plane": [], "cls": [], "pose": [], "refine": [], "icp": [],
                                     "total": []}
    for i in range(warmup + repeats):
        t0 = time.perf_counter()
        est.segment(rgb)
        t05 = time.perf_counter()
        plane = fit_support_plane(depth, K, est.seed, est.plane_cfg)
        plane_pixels(plane, depth, K, labels > 0, est.plane_cfg.mask_tol)
        t1 = time.perf_counter()
        if est.classifier is not None:
            est.classify(rgb, depth, K, labels)
        t15 = time.perf_counter()
        dets = est.estimate(rgb, depth, K, masks, plane=plane)
        t2 = time.perf_counter()
        assert len(dets) == len(masks)
        if i >= warmup:
            times["seg"].append(t05 - t0)
            times["plane"].append(t1 - t05)
            times["cls"].append(t15 - t1)
            times["pose"].append(est.timings["pose"])
            times["refine"].append(est.timings["refine"])
            times["icp"].append(est.timings["icp"])
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
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        weights = args.weights or make_default_run(Path(tmp))
        est = Estimator(weights)
        cfg = {"seg_input_size": list(est.seg_cfg.input_size), "seg_width": est.seg_cfg.width,
               "num_points": est.pose_cfg.num_points, "crop_size": est.pose_cfg.crop_size,
               "backbone_width": est.pose_cfg.backbone_width,
               "attention": [est.pose_cfg.use_pam, est.pose_cfg.use_cam, est.pose_cfg.use_gfem],
               "refine_iterations": est.refiner_cfg.iterations if est.refiner_cfg else 0}
        res = bench(weights, args.repeats, args.warmup)
    out = {"frame": "640x480", "objects": 5, "threads": args.threads, "torch": torch.__version__,
           "cpu": platform.processor() or platform.machine(), "weights": str(args.weights or "random default"),
           "config": cfg, "stages": res}
    try:
        from rich.console import Console
        from rich.table import Table

        t = Table(title=f"perception, 640x480, 5 objects, {args.threads} threads (ms per frame)")
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
