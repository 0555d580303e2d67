# One entry point for people and CI. Everything installs into ./.venv.
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# Parallel test workers (2 cores here).
PYTEST_WORKERS ?= 2

.PHONY: install run demo render-local test test-fast bench lint compose-check clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

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

test: install
	$(BIN)/python -m pytest -n $(PYTEST_WORKERS) --dist loadfile --timeout=900 -q tests

# The everyday lane: every test not marked slow (no browser, no live multi-process stacks, no
# long convergence runs). CI runs everything (make test).
test-fast: install
	$(BIN)/python -m pytest -n $(PYTEST_WORKERS) --dist loadfile --timeout=900 -q -m "not slow" tests

bench: install
	$(BIN)/python -m bench.raycast_throughput
	$(BIN)/python -m bench.mitsuba_crosscheck

lint: install
	$(BIN)/python -m ruff check api_schemas engine producer workers service samples tests bench

compose-check:
	docker-compose -f docker-compose.yml config -q

clean:
	rm -rf $(VENV) out .ibr-data
