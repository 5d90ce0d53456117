"""The cell configuration: the example loads, every mistake is named with file, line and key
path, and docs/configuration.md lists exactly the keys the validator accepts."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from vision_server.cameras import (
    FolderCameraSettings,
    OpenCVCameraSettings,
    RecordingWriter,
    RequestCameraSettings,
    SimCameraSettings,
)
from vision_server.config import ConfigError, Node, load_config
from vision_server.inspections import (
    LocateInspection,
    PresenceInspection,
    QRInspection,
    QRPoseInspection,
)

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "cell.yaml"

MINIMAL = """\
cameras:
  tool:
    source: request
inspections:
  - name: bright
    type: presence
    camera: tool
    measure: mean_intensity
    min: 10
"""


def write(tmp_path: Path, text: str, name: str = "cell.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def error_of(tmp_path: Path, text: str) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        load_config(write(tmp_path, text))
    return info.value


def test_the_example_cell_loads_with_every_inspection_type() -> None:
    config = load_config(EXAMPLE)
    kinds = {type(i) for i in config.inspections}
    assert kinds == {LocateInspection, PresenceInspection, QRInspection, QRPoseInspection}
    assert isinstance(config.cameras["tool"], RequestCameraSettings)
    assert isinstance(config.cameras["qc"], SimCameraSettings)
    assert config.server.port == 7878
    assert config.results.store_images == "failures"
    assert re.fullmatch(r"[0-9a-f]{16}", config.config_hash)


def test_minimal_config_and_defaults(tmp_path: Path) -> None:
    config = load_config(write(tmp_path, MINIMAL))
    assert config.server.host == "127.0.0.1"
    assert config.results.path == tmp_path / "results.sqlite3"
    (inspection,) = config.inspections
    assert inspection.name == "bright"
    assert inspection.frames == 1


def test_the_error_names_file_line_item_and_key(tmp_path: Path) -> None:
    text = (
        MINIMAL
        + """\
  - name: cap_check
    type: presence
    camera: tool
    measure: dark_fraction
    threshold: high
    min: 0.2
"""
    )
    error = error_of(tmp_path, text)
    assert str(error) == (
        "cell.yaml:14 inspections[1] (name='cap_check') -> threshold: expected a number, got 'high'"
    )
    assert error.line == 14


@pytest.mark.parametrize(
    ("snippet", "expected"),
    [
        ("colour: red\n", r"cell.yaml:10 colour: unknown key"),
        ("server:\n  prot: 7000\n", r"cell.yaml:11 server -> prot: unknown key"),
        ("server:\n  port: 70000\n", r"server -> port: expected a port in 0..65535"),
        ("server:\n  tls: {cert: nope.pem, key: nope.key}\n", r"tls -> cert: no such file"),
        ("results:\n  store_images: some\n", r"store_images: expected one of none, failures"),
        ("server:\n  idle_timeout_s: 0\n", r"server -> idle_timeout_s: expected a number > 0"),
        (
            "server:\n  max_buffered_bytes: 1000\n",
            r"server -> max_buffered_bytes: max_buffered_bytes \(1000\) must be at least",
        ),
    ],
)
def test_top_level_and_server_mistakes(tmp_path: Path, snippet: str, expected: str) -> None:
    assert re.search(expected, str(error_of(tmp_path, MINIMAL + snippet)))


def test_the_servers_timeouts_and_byte_budget_are_configured(tmp_path: Path) -> None:
    snippet = (
        "server:\n  idle_timeout_s: 120\n  frame_timeout_s: 12.5\n  write_timeout_s: 9\n"
        "  handshake_timeout_s: 4\n  capture_timeout_s: 2\n  max_buffered_bytes: 100000000\n"
    )
    (tmp_path / "cell.yaml").write_text(MINIMAL + snippet)
    server = load_config(tmp_path / "cell.yaml").server
    assert (server.idle_timeout_s, server.frame_timeout_s, server.write_timeout_s) == (120, 12.5, 9)
    assert (server.handshake_timeout_s, server.capture_timeout_s) == (4, 2)
    assert server.max_buffered_bytes == 100_000_000
    assert server.welcome_limits()["idle_timeout_ms"] == 120_000


def test_duplicate_keys_are_refused(tmp_path: Path) -> None:
    error = error_of(tmp_path, "server:\n  port: 1\n  port: 2\n")
    assert "duplicate key 'port' (first on line 2)" in str(error)
    assert error.line == 3


MERGED = """\
cameras:
  tool: &camera
    source: request
    intrinsics: {width: 640, height: 480, fx: 500, fy: 500, cx: 320, cy: 240}
  tool2:
    <<: *camera
    depth: true
