"""The live view tells when its frame was taken (``X-Frame-Timestamp`` on frame.jpg), so that
a viewer can tell a new frame from the cached one and measure its age on arrival (the
console's bench, bench/console.py). Against the real server with the example cell."""

from __future__ import annotations

import time
from collections.abc import Iterator

import cv2
import numpy as np
import pytest
from console_server import Browserless, console_server

from vision_server.frontends.http import FRAME_TIMESTAMP_HEADER


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Browserless]:
    with console_server(tmp_path_factory.mktemp("cell")) as running:
        c = Browserless(running.url)
        assert c.login().status == 200
        yield c


def test_a_server_cameras_frame_carries_the_time_it_was_captured(client: Browserless) -> None:
    before = time.time()
    first = client.get("/api/cameras/qc/frame.jpg")  # no frame cached yet: a capture now
    after = time.time()
    assert first.status == 200
    taken = float(first.headers[FRAME_TIMESTAMP_HEADER])
    # Clock order, not a duration: the capture happened during the request.
    assert before <= taken <= after


def test_a_request_cameras_frame_carries_the_time_the_robot_sent_it(
    client: Browserless,
) -> None:
    image = np.full((768, 1024), 200, np.uint8)
    png = cv2.imencode(".png", image)[1].tobytes()
    before = time.time()
    assert client.get("/api/cameras/tool/frame.jpg").status == 404  # nothing sent yet
    tried = client.try_("cap_locate", {"source": "upload"}, png)
    assert tried.status == 200, tried.body
    shown = client.get("/api/cameras/tool/frame.jpg")  # the uploaded image, as a robot's
    assert shown.status == 200
    assert float(shown.headers[FRAME_TIMESTAMP_HEADER]) >= before
