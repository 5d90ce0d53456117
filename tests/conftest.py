"""Shared fixtures: the repository and ../shared/data (present in CI, maybe not locally)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

# The machines are shared and noisy: no verdict may depend on how fast examples are made or run
# (Hypothesis's deadline and too_slow health check are timings). Tests' own settings add to this.
settings.register_profile("cellvision", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("cellvision")

REPO_ROOT = Path(__file__).resolve().parent.parent
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO_ROOT


@pytest.fixture(scope="session")
def qr_real_dir() -> Path:
    """The real QR photographs (../shared/data/qr_real); the test is skipped where absent."""
    path = SHARED_DATA / "qr_real"
    if not (path / "manifest.json").is_file():
        pytest.skip(f"real QR photographs not found at {path} (shared/ sits beside the clone)")
    return path


@pytest.fixture(scope="session")
def codes_real_dir() -> Path:
    """The real DataMatrix / Code 128 photographs (../shared/data/codes_real, or
    ``$CELLVISION_CODES_REAL``); the test is skipped where absent."""
    path = Path(os.environ.get("CELLVISION_CODES_REAL", SHARED_DATA / "codes_real"))
    if not (path / "manifest.json").is_file():
        pytest.skip(f"real code photographs not found at {path} (shared/ sits beside the clone)")
    return path
