"""The ``posegrasp`` command line: one program, a subcommand per job.

Each subcommand lives beside the code it drives, in a module exposing ``register(subparsers)``;
the handler it sets with ``set_defaults(run=...)`` receives the parsed arguments.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from posegrasp.arguments import positive_int, workers_arg  # noqa: F401  (option types, re-exported)
from posegrasp.errors import UserError


#: Modules that register subcommands, in the order they appear in ``--help``.
COMMAND_MODULES = (
    "posegrasp.sim.cli",
    "posegrasp.datagen.cli",
    "posegrasp.bop_cli",
    "posegrasp.perception.cli",
    "posegrasp.grasping.cli",
    "posegrasp.grasping.compare",
    "posegrasp.grasping.report",
    "posegrasp.objects.cli",
)


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2, no usage dump
        raise UserError(message)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="posegrasp", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    try:
        args = build_parser().parse_args(argv)
        return int(args.run(args) or 0)
    except UserError as e:
        print(f"posegrasp: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("posegrasp: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