inspections:
  - &check
    name: left
    type: presence
    camera: tool
    measure: dark_fraction
    threshold: 60
    min: 0.2
  - <<: *check
    name: right
    roi: [300, 0, 40, 40]
"""


def test_merge_keys_are_accepted_and_override(tmp_path: Path) -> None:
    config = load_config(write(tmp_path, MERGED))
    left, right = config.inspections
    assert isinstance(right, PresenceInspection)
    assert (right.name, right.measure, right.threshold, right.low) == (
        "right",
        "dark_fraction",
        60,
        0.2,
    )
    assert right.common.roi == (300, 0, 40, 40)
    assert left.common.roi is None
    tool2 = config.cameras["tool2"]
    assert isinstance(tool2, RequestCameraSettings)
    assert tool2.depth is True
    assert tool2.intrinsics is not None
    assert tool2.intrinsics.width == 640


def test_an_error_in_a_merged_value_names_the_line_it_is_written_on(tmp_path: Path) -> None:
    # The anchored entry's threshold is bad: the error is on its line, for both entries.
    error = error_of(tmp_path, MERGED.replace("threshold: 60", "threshold: high"))
    assert error.line == 14
    assert "inspections[0] (name='left') -> threshold" in str(error)
    # A bad key written beside the merge key is on its own line.
    error = error_of(tmp_path, MERGED.replace("    name: right\n", "    name: right\n    mn: 1\n"))
    assert error.line == 18
    assert "inspections[1] (name='right') -> mn: unknown key" in str(error)
    # A merged camera's bad value is reported where it is written, under the merging name.
    text = MERGED.replace("    depth: true\n", "    depth: true\n    fps: 3\n")
    error = error_of(tmp_path, text)
    assert "cameras -> tool2 -> fps: unknown key" in str(error)
    assert error.line == 8


@pytest.mark.parametrize(
    "text",
    ["a: &x [*x]\n", "a: &x\n  <<: *x\n", "a: &x {b: *x}\n"],
)
def test_recursive_aliases_are_refused(tmp_path: Path, text: str) -> None:
    assert "recursive" in str(error_of(tmp_path, text))


def test_aliases_that_expand_without_end_are_refused(tmp_path: Path) -> None:
    lines = ["a0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    for i in range(1, 7):
        lines.append(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]")
    error = error_of(tmp_path, "\n".join(lines) + "\n")
    assert "once aliases are expanded" in str(error)


def test_invalid_yaml_names_the_line(tmp_path: Path) -> None:
    error = error_of(tmp_path, "server:\n  port: [1, 2\n")
    assert str(error).startswith("cell.yaml:")
    assert "invalid YAML" in str(error)


@pytest.mark.parametrize(
    ("camera", "expected"),
    [
        ("{source: usb}", r"cameras -> tool -> source: expected one of request, opencv"),
        ("{source: request, dpeth: true}", r"cameras -> tool -> dpeth: unknown key"),
        ("{source: opencv}", r"cameras -> tool: missing required key 'device'"),
        ("{source: opencv, device: 0, fps: -3}", r"cameras -> tool: fps must be"),
        (
            "{source: request, intrinsics: {width: 640, height: 480, fx: 500, fy: 500, cx: 1}}",
            r"intrinsics: missing required key 'cy'",
        ),
        (
            "{source: request, intrinsics: {width: 640, height: 480, fx: -5, fy: 500, cx: 1, "
            "cy: 2}}",
            r"intrinsics: fx",
        ),
        ("{source: folder, path: /x, glob: ../../*.png}", r"glob"),
    ],
)
def test_camera_mistakes(tmp_path: Path, camera: str, expected: str) -> None:
    text = MINIMAL.replace("  tool:\n    source: request\n", f"  tool: {camera}\n")
    assert re.search(expected, str(error_of(tmp_path, text)))


def test_camera_sources_become_their_settings(tmp_path: Path) -> None:
    text = (
        MINIMAL
        + """\
  - {name: replay_check, type: presence, camera: replay, measure: mean_intensity, max: 200}
