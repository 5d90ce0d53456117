# The two commands: `make demo` (the main job on the simulated cell) and `make test` (the suite).
# Both bootstrap a local .venv and the system library libzbar0 themselves.
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: bootstrap test lint typecheck pytest wheel-check container-test demo bench soak clean

bootstrap:
	@VENV=$(VENV) ./scripts/bootstrap.sh

lint: bootstrap
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .

typecheck: bootstrap
	$(PY) -m mypy

# One pytest worker per core (pytest-xdist), each test file in one worker (its module fixtures
# start once): much of the suite waits on servers, browsers and processes it starts, and the
# whole suite must stay under 15 minutes on a 2-core machine. PYTEST_WORKERS=0: in this process.
PYTEST_WORKERS ?= auto
pytest: bootstrap
	$(PY) -m pytest -n $(PYTEST_WORKERS) --dist loadfile

# The server from the built wheel, outside any container.
wheel-check: bootstrap
	PYTHON=$(PY) ./scripts/check_wheel.sh

# The image built and run with rootful podman (also part of `make test`, through pytest); it
# sets podman up with scripts/container_setup.sh and skips, naming why, where it cannot.
container-test: bootstrap
	$(PY) -m pytest tests/test_container.py

test: lint typecheck wheel-check pytest

# `make demo STAY=1` keeps the server and its web console up after the task (Ctrl-C stops it);
# `make demo PACE=2` waits 2 s after each step, to follow the cell live in the console.
# `make demo LINE=1`: a robot controller (URScript's rules) picks through the line protocol alone.
demo: bootstrap
	$(PY) -m robot_client.demo $(if $(STAY),--stay) $(if $(PACE),--pace $(PACE)) $(if $(LINE),--via line)

bench: bootstrap
	$(PY) -m bench

# The long attack soak (issue 13): every hole as a bounded phase against a `serve` process, 10
# rounds; figures in soak-attack.json (docs/bench/reliability.md). `make test` runs the short
# form through tests/test_reliability.py.
soak: bootstrap
	$(PY) scripts/attack.py --json soak-attack.json

clean:
	rm -rf $(VENV) build dist *.egg-info .mypy_cache .pytest_cache .ruff_cache
