"""Fixtures of the MQTT publisher's tests: Debian's mosquitto found (or installed) once per
session (tests/helpers/mosquitto.py), a private broker per test."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from mosquitto import Broker, Programs, Unavailable, find_programs


@pytest.fixture(scope="session")
def mosquitto_programs() -> Programs:
    pytest.importorskip(
        "aiomqtt", reason="aiomqtt is not installed: pip install -e '.[test]' (extra mqtt)"
    )
    try:
        return find_programs()
    except Unavailable as exc:
        pytest.skip(f"no MQTT broker for the tests: {exc}")


@pytest.fixture
def broker(mosquitto_programs: Programs) -> Iterator[Broker]:
    """A running private broker, anonymous clients allowed, on a free port of 127.0.0.1."""
    running = Broker(mosquitto_programs)
    try:
        running.start()
        yield running
    finally:
        running.close()
