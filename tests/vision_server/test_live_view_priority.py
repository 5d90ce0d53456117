"""The console's live view is best effort: its JPEG encoding runs in a thread of its own at the
lowest priority, so that an open console slows its own frames on a saturated cell, not the
inspections (bench section 2d). Read from the thread itself, no timing."""

from __future__ import annotations

import os
import sys
import threading

import pytest
from loopback import run

from vision_server.frontends.http_live import LiveView
from vision_server.process import MAX_NICE
from vision_server.service import InspectionService, builtin_catalog


def _niceness() -> int:
    return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())


@pytest.mark.skipif(sys.platform != "linux", reason="per-thread niceness is Linux's")
def test_the_live_views_encoding_runs_at_the_lowest_priority() -> None:
    service = InspectionService(builtin_catalog())
    view = LiveView(service, max_fps=10.0)
    try:
        encoder = run(view._encode(_niceness))
    finally:
        view.close()
        service.close()
    assert encoder == MAX_NICE
    assert _niceness() < MAX_NICE  # the test's (the server's) own thread is untouched
