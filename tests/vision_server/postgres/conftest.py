"""Fixtures of the PostgreSQL result log's tests: one private cluster per test session
(tests/helpers/postgres.py), a fresh database per test."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from postgres import Cluster, Unavailable, find_bindir


@pytest.fixture(scope="session")
def pg_cluster() -> Iterator[Cluster]:
    pytest.importorskip(
        "psycopg", reason="psycopg is not installed: pip install -e '.[test]' (extra postgres)"
    )
    try:
        cluster = Cluster(find_bindir())
    except Unavailable as exc:
        pytest.skip(f"no PostgreSQL server for the tests: {exc}")
    try:
        cluster.start()
        yield cluster
    finally:
        cluster.close()


@pytest.fixture
def pg_url(pg_cluster: Cluster) -> str:
    """The URL of an empty database of the session's cluster (which is running)."""
    return pg_cluster.create_database()
