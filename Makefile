# The two commands: `make demo` (the main job on the simulated cell) and `make test` (the suite).
# Both bootstrap a local .venv and the system library libzbar0 themselves.
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: bootstrap test lint typecheck pytest wheel-check demo bench clean

bootstrap:
	@VENV=$(VENV) ./scripts/bootstrap.sh

lint: bootstrap
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .

typecheck: bootstrap
	$(PY) -m mypy

pytest: bootstrap
	$(PY) -m pytest

# The server as the Dockerfile runs it, from the built wheel (Docker itself is not available).
wheel-check: bootstrap
	PYTHON=$(PY) ./scripts/check_wheel.sh

test: lint typecheck wheel-check pytest

demo: bootstrap
	$(PY) -m robot_client.demo

bench: bootstrap
	$(PY) -m bench

clean:
	rm -rf $(VENV) build dist *.egg-info .mypy_cache .pytest_cache .ruff_cache
