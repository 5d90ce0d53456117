# The two commands: `make demo` (the main job on the simulated cell) and `make test` (the suite).
# Both bootstrap a local .venv and the system library libzbar0 themselves.
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: bootstrap test lint typecheck pytest demo bench clean

bootstrap:
	@VENV=$(VENV) ./scripts/bootstrap.sh

lint: bootstrap
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .

typecheck: bootstrap
	$(PY) -m mypy

pytest: bootstrap
	$(PY) -m pytest

test: lint typecheck pytest

demo: bootstrap
	$(PY) -m robot_client.demo

bench: bootstrap
	$(PY) -m bench

clean:
	rm -rf $(VENV) build dist *.egg-info .mypy_cache .pytest_cache .ruff_cache
