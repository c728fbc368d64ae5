"""Shared test set-up: headless EGL rendering, idle OpenMP threads that sleep; tests that need a slow fixture are
slow."""

import os

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
# The test workers share the cores, so torch's OpenMP threads (here and in every command the tests run) wait for
# a thread whose core another worker holds: spinning meanwhile, as they do by default, makes a training step 10-20x
# slower on 2 cores; sleeping costs an idle machine about 15 % (bench/perception.py). The results are the same.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

#: Fixtures whose set-up alone is minutes on 2 cores: a test using one is marked slow (``make test-fast`` skips it).
SLOW_FIXTURES = {"tiny_run",  # four networks trained for a few steps on the tiny BOP dataset
                 "fuzzer"}  # the fuzz harness's corpus and its seeded cases

#: Modules of end-to-end fault runs (full disks, Ctrl-C, every command's refusals run as a user would): slow.
SLOW_MODULES = {"test_full_disk.py", "test_interrupt.py", "test_hardening_runs.py", "test_fuzz.py"}


@pytest.hookimpl(tryfirst=True)  # before ``-m`` deselects by mark
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if SLOW_FIXTURES & set(getattr(item, "fixturenames", ())) or item.path.name in SLOW_MODULES:
            item.add_marker(pytest.mark.slow)