"""
        + """\
""".join(["", ""])
    )
    text = text.replace(
        "cameras:\n",
        "cameras:\n  usb: {source: opencv, device: /dev/video0, width: 1024, height: 768, "
        "fps: 30}\n  replay: {source: folder, path: images, glob: '*.png', mode: once}\n",
    )
    (tmp_path / "images").mkdir()
    cv2.imwrite(str(tmp_path / "images" / "f0.png"), np.zeros((8, 8), np.uint8))
    config = load_config(write(tmp_path, text))
    usb = config.cameras["usb"]
    assert isinstance(usb, OpenCVCameraSettings)
    assert (usb.device, usb.width, usb.fps) == ("/dev/video0", 1024, 30.0)
    replay = config.cameras["replay"]
    assert isinstance(replay, FolderCameraSettings)
    assert replay.path == Path("images")
    assert replay.mode == "once"


@pytest.mark.parametrize(
    ("inspection", "expected"),
    [
        ("{name: a, type: locate, camera: nope, method: circle}", r"no camera named 'nope'"),
        ("{name: a, type: scan, camera: tool}", r"type: expected one of locate, presence"),
        ("{name: bright, type: qr, camera: tool}", r"name 'bright' is already used"),
        ("{name: 'a b', type: qr, camera: tool}", r"bad name 'a b'"),
        ("{name: a, type: qr, camera: tool, roi: [0, 0, -5, 10]}", r"roi: ROI"),
        ("{name: a, type: qr, camera: tool, expect: {regex: '('}}", r"bad regular expression"),
        ("{name: a, type: presence, camera: tool, measure: mean_intensity}", r"needs min, max"),
        (
            "{name: a, type: presence, camera: tool, measure: template_score, min: 0.5}",
            r"needs a template image",
        ),
        (
            "{name: a, type: presence, camera: tool, measure: mean_intensity, min: 5, max: 1}",
            r"min \(5.0\) is above max",
        ),
        ("{name: a, type: locate, camera: tool, method: circle}", r"missing required key 'circle'"),
        (
            "{name: a, type: locate, camera: tool, method: circle, circle: {min_radius_px: 5}}",
            r"missing required key 'max_radius_px'",
        ),
        (
            "{name: a, type: locate, camera: tool, method: circle, circle: {min_radius_px: 5, "
            "max_radius_px: 9, edge_sigma_px: 7}}",
            r"edge_sigma_px \(7\) is above max_edge_sigma_px \(6\)",
        ),
        (
            "{name: a, type: locate, camera: tool, method: circle, circle: {min_radius_px: 5, "
            "max_radius_px: 9, edge_sigma_px: sharp}}",
            r"circle -> edge_sigma_px: .*sharp",
        ),
        (
            "{name: a, type: locate, camera: tool, method: circle, circle: {min_radius_px: 5, "
            "max_radius_px: 9, rays: 8}}",
            r"circle -> rays: expected 16\.\.3600 rays",
        ),
        (
            "{name: a, type: locate, camera: tool, method: circle, circle: {min_radius_px: 5, "
            "max_radius_px: 9, min_edge_contrast: 300}}",
            r"circle -> min_edge_contrast: expected a grey-level step",
        ),
        (
            "{name: a, type: locate, camera: tool, method: circle, circle: {min_radius_px: 5, "
            "max_radius_px: 9, centre: centroid}}",
            r"circle -> centre: expected one of edge, moments",
        ),
        (
            "{name: a, type: locate, camera: tool, method: blob, blob: {}, circle: {}}",
            r"'circle' options given, but method is 'blob'",
        ),
        (
            "{name: a, type: locate, camera: tool, method: template, template: {image: no.png}}",
            r"cannot read the template image",
        ),
        ("{name: a, type: qr_pose, camera: tool}", r"camera 'tool' gets no depth"),
        ("{name: a, type: qr, camera: tool, thershold: 3}", r"thershold: unknown key"),
    ],
)
def test_inspection_mistakes(tmp_path: Path, inspection: str, expected: str) -> None:
    error = error_of(tmp_path, MINIMAL + f"  - {inspection}\n")
    assert re.search(expected, str(error)), str(error)
    assert error.line is not None


# ----------------------------------------------------------------- valid means it can work

CELL = """\
cameras:
  tool:
    source: request
    intrinsics: {width: 640, height: 480, fx: 500, fy: 500, cx: 320, cy: 240}
  replay: {source: folder, path: frames, glob: '*.png'}
