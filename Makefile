# One entry point for people and CI. Everything installs into ./.venv.
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# Parallel test workers (2 cores here).
PYTEST_WORKERS ?= 2

.PHONY: install run test bench lint compose-check clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

# The main job: render the sample scenes with the reference renderer into ./out/
run: install
	$(BIN)/ibr render-local mirror_box -o out/mirror_box.png
	$(BIN)/ibr render-local cornell_box -o out/cornell_box.exr --indirect 16 --bounces 3
	$(BIN)/ibr render-local cornell_box -o out/cornell_box.png --indirect 16 --bounces 3

test: install
	$(BIN)/python -m pytest -n $(PYTEST_WORKERS) --timeout=900 -q tests

bench: install
	$(BIN)/python -m bench.raycast_throughput
	$(BIN)/python -m bench.mitsuba_crosscheck

lint: install
	$(BIN)/python -m ruff check api_schemas engine workers service samples tests bench

compose-check:
	docker-compose -f docker-compose.yml config -q

clean:
	rm -rf $(VENV) out
