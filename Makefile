# Set-up-to-result targets: `make demo`, `make test` (every test, as CI runs it) and `make test-fast` (the
# everyday tier: the tests not marked slow). Each builds .venv from scratch when needed.
SHELL := /bin/bash
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
export MUJOCO_GL ?= egl
export PYOPENGL_PLATFORM ?= egl

.PHONY: demo test test-fast setup sysdeps clean

setup: $(STAMP)

# Mesa EGL for headless rendering; Chromium for the test that opens the trial report in a real browser.
sysdeps:
	@if ! dpkg -s libegl1 libegl-mesa0 libgl1-mesa-dri chromium >/dev/null 2>&1; then \
	  echo "Installing Mesa EGL (software rendering) and Chromium"; \
	  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libegl1 libegl-mesa0 libgl1-mesa-dri chromium >/dev/null; \
	fi

$(STAMP): pyproject.toml setup.py $(wildcard perception/depth_fit/_*.[ch] datagen/_*.c) constraints.txt | sysdeps
	@test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q torch==2.13.0
	@# OpenCV's plain and contrib wheels share the cv2 folder: a .venv that holds the plain one gets the contrib one alone
	@if $(BIN)/pip show -q opencv-python-headless 2>/dev/null; then $(BIN)/pip uninstall -y -q opencv-python-headless opencv-contrib-python-headless; fi
	$(BIN)/pip install -q -c constraints.txt -e '.[test,ray]'
	$(BIN)/pip install -q -c constraints.txt --no-deps pyrender==0.1.45
	@touch $(STAMP)

demo: setup sysdeps
	$(BIN)/posegrasp trials --episodes 20 --seed 0 --perception model --workers 2 --out demo_out
	@echo "Open demo_out/report.html (episodes.jsonl and summary.json beside it)"

# The record-for-record comparison of a model campaign with its replay runs alone, in one process.
ALONE_TESTS := tests/test_captures.py
XDIST := -n 2 --dist loadfile

# The tests write bytecode caches even where the environment asks for none: without them pytest rewrites every test
# module's asserts again in each of its processes (5 s of CPU each).
test test-fast: export PYTHONDONTWRITEBYTECODE :=

# The suites run on two worker processes (pytest-xdist), a test file to a worker so that its fixtures are built
# once; the session fixtures of many files (the tiny dataset, its trained run) once for both. xdist hands the files
# out in the order given: the longest first, so that neither worker is left waiting on one at the end. The fault
# tests (full disks on a mounted tmpfs, Ctrl-C to a command's own process group, the fuzz harness; mostly slow)
# run their commands in child processes and draw their datasets there too, so they share the workers with the rest.
FAULT_TESTS := $(addprefix tests/,test_full_disk.py test_interrupt.py test_fuzz.py)
LONGEST_TESTS := $(addprefix tests/,test_closed_loop.py test_hardening_runs.py test_tray.py test_plugins.py \
	test_workers.py test_ray.py test_depth_icp.py perception/test_estimator.py test_trials.py test_tasks.py \
	perception/test_cli.py test_bin_pick.py)
test: setup sysdeps
	$(BIN)/python -m pytest -q $(XDIST) $(FAULT_TESTS) $(LONGEST_TESTS) tests $(addprefix --ignore=,$(ALONE_TESTS))
	$(BIN)/python -m pytest -q $(ALONE_TESTS)

test-fast: setup sysdeps
	$(BIN)/python -m pytest -q $(XDIST) -m "not slow" $(LONGEST_TESTS) tests

clean:
	rm -rf $(VENV) demo_out
