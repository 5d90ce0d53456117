"""Every message the reference implementation builds in these tests matches protocol/schema.

An autouse fixture checks the metadata of each message encoded during a test (by the test, the
reference client or the reference server it talks to) against ``messages/<type>.json``
(SPEC §6.3.1) and fails the test that built an invalid one. Property tests (Hypothesis) are
left out: they feed arbitrary values to the codec on purpose. So is a test marked
``invalid_messages``, which builds out-of-schema messages on purpose (to check a receiver).
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from typing import Any

import pytest

from protocol import schema
from protocol.frames import Frame
from protocol.messages import Message, Version


@pytest.fixture(autouse=True)
def _messages_match_the_schemas(
    request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch
) -> Iterator[None]:
    function: Any = getattr(request.node, "function", None)
    if getattr(function, "is_hypothesis_test", False) or request.node.get_closest_marker(
        "invalid_messages"
    ):
        yield
        return
    violations: list[str] = []
    lock = threading.Lock()  # servers in threads encode too
    encode = Message.to_frame

    def checked(self: Message, version: Version) -> Frame:
        frame = encode(self, version)
        # As the receiver sees it: through JSON (tuples become lists).
        metadata = json.loads(json.dumps(frame.metadata))
        try:
            schema.validate_metadata(self.TYPE, metadata)
        except schema.SchemaViolation as exc:
            with lock:
                violations.append(str(exc))
        except schema.SchemaUnavailable:
            pass  # a test that hides jsonschema on purpose (test_schema.py imports it)
        return frame

    monkeypatch.setattr(Message, "to_frame", checked)
    yield
    if violations:
        pytest.fail(
            f"{len(violations)} message(s) built in this test do not match protocol/schema: "
            + "; ".join(sorted(set(violations))[:5])
        )
