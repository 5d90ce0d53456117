"""Every RESULT the golden corpus (test_inspections/) produces matches protocol/schema: its
metadata ``messages/result.json`` and its ``data`` the schema of its inspection type
(SPEC §6.3.1). The cases run in-process through the inspection service, as
``vision-server test-inspections`` runs them, with an overlay asked for; each reply is rendered
by the TCP front-end and taken as a client receives it: encoded, framed and decoded again."""

from __future__ import annotations

import asyncio
from collections import Counter
from pathlib import Path
from typing import Any

from protocol import (
    CellvisionError,
    FrameDecoder,
    ImageRole,
    MessageType,
    Result,
    schema,
)
from vision_server.commands.golden import Case, color_images, depth_frames, find_cases, load_case
from vision_server.commands.offline import file_request, image_payload, offline_service
from vision_server.frontends.tcp import result_message
from vision_server.inspections import INSPECTION_TYPES

CORPUS = Path(__file__).resolve().parents[2] / "test_inspections"


def _wire_metadata(result: Result) -> dict[str, Any]:
    """The RESULT's metadata as a client decodes it from the bytes."""
    decoder = FrameDecoder()
    decoder.feed(result.to_frame((1, 0)).serialize())
    frame = decoder.next_frame()
    assert frame is not None
    assert frame.type == MessageType.RESULT
    metadata: dict[str, Any] = frame.metadata
    return metadata


def _results(case: Case) -> list[Result]:
    """Each image of the case through the service, rendered as the TCP front-end's RESULT;
    images that end in ERROR are left out (an ERROR has no data; the golden runner checks
    those expectations)."""
    service = offline_service(
        case.inspection, case.camera, case.base_dir, config_hash=case.config_hash
    )

    async def run_all() -> list[Result]:
        out = []
        try:
            for request_id, name in enumerate(color_images(case), start=1):
                color = case.images_dir / name
                depth = []
                if case.inspection.uses_depth:
                    depth = [image_payload(p, ImageRole.DEPTH) for p in depth_frames(color)]
                colour = image_payload(color, ImageRole.COLOR)
                request = file_request(case.inspection.name, colour, depth, overlay=".png")
                try:
                    reply = await service.inspect(request)
                except CellvisionError:
                    continue
                out.append(result_message(request_id, reply))
        finally:
            service.close()
        return out

    return asyncio.run(run_all())


def test_every_configurable_inspection_type_has_a_data_schema() -> None:
    assert set(INSPECTION_TYPES) == set(schema.DATA_TYPES)


def test_every_result_of_the_golden_corpus_matches_the_schemas() -> None:
    checked: Counter[str] = Counter()
    verdicts: Counter[str] = Counter()
    overlays = 0
    for directory in find_cases([CORPUS]):
        case = load_case(directory)
        if case.skip is not None:
            continue
        kind = case.inspection.type
        for result in _results(case):
            metadata = _wire_metadata(result)
            schema.validate_metadata(MessageType.RESULT, metadata)
            schema.validate_data(kind, metadata["data"])
            checked[kind] += 1
            verdicts[metadata["verdict"]] += 1
            overlays += len(metadata.get("images", []))
    # Every type, both verdicts and overlay descriptors really went through the schemas.
    assert set(checked) == set(schema.DATA_TYPES), checked
    assert sum(checked.values()) >= 40, checked
    assert verdicts["pass"] > 0
    assert verdicts["fail"] > 0
    assert overlays > 0
