"""The fuzz harness (``tests/fuzz.py``): every file kind of a small dataset, weights folder, trials run folder, object set
and settings file mutated, and every reading command run on the mutated copy: one stderr line on refusal, no
traceback, no hang, no false OK, no score out of range, nothing already written changed.

``make test`` runs a fixed, seeded selection (``POSEGRASP_FUZZ_CASES``, default 26) covering every file kind and
command; ``POSEGRASP_FUZZ=full`` runs 1000 cases (``POSEGRASP_FUZZ_CASES`` to change) on two workers and prints the
counts and every failing case to stdout (``POSEGRASP_FUZZ_ONLY=N,M`` reruns cases N and M of that draw).
"""

from __future__ import annotations

import os
import random

import pytest

import fuzz

FULL = os.environ.get("POSEGRASP_FUZZ") == "full"
N_CASES = int(os.environ.get("POSEGRASP_FUZZ_CASES", 1000 if FULL else 26))  # 26: one per file kind
SEED = int(os.environ.get("POSEGRASP_FUZZ_SEED", 0))


@pytest.fixture(scope="module")
def fuzzer(tmp_path_factory):
    work = tmp_path_factory.mktemp("fuzz")
    z = fuzz.Zygote()  # the corpus is built by a fork server of its own
    try:
        base = fuzz.build_corpus(work, lambda argv, cwd: z.run(argv, cwd, 600))
    finally:
        z.close()
    f = fuzz.Fuzzer(base, work, workers=2 if FULL else 1)
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
