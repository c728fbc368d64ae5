"""The ``posegrasp`` command line: one program, a subcommand per job.

Each subcommand lives beside the code it drives, in a module exposing ``register(subparsers)``;
the handler it sets with ``set_defaults(run=...)`` receives the parsed arguments.
"""

from __future__ import annotations

import argparse
import atexit
import errno
import importlib
import os
import sys
import threading
from typing import NoReturn

from posegrasp.arguments import positive_int, workers_arg  # noqa: F401  (option types, re-exported)
from posegrasp.errors import NoSpaceError, SimulationError, UserError
from posegrasp.io import flush_output, is_no_space

#: Exit status of a full disk (``EX_IOERR`` of sysexits.h); bad input exits 2, Ctrl-C 130.
EXIT_NO_SPACE = 74


#: Modules that register subcommands, in the order they appear in ``--help``, with the commands each registers:
#: a command line names one, and only its module is imported (a program's start-up is its imports).
COMMAND_MODULES = {
    "posegrasp.sim.cli": ("scene",),
    "posegrasp.datagen.cli": ("datagen",),
    "posegrasp.bop.cli": ("dataset",),
    "posegrasp.perception.cli": ("train", "eval", "perturb"),
    "posegrasp.grasping.provider_eval": ("eval",),  # eval --perception SPEC: providers live in grasping
    "posegrasp.grasping.cli": ("trials", "calibrate"),
    "posegrasp.grasping.compare": ("compare",),
    "posegrasp.grasping.report": ("report",),
    "posegrasp.objects.cli": ("objects",),
}


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2, no usage dump
        raise UserError(message)


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The program's parser; with ``argv`` whose first word is a command, that command's module alone registers."""
    parser = _Parser(prog="posegrasp", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    word = next((a for a in argv or () if not a.startswith("-")), None)
    chosen = [m for m, cmds in COMMAND_MODULES.items() if word in cmds] or list(COMMAND_MODULES)
    for name in chosen:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    os.environ.setdefault("MUJOCO_GL", "egl")
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    args = None
    try:
        args = build_parser(sys.argv[1:] if argv is None else argv).parse_args(argv)
        return int(args.run(args) or 0)
    except UserError as e:
        print(f"posegrasp: error: {e}", file=sys.stderr)
        return 2
    except NoSpaceError as e:
        print(f"posegrasp: error: {e}", file=sys.stderr)
        return EXIT_NO_SPACE
    except SimulationError as e:  # a scene that never settles, physics the settings make unstable
        print(f"posegrasp: error: {str(e).splitlines()[0] if str(e) else type(e).__name__}; check the settings",
              file=sys.stderr)
        return 2
    except OSError as e:  # a full disk met outside the writers that name their folder
        if e.errno == errno.ENAMETOOLONG:
            print(f"posegrasp: error: {str(e.filename)[:80]}...: the path is too long to name a file", file=sys.stderr)
            return 2
        if not is_no_space(e):
            raise
        print(f"posegrasp: error: {NoSpaceError(_written_folder(e, args))}", file=sys.stderr)
        return EXIT_NO_SPACE
    except KeyboardInterrupt:
        hint = getattr(args, "resume_hint", None)
        print("posegrasp: interrupted" + (f"; {hint}" if hint else ""), file=sys.stderr)
        return 130


def _written_folder(e: OSError, args: argparse.Namespace | None) -> str:
    """The folder a failed write went to: the error's file's folder, else the command's output."""
    if e.filename:
        return os.path.dirname(os.path.abspath(e.filename))
    out = getattr(args, "out", None) or getattr(args, "dir", None)
    return str(out) if out else os.getcwd()


def exit_now(status: int) -> NoReturn:
    """End the process with ``status`` as ``sys.exit`` does, less the interpreter's teardown: the threads are joined
    and the exit handlers run (``atexit``: Ray's shutdown, temporary folders, logging), stdout and stderr flushed,
    but the modules are not freed one by one (about 0.5 s with torch, SciPy and MuJoCo loaded; 0.8 s in a forked
    process, whose teardown copies every page it touches). The program's files are closed by then. Under a
    profiler or a debugger (``python -m cProfile``, which writes its results after the program returns) it is
    ``sys.exit``."""
    if sys.getprofile() is not None or sys.gettrace() is not None:
        sys.exit(status)
    threading._shutdown()  # what the interpreter does first on its way out: join the threads not daemonic
    atexit._run_exitfuncs()
    flush_output()
    os._exit(status)


def entry() -> NoReturn:
    """The ``posegrasp`` program: ``main``'s status (or ``SystemExit``'s) as the exit status, by ``exit_now``; an
    uncaught error ends it the usual way, with its traceback."""
    try:
        status = main()
    except SystemExit as e:  # ``--help``'s, or a plug-in's
        status = _exit_status(e.code)
    exit_now(status)


def _exit_status(code: object) -> int:
    """The exit status of ``SystemExit(code)``, as the interpreter reads it: None is 0, a message is printed (1)."""
    if code is None or isinstance(code, int):
        return code or 0
    print(code, file=sys.stderr)
    return 1


if __name__ == "__main__":
    entry()
