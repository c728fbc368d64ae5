"""``posegrasp eval --perception SPEC``: a perception provider scored on a BOP split as ``eval --weights RUN`` scores
the network, with the same metrics, tables and results CSV (``perception.evaluate``), so that a method and the
baselines (``ppf``, ``depth-icp``, ``model[:RUN]``, a ``py:`` plug-in, an installed name, or ``bop-csv:FILE``, whose
rows are read by scene_id and im_id) are scored by one command.

Each image reaches the provider as a hand-camera capture reaches it in the trials (``Observation``: RGB, depth in m,
K, and the image's ``scene_id`` and ``im_id``), with the seed ``EvalConfig.seed``; its estimates are checked as the
trials check them (``grasping.perception.checked_estimates``; a plug-in runs in its own process with the trials' time
limit, a built-in provider without one: its time is what eval measures). A provider that raises, hangs or answers
what the planner could not use stops the evaluation with one line naming the image, before anything is written.
The oracles read the simulator's labels, which a dataset does not hold: refused.

The provider knows the object set ``--objects`` (default: the shipped blocks); the dataset must show that set's
models (its ``models/models_info.json`` the set's, as ``datagen --objects SET`` writes it).

The ``eval`` command is ``perception.cli``'s; ``register`` adds ``--perception`` and ``--objects`` to it (perception
may not import the providers, which live here) and sends a run with ``--perception`` here.
"""

from __future__ import annotations

import argparse
import functools
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from posegrasp.errors import DatasetError, PerceptionError, UserError

if TYPE_CHECKING:  # the command line registers ``--perception`` without loading the providers (torch, MuJoCo)
    from posegrasp.perception.evaluate import EvalConfig, Method

#: ``eval``'s flags that choose or ablate the network's stages: meaningless for a provider, refused with it.
NETWORK_FLAGS = {"gt_masks": "--gt-masks", "no_refiner": "--no-refiner", "no_cls": "--no-cls",
                 "no_depth_fit": "--no-depth-fit", "no_plane": "--no-plane", "no_guided": "--no-guided",
                 "no_split": "--no-split", "min_mask_px": "--min-mask-px", "threads": "--threads"}


def provider_method(spec: str, objects: str = "", cfg: EvalConfig | None = None) -> Method:
    """The provider ``spec`` for the object set ``objects`` as eval runs it on each image (module doc); a one-line
    UserError when it cannot be built or is an oracle."""
    from posegrasp.catalog import catalog_by_id, set_root
    from posegrasp.grasping.perception import Observation, checked_estimates, reads_labels
    from posegrasp.grasping.provider_registry import canonical_spec, make_provider
    from posegrasp.perception.evaluate import EvalConfig, FrameResult, Method

    cfg = cfg or EvalConfig()
    spec = canonical_spec(spec)
    provider = make_provider(spec, objects)
    if reads_labels(provider):
        raise UserError(f"--perception {spec!r} reads the simulator's labels, which a dataset does not hold; eval "
                        "scores providers that see the images (ppf, depth-icp, model[:RUN], py:..., bop-csv:FILE)")
    known = sorted(catalog_by_id(objects))
    name = str(getattr(provider, "name", spec))

    def run(rec: Any, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, gt_masks: list) -> FrameResult:
        obs = Observation(rgb, np.asarray(depth, dtype=np.float32), np.asarray(K, dtype=np.float64), rec.scene_id,
                          rec.im_id)
        t0 = time.perf_counter()
        try:
            found = checked_estimates(provider.estimate(obs, cfg.seed), known, f"provider {name!r}")
        except PerceptionError as e:
            raise UserError(f"--perception {spec!r} on scene {rec.scene_id} image {rec.im_id}: {e}") from None
        except Exception as e:  # a provider's own error: one line, nothing written
            raise UserError(f"--perception {spec!r} on scene {rec.scene_id} image {rec.im_id} raised "
                            f"{type(e).__name__}: {' '.join(str(e).split())[:200]}") from None
        return found, {"provider": time.perf_counter() - t0}, None

    return Method(run, known, ("provider",), 0, {"perception": spec, "objects": str(set_root(objects))})


def check_models(data: Path, objects: str) -> None:
    """A one-line DatasetError unless the dataset ``data`` shows the object set ``objects``'s models."""
    from posegrasp import bop, inputs
    from posegrasp.catalog import set_root

    ours, theirs = bop.models_info_path(set_root(objects)), bop.models_info_path(data)
    if inputs.read_bytes(ours, "text", DatasetError) != inputs.read_bytes(theirs, "text", DatasetError):
        raise DatasetError(f"--data {data} shows other models than the object set {set_root(objects)} "
                           "(models/models_info.json differs); give the set it was generated with: --objects SET")


def run_eval(args: argparse.Namespace, weights_run: Callable[[argparse.Namespace], int]) -> int:
    """Handler of ``posegrasp eval``: ``--perception SPEC`` here, ``--weights RUN`` by ``weights_run``."""
    from posegrasp.bop.check import require_valid
    from posegrasp.perception.cli import eval_settings, print_eval_summary
    from posegrasp.perception.evaluate import evaluate_method

    if args.perception is None:
        return weights_run(args)
    if args.weights is not None:
        raise UserError("give --weights RUN or --perception SPEC, not both")
    given = [flag for dest, flag in NETWORK_FLAGS.items() if getattr(args, dest, None) not in (None, False)]
    if given:
        raise UserError(f"{given[0]} chooses the network's stages (--weights); it does not apply to --perception")
    if args.out is None:
        raise UserError("eval --perception needs --out FOLDER for its reports")
    cfg = eval_settings(args)
    objects = args.objects or ""
    check_models(args.data, objects)
    require_valid(args.data, cfg.split, cfg.max_images or None, scoring=True, progress=not args.no_progress)
    method = provider_method(args.perception, objects, cfg)
    report = evaluate_method(args.data, method, args.out, cfg, progress=not args.no_progress)
    print_eval_summary(args.out, report)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``--perception`` and ``--objects`` to the ``eval`` command (``perception.cli`` registers it first)."""
    e = sub.choices["eval"]
    e.add_argument("--perception", metavar="SPEC",
                   help="score a perception provider instead of --weights: ppf[:FILE] | depth-icp[:FILE] | "
                        "model[:RUN] | py:MODULE_OR_FILE:FACTORY[:ARGS] | an installed name | bop-csv:RESULTS.csv "
                        "(docs/estimators.md); needs --out")
    e.add_argument("--objects", help="with --perception: the object set the dataset shows (default: the shipped "
                                     "blocks)")
    e.set_defaults(run=functools.partial(run_eval, weights_run=e.get_default("run")))

