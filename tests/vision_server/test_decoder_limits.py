"""The second fence: OpenCV's decoders enforce the server's pixel limit themselves, so a header
parser and a decoder that disagree can never allocate beyond it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from vision_server import ServerSettings
from vision_server.process import decoder_limits

ROOT = Path(__file__).resolve().parents[2]

# The parser is made to lie (it reports 16x8 for a JPEG whose frame header says 3000x3000),
# then the image is decoded. Prints what happened and the process's peak RSS.
DISAGREE = """
import json, re, sys
if sys.argv[1] == "fenced":
    import vision_server  # sets OpenCV's limits before cv2 loads
    from vision_server import decoder_limits
    assert decoder_limits.loaded_limit() == 4096 * 4096
import protocol.images
from protocol import ImagePayload, array_from_payload
from protocol.errors import BadImage
from protocol.image_headers import ImageHeader
from tests.helpers.hostile_images import stray_byte_bomb

protocol.images.jpeg_header = lambda data, request_id=0: ImageHeader(16, 8, 1, 8)
before = int(re.search(r"VmHWM:\\s+(\\d+)", open("/proc/self/status").read())[1]) * 1024
try:
    array_from_payload(ImagePayload("jpeg", 0, 0, stray_byte_bomb(5000, 5000)), max_pixels=200)
    outcome = "decoded"
except BadImage as exc:
    outcome = str(exc)
hwm = int(re.search(r"VmHWM:\\s+(\\d+)", open("/proc/self/status").read())[1]) * 1024
print(json.dumps({"outcome": outcome, "hwm": hwm, "growth": hwm - before}))
"""


def _run(mode: str) -> dict[str, object]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("OPENCV_IO_MAX_IMAGE")}
    env["PYTHONPATH"] = str(ROOT)
    run = subprocess.run(
        [sys.executable, "-c", DISAGREE, mode],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    result: dict[str, object] = json.loads(run.stdout.splitlines()[-1])
    return result


def test_opencv_refuses_what_a_lying_parser_let_through() -> None:
    fenced = _run("fenced")
    assert "CV_IO_MAX_IMAGE_PIXELS" in str(fenced["outcome"]), fenced
    # Without the fence the same file is decoded (25 Mpx, then refused only by the shape check):
    # the control shows that the fence is what stopped it.
    unfenced = _run("unfenced")
    assert "decoder produced (5000, 5000)" in str(unfenced["outcome"]), unfenced
    # What the decode attempt added to each process's peak (the two import different modules,
    # so their baselines differ): the 25 MB decode happens only without the fence.
    assert int(str(fenced["growth"])) + 20 * 2**20 < int(str(unfenced["growth"]))


def test_the_default_fence_is_the_servers_default_limit() -> None:
    assert ServerSettings().max_image_pixels == decoder_limits.DEFAULT_MAX_IMAGE_PIXELS
    assert decoder_limits.opencv_environment(1000) == {
        "OPENCV_IO_MAX_IMAGE_PIXELS": "1000",
        "OPENCV_IO_MAX_IMAGE_WIDTH": "1000",
        "OPENCV_IO_MAX_IMAGE_HEIGHT": "1000",
    }


def test_an_operators_environment_is_kept_and_cv2_loads_after_it() -> None:
    code = (
        "import os, sys, vision_server\n"
        "from vision_server import decoder_limits as d\n"
        "print(d.loaded_limit(), os.environ.get('OPENCV_IO_MAX_IMAGE_WIDTH'), 'cv2' in sys.modules)"
    )
    env = {k: v for k, v in os.environ.items() if not k.startswith("OPENCV_IO_MAX_IMAGE")}
    env.update(PYTHONPATH=str(ROOT), OPENCV_IO_MAX_IMAGE_PIXELS="5000")
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, check=True
    )
    assert out.stdout.split() == ["5000", "None", "True"]


def test_ensure_without_argv_reports_a_mismatch_instead_of_re_executing() -> None:
    # In this (test) process cv2 may have loaded before vision_server: the limit is unknown or
    # the default; either way a different one cannot be applied without re-executing.
    assert decoder_limits.ensure(1234) is False
