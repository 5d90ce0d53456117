"""Copies of the image path (issue 16, part 3), counted with buffer tracking over loopback:
an INSPECT of a 1024x768 gray image from the real client to the real server, and its RESULT
with a PNG overlay back (tests/helpers/copies.py does the counting)."""

from __future__ import annotations

import pytest
from copies import CopyCount, measure_copies
from loopback import run

from wireio import READ_BUFFER_BYTES


@pytest.fixture(scope="module")
def counted() -> CopyCount:
    # Three requests on one connection; the last is counted (a steady connection).
    return run(measure_copies(1024, 768, rounds=3), timeout_s=120.0)


def test_the_client_hands_its_transport_views_of_the_callers_array(counted: CopyCount) -> None:
    assert counted.client_views_share_array
    assert not counted.client_joined  # no b"".join of header and pixels


def test_the_server_copies_the_image_at_most_once_into_the_array_the_inspection_reads(
    counted: CopyCount,
) -> None:
    # The inspection's array is a view of the frame body the socket was read into ...
    assert counted.server_array_shares_body
    # ... and only the first bytes, read with the header, were copied into that body (once).
    assert counted.server_body_copied <= READ_BUFFER_BYTES
    assert counted.server_copies < 0.1


def test_the_overlay_comes_back_the_same_way(counted: CopyCount) -> None:
    assert counted.overlay_bytes > 4 * READ_BUFFER_BYTES  # large enough to be read directly
    assert counted.server_overlay_view  # the encoded PNG itself went to the transport
    assert counted.client_overlay_in_body  # the client's overlay views its frame body
    assert counted.client_body_copied <= READ_BUFFER_BYTES
