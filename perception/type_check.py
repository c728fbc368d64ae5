"""The type check: a part the instance classifier is unsure of is fitted to the depth image as each of its likely
types, and takes the type whose fit, weighed against the classifier's belief, is best:

    type = argmin_c  s_c - weight * ln p_c      over the candidates c: p_c >= min_prob, at most max_types

s_c: the depth fit's score (m, lower is better; ``perception.depth_fit.score``) of the part posed as type c; p_c: the
classifier's probability of c. The classifier's arg-max is always a candidate, "not a block" (id 0) never. A part
of tightly packed blocks often shows too little of its outline for the classifier (one brick's end under another
looks like a shorter brick), while its depth points still tell the sizes apart: the fit of a too small type leaves
points unexplained, that of a too large one fills space the camera sees through.
"""

from __future__ import annotations

from dataclasses import field

import numpy as np

from posegrasp.config import settings, within


@settings
class TypeCheckConfig:
    """Which types a part is fitted as, and how the fit and the classifier are weighed
    (``perception.type_check``)."""

    #: Weight (m per nat) of the classifier's log-probability against the fit's score (0: the classifier decides).
    weight: float = field(default=0.001, metadata=within(0, 1))
    #: Types less probable than this are not fitted.
    min_prob: float = field(default=0.05, metadata=within(0, 1))
    #: At most this many types per part, the most probable first.
    max_types: int = field(default=4, metadata=within(1, 1000))
    #: After the depth fit's first grid steps, a type whose best ranked fit plus cost trails the part's best by more
    #: than this (m) is fitted no further (``perception.depth_fit.rivals``; inf: every type fitted to the end).
    steps_margin: float = field(default=0.001, metadata=within(0, float("inf")))
    #: Likewise after the depth fit's turns (m).
    turns_margin: float = field(default=0.0005, metadata=within(0, float("inf")))


def candidates(prob: np.ndarray, obj_ids: list[int], cfg: TypeCheckConfig) -> list[tuple[int, float]]:
    """The types (obj_id, p) a part with class probabilities ``prob`` (n,) (order ``obj_ids``) is fitted as, the most
    probable first; the arg-max alone when it is "not a block" (0) or the check is off."""
    order = [int(i) for i in np.argsort(-prob, kind="stable")]
    best = order[0]
    if obj_ids[best] == 0 or cfg.weight <= 0:
        return [(obj_ids[best], float(prob[best]))]
    picked = [i for i in order if obj_ids[i] != 0 and (i == best or prob[i] >= cfg.min_prob)][:cfg.max_types]
    return [(obj_ids[i], float(prob[i])) for i in picked]


def cost(prob: float, cfg: TypeCheckConfig) -> float:
    """The cost (m) of a type of classifier probability ``prob`` added to its fit score: -weight ln prob."""
    return -cfg.weight * float(np.log(max(prob, 1e-6)))


def choose(fit_scores: list[float], probs: list[float], cfg: TypeCheckConfig) -> int:
    """The index of the best candidate: the lowest ``fit_scores`` (m) less ``weight`` x ln ``probs``; the first on
    ties."""
    return int(np.argmin([s + cost(p, cfg) for s, p in zip(fit_scores, probs)]))


def best_per_part(parts: list[int], fit_scores: list[float], probs: list[float], cfg: TypeCheckConfig) -> list[int]:
    """Of fits j, each of part ``parts[j]`` posed as one of its candidate types (fit score ``fit_scores[j]`` (m), the
    classifier's probability ``probs[j]`` of that type), the index of each part's best (``choose``), in the order the
    parts first appear."""
    by_part: dict[int, list[int]] = {}
    for j, i in enumerate(parts):
        by_part.setdefault(i, []).append(j)
    return [js[choose([fit_scores[j] for j in js], [probs[j] for j in js], cfg)] for js in by_part.values()]
