# One entry point for people and CI. Everything installs into ./.venv.
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
# Two installs, each remembered by a stamp: the runtime (what `make run` needs: the service, its
# workers and the CLI) and, on top of it, the development extras of pyproject.toml's `dev`
# (pytest, Mitsuba, Playwright, moto, mypy, ruff, ...) that the tests, benchmarks and lint need.
# Both are redone when pyproject.toml or constraints.txt (the versions the tests passed with, which
# every install keeps to) changes; `make test` after `make run` only adds the extras.
RUNTIME_STAMP := $(VENV)/.installed-runtime
DEV_STAMP := $(VENV)/.installed-dev
# Parallel test workers, one per core here. Three were no faster on a fresh clone (902 s of pytest,
# against 796 s and 930 s with two in runs on either side of it): the kernels' numba threads and
# Mitsuba already use both cores.
PYTEST_WORKERS ?= 2
# Each worker takes whole test files (--dist loadfile) in the order tests/conftest.py sets: files
# with slow tests first, so the run does not end with one worker alone on a long file. The files
# that share a live stack (tests/e2e/, the *_cli_live.py CLI tests) go to one worker as one unit
# (tests/conftest.py's scheduler), which starts that stack once.
PYTEST_DIST := -n $(PYTEST_WORKERS) --dist loadfile --no-loadscope-reorder

.PHONY: install install-dev run demo render-local warm-cache test test-fast bench lint compose-check clean

$(RUNTIME_STAMP): pyproject.toml constraints.txt
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c constraints.txt -e .
	touch $(RUNTIME_STAMP)

$(DEV_STAMP): $(RUNTIME_STAMP)
	$(BIN)/python -m pip install --quiet -c constraints.txt -e '.[dev]'
	touch $(DEV_STAMP)

install: $(RUNTIME_STAMP)

install-dev: $(DEV_STAMP)

# The main job: start the service with its embedded defaults (private Redis, local object
# store under ./.ibr-data), load the sample scenes, render one through the queue into
# out/mirror_box.png, and keep serving on http://127.0.0.1:8000 until Ctrl-C.
run: install
	$(BIN)/ibr up --data-dir .ibr-data --demo mirror_box --demo-output out/mirror_box.png

# The same, stopping after the demo render (for scripted checks).
demo: install
	$(BIN)/ibr up --data-dir .ibr-data --demo mirror_box --demo-output out/mirror_box.png --exit-after-demo

# Render sample scenes in-process with the reference renderer (no service).
render-local: install
	$(BIN)/ibr render-local mirror_box -o out/mirror_box_local.png
	$(BIN)/ibr render-local cornell_box -o out/cornell_box.exr --indirect 16 --bounces 3

# Fill numba's disk cache (engine/__pycache__/ibr-engine-<hash>) with the render kernels, the
# warm-up's two lanes in two processes at once: with a cold cache (a fresh clone) both pytest
# workers and the worker processes the tests start would compile the same kernels, each on one
# core. A warm cache loads in seconds. A failed step is not fatal here: the tests name it.
warm-cache: install
	@t0=$$(date +%s); \
	$(BIN)/python -m workers.warmup --lanes 2 --lane 0 --log-level WARNING >/dev/null & lane0=$$!; \
	$(BIN)/python -m workers.warmup --lanes 2 --lane 1 --log-level WARNING >/dev/null; s1=$$?; \
	wait $$lane0; s0=$$?; \
	echo "numba cache warm-up: $$(( $$(date +%s) - t0 )) s"; \
	[ $$s0 -eq 0 ] && [ $$s1 -eq 0 ] || echo "numba cache warm-up: a step failed (tests/test_worker_warmup.py names it)"

# --durations: the slowest tests of every full run are in its log, for the suite's time budget.
test: install-dev warm-cache
	$(BIN)/python -m pytest $(PYTEST_DIST) --timeout=900 --durations=30 -q tests

# The everyday lane: every test not marked slow (no browser, no live multi-process stacks, no
# long convergence runs). CI runs everything (make test).
test-fast: install-dev warm-cache
	$(BIN)/python -m pytest $(PYTEST_DIST) --timeout=900 -q -m "not slow" tests

bench: install-dev
	$(BIN)/python -m bench.raycast_throughput
	$(BIN)/python -m bench.mitsuba_crosscheck

lint: install-dev
	$(BIN)/python -m ruff check api_schemas ibr_client engine producer workers service samples tests bench

compose-check:
	docker-compose -f docker-compose.yml config -q

clean:
	rm -rf $(VENV) out .ibr-data
