"""``posegrasp objects import|show``: make an object set from meshes, and draw one."""

from __future__ import annotations

import argparse
import sys

from posegrasp.arguments import in_dir, number, out_dir, out_file, workers_arg

#: The settings its commands read, for the settings page (``posegrasp.settings_doc``).
SETTINGS = (
    dict(title="Object import", target="posegrasp.objects.config:ImportConfig", table="import",
         command="`posegrasp objects import --config FILE`, table `[import]`"),
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("objects", help="object sets: import parts (STL, OBJ, PLY, GLB/GLTF, STEP, URDF, BOP models) or "
                                        "draw a set")
    cmds = p.add_subparsers(dest="objects_command", required=True, metavar="import|show")
    imp = cmds.add_parser("import", help="make an object set from meshes: repaired, measured, symmetries found, "
                                         "collision pieces by convex decomposition (CoACD)")
    imp.add_argument("meshes", nargs="+", metavar="MESH",
                     help="STL, OBJ (+MTL), PLY, GLB, GLTF, STEP or URDF files, or BOP models folders")
    imp.add_argument("--out", required=True, type=out_dir(), help="the object set folder to write")
    imp.add_argument("--unit", nargs="+", default=["m"], metavar="m|cm|mm",
                     help="length unit of the mesh files, one for all or one per mesh (default m; BOP models are mm; "
                          "STEP files declare their own)")
    imp.add_argument("--scale", nargs="+", type=number("--scale", 0.0, open_lo=True), default=None,
                     metavar="FACTOR", help="factor multiplying --unit, one for all or one per mesh (default 1; e.g. "
                                            "0.1 with --unit m for a mesh in decimetres)")
    imp.add_argument("--density", type=number("--density", 1.0, 25000.0), default=None,
                     help="density in kg/m^3 (default 1050, ABS plastic)")
    imp.add_argument("--mesh-root", type=in_dir("--mesh-root"), default=None, metavar="DIR",
                     help="the folder a URDF's meshes are found under, package://NAME/ paths included, never outside "
                          "it (default: the URDF's folder and the one above)")
    imp.add_argument("--name", nargs="+", default=None, metavar="NAME", help="one name per mesh (default: file names)")
    imp.add_argument("--config", default=None,
                     help="import settings TOML: an [import] table of objects.config.ImportConfig's fields")
    imp.add_argument("--workers", type=workers_arg, default=None,
                     help="worker processes, one part each at a time (default: one per core), or 'ray'")
    imp.add_argument("--no-progress", action="store_true", help="no progress bar")
    imp.set_defaults(run=run_import)
    show = cmds.add_parser("show", help="draw each object of a set with its collision pieces and symmetry axes")
    show.add_argument("set", metavar="SET", help="object set folder")
    show.add_argument("--out", required=True, type=out_file("--out", (".png",)), help="PNG file to write")
    show.add_argument("--force", action="store_true", help="replace --out even if this command did not write it")
    show.set_defaults(run=run_show)


def run_import(args: argparse.Namespace) -> int:
    from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn

    from posegrasp.config import override
    from posegrasp.objects.config import load_import_config
    from posegrasp.objects.importer import import_objects, sources
    from posegrasp.objset import check_writable_set, write_object_set
    from posegrasp.progress import progress

    cfg = override(load_import_config(args.config), density=args.density,
                   mesh_root=None if args.mesh_root is None else str(args.mesh_root))
    check_writable_set(args.out)
    replacing = (args.out / "objectset.json").is_file()
    srcs = sources(args.meshes, args.unit, args.name, args.scale)
    reports: dict[int, list[str]] = {}

    def report(o, seconds: float) -> None:
        lines = reports.setdefault(o.obj_id, [])
        sym = f"{len(o.symmetries_discrete)} discrete" + (
            f" + {len(o.symmetries_continuous)} continuous" if o.symmetries_continuous else "")
        n = len(o.collision)
        lines.append(f"{o.obj_id} {o.name}: {o.mass * 1000:.1f} g, {o.extents[0] * 1000:.1f} x "
                     f"{o.extents[1] * 1000:.1f} x {o.extents[2] * 1000:.1f} mm, symmetries {sym}, "
                     f"{n} collision piece{'s' if n != 1 else ''} covering {o.collision_volume_ratio:.3f} of its "
                     f"volume ({seconds:.1f} s)")
        lines.extend(f"  repaired: {r}" for r in o.repairs)
        if o.repairs:
            lines.append(f"  volume change by the repairs: {100 * o.volume_change:+.2f} %")
        lines.extend(f"  warning: {w}" for w in o.warnings)
        bar.advance(task)

    with progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  enabled=not args.no_progress, transient=True) as bar:
        task = bar.add_task("import", total=len(srcs))
        objects = import_objects(srcs, cfg, report, args.workers)
    write_object_set(args.out, objects, cfg.firm_hold_tasks)
    if replacing:
        print(f"posegrasp: note: replaced the object set that was in {args.out}", file=sys.stderr)
    print("\n".join(ln for i in sorted(reports) for ln in reports[i]))
    print(f"wrote object set {args.out} ({len(objects)} objects)")
    return 0


def run_show(args: argparse.Namespace) -> int:
    from posegrasp.objects.show import draw_set
    from posegrasp.objset import load_object_set
    from posegrasp.outputs import check_out_file

    check_out_file(args.out, "objects show", force=args.force, sealed=[args.set])
    draw_set(load_object_set(args.set), args.out)
    print(f"wrote {args.out}")
    return 0
