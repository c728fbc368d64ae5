"""``posegrasp scene``: build a random scene, move the arm to the look pose, and write a labelled capture."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from posegrasp.arguments import nonneg_int, out_dir, positive_int
from posegrasp.config import check_range
from posegrasp.errors import SimulationError, UserError
from posegrasp.lock import folder_lock
from posegrasp.outputs import Record
from posegrasp.sim.config import CameraConfig

#: The settings its commands read, for the settings page (``posegrasp.settings_doc``).
SETTINGS = (
    dict(title="Workcell", target="posegrasp.sim.config:WorkcellConfig", table="",
         command="`posegrasp scene --config FILE`",
         note="The shipped values are `assets/workcell.toml`. Datagen settings hold these as `[workcell]`, trial "
              "settings as `[scene.workcell]`."),
)


def parse_resolution(text: str) -> tuple[int, int]:
    """``"640x480"`` -> (640, 480), within ``CameraConfig``'s bounds; a one-line error for anything else."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UserError(f"resolution {text!r} is not WIDTHxHEIGHT, e.g. 640x480") from None
    fields = {f.name: f for f in dataclasses.fields(CameraConfig)}
    return check_range(fields["width"], w, "--resolution width"), check_range(fields["height"], h, "--resolution height")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("scene", help="render a random settled scene from the hand camera at the look pose")
    p.add_argument("--seed", type=nonneg_int("--seed"), default=0, help="scene seed (same seed, same scene)")
    p.add_argument("--blocks", type=positive_int("--blocks"), default=5, help="number of blocks to drop into the pick area")
    p.add_argument("--types", default="", help="comma-separated block types to draw from (default: all)")
    p.add_argument("--resolution", default=None, help="hand camera WIDTHxHEIGHT (default from the config)")
    p.add_argument("--config", default=None, help="workcell TOML file (default: assets/workcell.toml)")
    p.add_argument("--objects", default=None,
                   help="object set folder to draw objects from (default: the shipped blocks; docs/objects.md)")
    p.add_argument("--out", required=True, type=out_dir(), help="output folder")
    p.set_defaults(run=run_scene)


def run_scene(args: argparse.Namespace) -> int:
    from posegrasp.sim.config import load_workcell_config, with_objects
    from posegrasp.sim.scene import SceneConfig, make_scene

    wcfg = with_objects(load_workcell_config(args.config), args.objects)
    if args.resolution:
        w, h = parse_resolution(args.resolution)
        wcfg = dataclasses.replace(wcfg, hand_camera=dataclasses.replace(wcfg.hand_camera, width=w, height=h))
    types = tuple(t.strip() for t in args.types.split(",") if t.strip())
    scene = make_scene(args.seed, args.blocks, SceneConfig(block_types=types, workcell=wcfg))
    with folder_lock(args.out, owns=(SCENE_RECORD,)) as out:
        _write_scene(args, scene, wcfg, out)
    return 0


#: The files ``posegrasp scene`` writes: a non-empty --out holding none of them is someone else's folder.
SCENE_FILES = ("rgb.png", "depth.png", "mask.png", "overview.png", "scene.json")
#: What marks a folder ``posegrasp scene`` wrote (``posegrasp.outputs``).
SCENE_RECORD = Record("scene.json", ("seed", "camera", "K", "blocks"))


def _write_scene(args: argparse.Namespace, scene, wcfg, out: Path) -> None:
    """Capture the settled ``scene`` from the hand and overview cameras and write ``SCENE_FILES`` into ``out``."""
    from posegrasp.io import write_image, write_json
    from posegrasp.sim.camera import CameraRenderer
    from posegrasp.sim.workcell import HAND_CAMERA, OVERVIEW_CAMERA

    wc = scene.workcell
    if not wc.drive_arm(wc.look_q):
        raise SimulationError("the arm did not reach the look pose")
    c = wcfg.hand_camera
    hand = CameraRenderer(wc, HAND_CAMERA, c, wcfg.render)
    frame = hand.capture()
    over = CameraRenderer(wc, OVERVIEW_CAMERA, wcfg.overview_camera, wcfg.render)
    T_world_obj = wc.block_poses()
    write_json(out / "scene.json", {
        "seed": args.seed,
        "camera": HAND_CAMERA,
        "width": c.width, "height": c.height,
        "K": frame.K,
        "depth_scale_mm": 1.0,
        "T_world_cam": frame.T_world_cam,
        "arm_q": wc.arm_q,
        "blocks": [
            {"instance": k, "obj_id": inst.block.obj_id, "type": inst.block.name, "rgba": inst.rgba,
             "T_cam_obj": frame.T_cam_obj[k - 1], "T_world_obj": T_world_obj[k - 1],
             "visible_px": int((frame.mask == k).sum())}
            for k, inst in enumerate(wc.blocks, start=1)
        ],
    })  # first: the record that marks the folder as a scene's
    write_image(out / "rgb.png", frame.rgb)
    write_image(out / "depth.png", np.round(frame.depth * 1000.0).astype(np.uint16))
    write_image(out / "mask.png", frame.mask.astype(np.uint8))
    write_image(out / "overview.png", over.rgb())
    hand.close()
    over.close()
    print(f"scene seed {args.seed}: {len(wc.blocks)} blocks -> {out}")
