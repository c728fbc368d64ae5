"""Perception providers by name: ``make_provider(spec)`` builds the provider a ``--perception`` value names.

- ``oracle`` and ``noisy-oracle[:TRANS_M,ROT_DEG]``: ``grasping.perception``;
- ``model[:RUN]``: the learned network, ``grasping.model_provider``, imported (with torch) only when asked for.
"""

from __future__ import annotations

from typing import Callable

from posegrasp.errors import UserError
from posegrasp.grasping.perception import Provider, noisy_oracle_from_spec, oracle_from_spec


def _model(args: str | None) -> Provider:
    from posegrasp.grasping.model_provider import from_spec

    return from_spec(args)


#: Provider factories by name; each gets the text after ``name:`` (or None).
FACTORIES: dict[str, Callable[[str | None], Provider]] = {
    "oracle": oracle_from_spec,
    "noisy-oracle": noisy_oracle_from_spec,
    "model": _model,
}


def make_provider(spec: str) -> Provider:
    """A provider from ``name[:ARGS]`` (``oracle``, ``noisy-oracle:0.005,5``, ``model:RUN``)."""
    name, _, args = spec.partition(":")
    if name not in FACTORIES:
        raise UserError(f"unknown perception {spec!r}; choose one of: {', '.join(sorted(FACTORIES))}")
    return FACTORIES[name](args or None)
