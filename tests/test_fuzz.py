"""The fuzz harness (``tests/fuzz.py``): every file kind of a small dataset, weights folder, trials run folder, object set
and settings file mutated, and every reading command run on the mutated copy: one stderr line on refusal, no
traceback, no hang, no false OK, no score out of range, nothing already written changed.

``make test`` runs a fixed, seeded selection (``POSEGRASP_FUZZ_CASES``, default 26) covering every file kind and
command, and 24 hostile cases (``tests/fuzz_hostile.py``: file kinds, sizes, nesting, values, output paths, physics;
``POSEGRASP_FUZZ_HOSTILE``), on two workers; ``POSEGRASP_FUZZ=full`` runs 1000 mutations and 1200 hostile cases and
prints the counts and every failing case to stdout (``POSEGRASP_FUZZ_ONLY=N,M`` reruns cases N and M of a draw;
hostile cases are numbered from 100000).
"""

from __future__ import annotations

import os
import random

import pytest

import fuzz
import fuzz_hostile

FULL = os.environ.get("POSEGRASP_FUZZ") == "full"
N_CASES = int(os.environ.get("POSEGRASP_FUZZ_CASES", 1000 if FULL else 26))  # 26: one per file kind
SEED = int(os.environ.get("POSEGRASP_FUZZ_SEED", 0))
N_HOSTILE = int(os.environ.get("POSEGRASP_FUZZ_HOSTILE", 1200 if FULL else 24))  # 24: each generator 4 times


@pytest.fixture(scope="module")
def fuzzer(tmp_path_factory):
    work = tmp_path_factory.mktemp("fuzz")
    z = fuzz.Zygote()  # the corpus is built by a fork server of its own
    try:
        base = fuzz.build_corpus(work, lambda argv, cwd: z.run(argv, cwd, 600))
    finally:
        z.close()
    f = fuzz.Fuzzer(base, work, workers=2)
    yield f
    f.close()
    assert fuzz.tree_hashes(base) == f.base_hashes, "a command changed the shared corpus through a hard link"


def test_every_file_kind_and_command_is_drawn(fuzzer):
    cases = fuzz.draw_cases(fuzzer.base, N_CASES, SEED)
    kinds = set(fuzz.corpus_files(fuzzer.base))
    assert {c.kind for c in cases} == kinds
    assert {c.command for c in cases} == {c.name for c in fuzz.COMMANDS}
    assert kinds >= {k for c in fuzz.COMMANDS for k in c.kinds}, "a command reads a kind the corpus lacks"


def test_mutations_are_seeded(fuzzer):
    cases = fuzz.draw_cases(fuzzer.base, 40, SEED)
    assert cases == fuzz.draw_cases(fuzzer.base, 40, SEED)
    for c in cases:
        data = (fuzzer.base / c.rel).read_bytes()
        a = fuzz.mutate(random.Random(c.number), c.rel, c.kind, data)
        b = fuzz.mutate(random.Random(c.number), c.rel, c.kind, data)
        assert a == b, (c, a.what)


def test_fuzz(fuzzer):
    cases = fuzz.draw_cases(fuzzer.base, N_CASES, SEED)
    if os.environ.get("POSEGRASP_FUZZ_ONLY"):  # case numbers, comma-separated: rerun those of a report
        only = {int(n) for n in os.environ["POSEGRASP_FUZZ_ONLY"].split(",")}
        cases = [c for c in cases if c.number in only]
    progress = (lambda v: print(f"case {v.case.number} {v.category} {v.case.command} {v.case.rel} ({v.mutation}) "
                                f"{v.seconds:.1f}s", flush=True)) if FULL else None
    verdicts = fuzzer.run_cases(cases, keep_failures=FULL, progress=progress)
    report = fuzz.format_report(verdicts)
    print(report)
    assert not [v for v in verdicts if v.problem], report


def _only(cases: list) -> list:
    if os.environ.get("POSEGRASP_FUZZ_ONLY"):  # case numbers, comma-separated: rerun those of a report
        only = {int(n) for n in os.environ["POSEGRASP_FUZZ_ONLY"].split(",")}
        cases = [c for c in cases if c.number in only]
    return cases


def test_fuzz_hostile(fuzzer):
    cases = _only(fuzz_hostile.draw_hostile(fuzzer.base, N_HOSTILE, SEED, start=100000))
    assert len({c.generator for c in cases}) == len(fuzz_hostile.GENERATORS) or os.environ.get("POSEGRASP_FUZZ_ONLY")
    progress = (lambda v: print(f"hcase {v.case.number} {v.category} {v.case.generator}/{v.case.variant} "
                                f"{v.case.command} {v.mutation} {v.seconds:.1f}s", flush=True)) if FULL else None
    verdicts = fuzzer.run_cases(cases, keep_failures=FULL, progress=progress,
                                run=lambda c, z, keep: fuzz_hostile.run_hostile(fuzzer, c, z, keep))
    report = fuzz.format_report(verdicts)
    by_gen: dict[str, int] = {}
    for v in verdicts:
        by_gen[v.case.generator] = by_gen.get(v.case.generator, 0) + 1
    print(report.replace("by file kind", "by generator: " + ", ".join(f"{k} {n}" for k, n in sorted(by_gen.items()))
                         + "\nby file kind", 1))
    assert not [v for v in verdicts if v.problem], report