inspections:
  - name: caps
    type: locate
    camera: tool
    roi: [0, 0, 640, 480]
    method: circle
    min_score: 0.5
    circle: {min_radius_px: 10, max_radius_px: 20}
  - name: magnet
    type: presence
    camera: replay
    measure: blob_count
    threshold: 60
    min: 1
"""


def check_config(path: Path) -> subprocess.CompletedProcess[str]:
    """``vision-server check-config PATH --json`` as a user runs it."""
    return subprocess.run(
        [sys.executable, "-m", "vision_server", "check-config", str(path), "--json"],
        cwd=path.parent,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


@pytest.fixture
def cell_dir(tmp_path: Path) -> Path:
    (tmp_path / "frames").mkdir()
    cv2.imwrite(str(tmp_path / "frames" / "f0.png"), np.zeros((48, 64), np.uint8))
    textured = np.zeros((30, 30), np.uint8)
    cv2.circle(textured, (15, 15), 8, 255, -1)
    cv2.imwrite(str(tmp_path / "cap.png"), textured)
    cv2.imwrite(str(tmp_path / "flat.png"), np.full((30, 30), 128, np.uint8))
    return tmp_path


@pytest.mark.parametrize(
    ("old", "new", "line", "expected"),
    [
        # a folder camera whose folder does not exist, or whose glob matches nothing
        (
            "path: frames,",
            "path: framez,",
            5,
            r"cameras -> replay -> path: the folder \S*framez does not exist",
        ),
        (
            "glob: '*.png'",
            "glob: '*.jpg'",
            5,
            r"cameras -> replay -> glob: no file in \S*frames matches '\*.jpg'",
        ),
        ("glob: '*.png'", "glob: '*.png', depth_glob: '*.depth.png'", 5, r"depth_glob: no file in"),
        # an ROI outside the camera's declared size
        (
            "roi: [0, 0, 640, 480]",
            "roi: [600, 0, 64, 48]",
            10,
            r"inspections\[0\] \(name='caps'\) -> roi: ROI \[u=600, v=0, width=64, height=48\] "
            r"reaches past the 640x480 image of camera 'tool' \(its intrinsics\)",
        ),
        # a score outside its method's range (circle scores are fractions)
        (
            "min_score: 0.5",
            "min_score: 20",
            12,
            r"min_score 20 is out of range for method circle: its score is the fraction",
        ),
        # presence ranges, and keys the measure does not use
        (
            "    min: 1\n",
            "    min: 1\n    max: -1\n",
            20,
            r"max -1 is out of range for measure blob_count",
        ),
        (
            "measure: blob_count\n    threshold: 60\n    min: 1\n",
            "measure: dark_fraction\n    threshold: 60\n    min: 20\n",
            19,
            r"min 20 is out of range for measure dark_fraction: its value is a fraction",
        ),
        (
            "measure: blob_count\n    threshold: 60",
            "measure: mean_intensity\n    threshold: 60",
            18,
            r"threshold is not used by measure mean_intensity",
        ),
        (
            "threshold: 60",
            "threshold: 60\n    polarity: light",
            19,
            r"polarity: expected one of dark, bright",
        ),
    ],
)
def test_check_config_refuses_what_cannot_work(
    cell_dir: Path, old: str, new: str, line: int, expected: str
) -> None:
    assert old in CELL
    path = write(cell_dir, CELL.replace(old, new))
    done = check_config(path)
    assert done.returncode == 2, done.stdout
    report = json.loads(done.stdout)
    assert report["valid"] is False
    error = report["error"]  # the one error shape of --json, with line and key path
    assert error["kind"] == "usage"
    assert error["line"] == line
    assert re.search(expected, error["message"]), error["message"]
    assert error["message"].startswith(f"cell.yaml:{line} "), error["message"]


def test_check_config_accepts_the_working_cell_and_merge_keys(cell_dir: Path) -> None:
    done = check_config(write(cell_dir, CELL))
    assert done.returncode == 0, done.stdout + done.stderr
    assert json.loads(done.stdout)["inspections"]
    merged = CELL.replace("  - name: caps\n", "  - &caps\n    name: caps\n") + (
        "  - <<: *caps\n    name: caps_right\n    roi: [320, 0, 320, 480]\n"
    )
    done = check_config(write(cell_dir, merged))
    assert done.returncode == 0, done.stdout + done.stderr
    names = [i["name"] for i in json.loads(done.stdout)["inspections"]]
    assert names == ["caps", "magnet", "caps_right"]


@pytest.mark.parametrize(
    ("inspection", "expected"),
    [
        (
            "{name: t, type: locate, camera: tool, method: template, template: {image: flat.png}}",
            r"template -> image: the template image 'flat.png' is one flat grey",
        ),
        (
            "{name: t, type: locate, camera: tool, method: template, roi: [0, 0, 20, 20], "
            "template: {image: cap.png}}",
            r"the 30x30 template 'cap.png' is larger than the 20x20 ROI",
        ),
        (
            "{name: t, type: presence, camera: tool, measure: template_score, min: 0.5, "
            "roi: [0, 0, 20, 40], template: cap.png}",
            r"template: the 30x30 template \S+ is larger than the 20x40 ROI",
        ),
        (
            "{name: t, type: presence, camera: tool, measure: template_score, min: 2, "
            "template: cap.png}",
            r"min 2 is out of range for measure template_score: its value is a normalised",
        ),
        (
            "{name: t, type: locate, camera: tool, method: template, min_score: 1.5, "
            "template: {image: cap.png}}",
            r"min_score 1.5 is out of range for method template",
        ),
        (
            "{name: t, type: locate, camera: tool, method: blob, min_score: -1, blob: {}}",
            r"min_score -1 is out of range for method blob: its score is the blob's area",
        ),
        (
            "{name: t, type: locate, camera: tool, method: blob, "
            "blob: {min_area_px: 50, max_area_px: 10}}",
            r"max_area_px \(10\) is below min_area_px \(50\)",
        ),
        (
            "{name: t, type: locate, camera: tool, method: template, "
            "template: {image: cap.png, angle_min: -4, angle_max: 4}}",
            r"more than a full turn",
        ),
        (
            "{name: t, type: locate, camera: tool, method: template, "
            "template: {image: cap.png, angle_max: 1, angle_step: 0.0001}}",
            r"10001 rotations per request",
        ),
        (
            "{name: t, type: locate, camera: tool, method: template, "
            "template: {image: cap.png, scale_min: 1.1, scale_max: 0.9}}",
            r"scale_max \(0.9\) is below scale_min \(1.1\)",
        ),
        (
            "{name: t, type: locate, camera: tool, method: template, "
            "template: {image: cap.png, scale_min: 0.3}}",
            r"scale_min.*expected a scale \(part size / template size\) in 0.5..2, got 0.3",
        ),
        (
            "{name: t, type: locate, camera: tool, method: template, "
            "template: {image: cap.png, angle_max: 1, angle_step: 0.01, scale_min: 0.9, "
            "scale_max: 1.1, scale_step: 0.005}}",
            r"101 rotations x 41 scales = 4141 poses per request: more than 3600",
        ),
        (
            "{name: t, type: presence, camera: tool, measure: mean_intensity, min: 300}",
            r"min 300 is out of range for measure mean_intensity: its value is a grey level",
        ),
        (
            "{name: t, type: presence, camera: tool, measure: edge_density, max: 0.5, "
            "min_blob_area: 3}",
            r"min_blob_area is not used by measure edge_density",
        ),
        (
            "{name: t, type: presence, camera: usb, measure: edge_density, max: 0.5, "
            "roi: [0, 0, 400, 300]}",
            r"reaches past the 320x240 image of camera 'usb' \(its width and height\)",
        ),
    ],
)
def test_parameters_outside_their_range_are_refused(
    cell_dir: Path, inspection: str, expected: str
) -> None:
    text = CELL.replace(
        "cameras:\n", "cameras:\n  usb: {source: opencv, device: 0, width: 320, height: 240}\n"
    )
    error = error_of(cell_dir, text + f"  - {inspection}\n")
    assert re.search(expected, str(error)), str(error)
    assert error.line == 21


def test_blob_count_counts_bright_blobs_with_polarity_bright(cell_dir: Path) -> None:
    # Three bright specks on a dark plate: `dark` (the default) counts the plate as one blob.
    image = np.full((48, 64), 20, np.uint8)
    for u in (10, 30, 50):
        cv2.circle(image, (u, 24), 4, 230, -1)
    cv2.imwrite(str(cell_dir / "specks.png"), image)
    text = CELL.replace("min: 1\n", "min: 3\n    polarity: bright\n    min_blob_area: 10\n")
    write(cell_dir, text)

    def run() -> dict[str, Any]:
        done = subprocess.run(
            [
                sys.executable,
                "-m",
                "vision_server",
                "run",
                "--config",
                "cell.yaml",
                "magnet",
                "--image",
                "specks.png",
                "--json",
            ],
            cwd=cell_dir,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
        result: dict[str, Any] = json.loads(done.stdout)
        return result

    bright = run()
    assert bright["verdict"] == "pass"
    assert bright["data"]["value"] == 3.0
    write(cell_dir, text.replace("    polarity: bright\n", ""))
    dark = run()
    assert dark["verdict"] == "fail"
    assert dark["data"]["value"] == 1.0


def test_template_paths_resolve_against_the_config_file(tmp_path: Path) -> None:
    (tmp_path / "templates").mkdir()
    template = np.zeros((20, 20), np.uint8)
    cv2.circle(template, (10, 10), 6, 255, -1)
    cv2.imwrite(str(tmp_path / "templates" / "cap.png"), template)
    text = MINIMAL + (
        "  - {name: t, type: locate, camera: tool, method: template,\n"
        "     template: {image: templates/cap.png, angle_min: -0.5, angle_max: 0.5}}\n"
    )
    config = load_config(write(tmp_path, text))
    inspection = config.inspections[1]
    assert isinstance(inspection, LocateInspection)
    assert inspection.options["template"].shape == (20, 20)
    assert inspection.options["angle_range"] == (-0.5, 0.5)


# ----------------------------------------------------------------------------- the docs

DOC = ROOT / "docs" / "configuration.md"


def documented_keys() -> dict[str, set[str]]:
    """Heading -> the keys in the first column of its table."""
    sections: dict[str, set[str]] = {}
    heading = ""
    for line in DOC.read_text(encoding="utf-8").splitlines():
        if line.startswith("#"):
            heading = line.lstrip("#").strip()
            continue
        match = re.match(r"\| `([a-z_]+)` \|", line)
        if match and heading:
            sections.setdefault(heading, set()).add(match.group(1))
    return sections


def test_docs_list_exactly_the_keys_the_validator_reads(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every branch of the validator is exercised; the keys it looks at (present or not) are
    compared with the tables of docs/configuration.md."""
    read: dict[str, set[str]] = {}
    original_take = Node.take

    def section(node: Node) -> str:
        path = node.path
        if path[:1] == ("server",):
            return "server.tls" if path[1:] == ("tls",) else "server"
        if path[:1] == ("results",):
            return "results"
        if path[:1] == ("line",):
            return "line"
        if path[:1] == ("modbus",):
            return "modbus"
        if path[:1] == ("mqtt",):
            return "mqtt.tls" if path[1:] == ("tls",) else "mqtt"
        if path[:1] == ("inspections",) and path[2:3] == ("output",):
            if len(path) == 3:
                return "inspections.output"
            return "output.fields" if path[3] == "fields" else "top"  # scale: any field name
        if path[:1] == ("cameras",) and len(path) == 2:
            return f"source: {node.data.get('source')}"
        if path[:1] == ("cameras",) and path[2:] == ("intrinsics",):
            return "cameras.intrinsics"
        if path[:1] == ("cameras",) and path[2:] == ("mount",):
            return "cameras.mount"
        if path[:1] == ("cameras",) and path[2:3] == ("mount",):
            return "mount pose"
        if path[:1] == ("inspections",) and len(path) == 2:
            return f"type: {node.data.get('type')}"
        if path[:1] == ("inspections",) and path[2:3] == ("measurements",):
            return "caliper.band" if path[4:] == ("band",) else "caliper.measurements"
        if path[:1] == ("inspections",) and len(path) == 3:
            return f"locate.{path[2]}"
        return "top"

    def recording_take(self: Node, key: str, convert: Any, *default: Any) -> Any:
        read.setdefault(section(self), set()).add(key)
        return original_take(self, key, convert, *default)

    def recording_sub(self: Node, key: str, *, required: bool = False) -> Node:
        read.setdefault(section(self), set()).add(key)
        return original_sub(self, key, required=required)

    def recording_items(self: Node, key: str) -> list[Node]:
        read.setdefault(section(self), set()).add(key)
        return original_items(self, key)

    original_sub = Node.sub
    original_items = Node.items
    monkeypatch.setattr(Node, "take", recording_take)
    monkeypatch.setattr(Node, "sub", recording_sub)
    monkeypatch.setattr(Node, "items", recording_items)

    template = tmp_path / "t.png"
    cv2.imwrite(str(template), np.arange(81, dtype=np.uint8).reshape(9, 9))
    (tmp_path / "d").mkdir()
    cv2.imwrite(str(tmp_path / "d" / "f0.png"), np.zeros((8, 8), np.uint8))
    (tmp_path / "token").write_text("secret")
    with RecordingWriter(tmp_path / "rec", camera="x", source="folder") as recording:
        recording.add(np.zeros((8, 8), np.uint8), timestamp_s=0.0)
    text = f"""\
server: {{host: 0.0.0.0, port: 0, name: x, max_frame_bytes: 1000000, max_image_pixels: 1000,
         max_in_flight: 2, max_connections: 3, workers: 1, queue_depth: 0,
         auth_token_file: token, shutdown_grace_s: 1, allow_reload: false,
         capture_timeout_s: 2, handshake_timeout_s: 3, idle_timeout_s: 4, frame_timeout_s: 5,
         write_timeout_s: 6, max_buffered_bytes: 7000000}}
results: {{enabled: true, path: r.db, store_images: all, max_image_mb: 5}}
cameras:
  req: {{source: request, depth: true,
         intrinsics: {{width: 64, height: 48, fx: 50, fy: 50, cx: 32, cy: 24}},
         mount: {{base_from_camera: {{xyz: [0, 0, 1], rpy: [3.14159265, 0, 0]}}}}}}
  cv: {{source: opencv, device: 0,
        mount: {{tool_from_camera: {{xyz: [0, 0, 0.1], rpy: [0, 0, 0]}}}}}}
  dir: {{source: folder, path: d}}
  sim: {{source: sim, scene: {EXAMPLE.parent / "scenes" / "grundfos_cell.yaml"}, camera: rgbd}}
  rs: {{source: realsense, serial: "1", width: 64, height: 48, fps: 15, depth: true,
        depth_width: 32, depth_height: 24, reconnect_interval_s: 2}}
  gc: {{source: genicam, cti: p.cti, serial: "2", pixel_format: Mono12, exposure_us: 100,
        gain_db: 1, trigger: hardware, trigger_source: Line1, reconnect_interval_s: 2}}
  rc: {{source: recording, path: rec, loop: true}}
inspections:
  - {{name: t, type: locate, camera: req, method: template, template: {{image: t.png}}}}
  - {{name: c, type: locate, camera: req, method: circle,
      circle: {{min_radius_px: 1, max_radius_px: 2}},
      output: {{frame: base, plane_z_m: 0, offset_m: [0, 0, 0.01], tool_rpy: [3, 0, 0]}}}}
  - {{name: b, type: locate, camera: req, method: blob, blob: {{}}}}
  - {{name: p, type: presence, camera: req, measure: mean_intensity, min: 1}}
  - {{name: q, type: qr, camera: req}}
  - {{name: k, type: code, camera: req, symbologies: [datamatrix, code128], expect: x,
      min_grade: {{module_px: 2, contrast: 0.2, decode_margin: 0.3, quiet_zone_modules: 1}}}}
  - {{name: cal, type: caliper, camera: req, units: mm, plane_distance_m: 0.3,
      measurements: [
        {{name: e, kind: edge, band: {{center: [30, 20], length: 20, width: 3, angle_rad: 0}},
         polarity: any, select: first, min_strength: 5, smoothing: 1, min: 0, max: 9}},
        {{name: w, kind: width, band: {{center: [30, 20], length: 20}}, first: any,
         second: any, expected: 5, tolerance: 1}},
        {{name: c, kind: circle, center: [30, 24], radius: 5, search: 2, rays: 16,
         band_width: 3, arc_rad: [0, 3], value: roundness}},
        {{name: l, kind: line, band: {{center: [30, 20], length: 10, width: 8}}, segments: 4}},
        {{name: d, kind: distance, from: e, to: l, value: distance}}]}}
  - {{name: cal2, type: caliper, camera: req, units: mm, mm_per_px: 0.1,
      measurements: [{{name: e, kind: edge, band: {{center: [30, 20], length: 20}}}}]}}
  - {{name: qp, type: qr_pose, camera: req, number: 9,
      output: {{fields: [found, {{name: x, decimals: 1, scale: 1000}}], decimals: 2,
               scale: {{found: 1}}, missing: -1}}}}
line: {{enabled: true, host: 0.0.0.0, port: 0, tls: false, format: ur, max_line_bytes: 100,
       idle_timeout_s: 1, deadline_s: 2, max_connections: 3, write_timeout_s: 4}}
modbus: {{enabled: true, host: 0.0.0.0, port: 0, unit_id: 3, word_order: low_first,
         deadline_s: 2, max_connections: 2}}
mqtt: {{enabled: true, host: broker, port: 8883, cell: c7, topic_prefix: plant/h2, client_id: x,
       username: u, password_file: token, tls: {{}}, keepalive_s: 10, max_in_flight: 8,
       spool: s.db, spool_max_mb: 1, reconnect_min_s: 1, reconnect_max_s: 2,
       publish_timeout_s: 3}}
"""
    load_config(write(tmp_path, text))
    docs = documented_keys()
    expected_sections = {
        "server": docs["server"],
        "server.tls": docs["server.tls"],
        "results": docs["results"],
        "line": docs["line"],
        "modbus": docs["modbus"],
        "mqtt": docs["mqtt"],
        "mqtt.tls": docs["mqtt.tls"],
        "inspections.output": docs["inspections.output"],
        "output.fields": {"name", "decimals", "scale"},
        "cameras.intrinsics": docs["cameras.intrinsics"],
        "cameras.mount": docs["cameras.mount"],
        "mount pose": {"xyz", "rpy"},
        **{
            f"source: {s}": docs["cameras"] | docs.get(f"source: {s}", set())
            for s in ("request", "opencv", "folder", "sim", "realsense", "genicam", "recording")
        },
        **{
            f"type: {t}": docs["inspections"] | docs[f"type: {t}"]
            for t in ("locate", "presence", "qr", "code", "qr_pose", "caliper")
        },
        "caliper.measurements": docs["caliper.measurements"],
        "caliper.band": docs["caliper.band"],
        **{f"locate.{m}": docs[f"locate.{m}"] for m in ("template", "circle", "blob")},
    }
    read.pop("top", None)
    # The validator also accepts the top-level sections themselves.
    for name, keys in expected_sections.items():
        got = read.get(name, set())
        if name.startswith("type: locate"):
            got = got - {"template", "circle", "blob"} | (keys & {"template", "circle", "blob"})
        assert got == keys, f"{name}: validator reads {sorted(got)}, docs list {sorted(keys)}"


def test_a_tls_key_that_is_not_the_certificates_is_a_configuration_error(tmp_path: Path) -> None:
    """check-config said valid and serve then failed to listen (exit 3): now both refuse it as
    a configuration error with file, line and key."""
    from certs import self_signed

    first, second = tmp_path / "a", tmp_path / "b"
    first.mkdir()
    second.mkdir()
    cert, _ = self_signed(first)
    _, other_key = self_signed(second)
    for key in (other_key, cert):  # another certificate's key; the certificate as its own key
        text = MINIMAL + f"server:\n  tls: {{cert: {cert}, key: {key}}}\n"
        error = error_of(tmp_path, text)
        assert "server -> tls -> key: the certificate and key cannot serve TLS" in str(error)
        config = str(tmp_path / "cell.yaml")
        done = subprocess.run(
            [sys.executable, "-m", "vision_server", "serve", "--config", config],
            capture_output=True, text=True, timeout=60, check=False,
        )  # fmt: skip
        assert done.returncode == 2, done.stderr
        assert "cannot serve TLS" in done.stderr


def test_the_server_section_holds_every_field_of_its_parts() -> None:
    """ServerSettings.service() and .tcp() copy their fields by name: each must exist in the
    section, with the same default."""
    from dataclasses import fields

    from vision_server.config import ServerSettings, ServiceSettings, TcpSettings

    section = ServerSettings()
    for part, built in ((ServiceSettings(), section.service()), (TcpSettings(), section.tcp())):
        for f in fields(part):
            assert getattr(built, f.name) == getattr(part, f.name), f.name
