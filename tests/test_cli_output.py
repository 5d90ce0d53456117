"""What the two command-line tools say, as a user runs them (subprocesses, against ``vision-server
serve`` processes): issue 14 points 1 (overlays), 7 (image files), 8 (``run``'s pixel limit),
9 (brackets in messages), 10 (readable results), 13 (reload feedback) and 14 (``--version``,
OpenCV's own lines, ``| head``, ``--help``, the demo server)."""

from __future__ import annotations

import json
import re
import signal
import subprocess
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from cli_tools import LISTENING, REPO_ROOT, TOOLS, Server, _env, _serve, tool

CASES = REPO_ROOT / "test_inspections"
TWO_CAPS = CASES / "cap_locate_circle" / "images" / "two_caps.png"
EMPTY_BELT = CASES / "cap_locate_circle" / "images" / "empty_belt.png"
STATION = CASES / "station_pose"
CELL = """\
server: {port: 0, allow_reload: true}
results: {enabled: false}
cameras:
  tool: {source: request}
  replay: {source: folder, path: replay, glob: "*.png", mode: cycle}
  rgbd:
    source: request
    depth: true
    intrinsics: {width: 224, height: 192, fx: 570.3, fy: 570.3, cx: 111.5, cy: 95.5}
inspections:
  - {name: bright, type: presence, camera: tool, measure: mean_intensity, min: 100}
  - name: cap_locate
    type: locate
    camera: tool
    method: circle
    circle: {min_radius_px: 30, max_radius_px: 50, polarity: bright}
    min_count: 1
    max_count: 10
  - {name: replayed, type: presence, camera: replay, measure: mean_intensity, min: 100}
  - {name: station_pose, type: qr_pose, camera: rgbd, method: plane,
     expect: "cellvision:station-1", side_m: 0.16, max_plane_rms_m: 0.005}
"""


def _cell(directory: Path, text: str = CELL) -> Path:
    (directory / "replay").mkdir(exist_ok=True)
    cv2.imwrite(str(directory / "replay" / "first.png"), np.full((24, 32), 200, np.uint8))
    config = directory / "cell.yaml"
    config.write_text(text)
    return config


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    yield from _serve(_cell(tmp_path_factory.mktemp("cell")))


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """two_caps.png in other formats, and images no colour inspection can take."""
    directory = tmp_path_factory.mktemp("files")
    caps = cv2.imread(str(TWO_CAPS), cv2.IMREAD_COLOR)
    out = {}
    for suffix in (".bmp", ".tif", ".webp", ".pgm"):
        out[suffix] = directory / f"two_caps{suffix}"
        picture = caps if suffix != ".pgm" else cv2.cvtColor(caps, cv2.COLOR_BGR2GRAY)
        assert cv2.imwrite(str(out[suffix]), picture)
    sixteen = np.full((32, 32), 50000, np.uint16)
    for suffix in (".png", ".tif"):
        out[f"16{suffix}"] = directory / f"sixteen{suffix}"
        assert cv2.imwrite(str(out[f"16{suffix}"]), sixteen)
    tiff = out[".tif"].read_bytes()
    out["broken.tif"] = directory / "broken.tif"
    out["broken.tif"].write_bytes(tiff[: len(tiff) // 2])  # OpenCV complains about it
    return out


def _run(config: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return tool("vision-server", "run", "--config", str(config), *args)


def _inspect(server: Server, *args: str) -> subprocess.CompletedProcess[str]:
    return tool("robot-client", "--server", server.address, "inspect", *args)


def _json_lines(text: str) -> list[dict[str, object]]:
    return [json.loads(line) for line in text.splitlines()]


# ----------------------------------------------------------------------------- point 1


@pytest.mark.parametrize("target", ["missing/overlay.png", "overlay.txt", "overlay"])
def test_an_overlay_that_cannot_be_written_is_refused_before_anything_runs(
    cell: Server, tmp_path: Path, target: str
) -> None:
    """``run`` said "overlay written" into a missing folder (exit 0, no file), ``inspect`` said
    nothing, ``.txt`` was a cv2.error traceback."""
    overlay = tmp_path / target
    for done in (
        _run(cell.config, "cap_locate", "--image", str(TWO_CAPS), "--overlay", str(overlay)),
        _inspect(cell, "cap_locate", "--image", str(TWO_CAPS), "--overlay", str(overlay)),
    ):
        assert done.returncode == 2, done.stdout + done.stderr
        assert "Traceback" not in done.stderr
        assert f"--overlay {overlay}" in done.stderr
        assert "written" not in done.stdout
        assert not overlay.exists()
        assert not overlay.parent.exists() or overlay.parent == tmp_path  # no folder created


def test_an_overlay_is_written_where_asked(cell: Server, tmp_path: Path) -> None:
    run_png, inspect_jpg = tmp_path / "run.png", tmp_path / "inspect.jpg"
    for path, done in (
        (
            run_png,
            _run(cell.config, "cap_locate", "--image", str(TWO_CAPS), "--overlay", str(run_png)),
        ),
        (
            inspect_jpg,
            _inspect(cell, "cap_locate", "--image", str(TWO_CAPS), "--overlay", str(inspect_jpg)),
        ),
    ):
        assert done.returncode == 0, done.stderr
        assert f"overlay written to {path}" in done.stdout
        overlay = cv2.imread(str(path))
        assert overlay is not None
        assert overlay.shape[:2] == (384, 512)


# ----------------------------------------------------------------------------- point 7


@pytest.mark.parametrize("suffix", [".bmp", ".tif", ".webp", ".pgm"])
def test_both_tools_read_every_format_opencv_reads(
    cell: Server, files: dict[str, Path], suffix: str
) -> None:
    image = str(files[suffix])
    for done in (
        _run(cell.config, "cap_locate", "--image", image, "--json"),
        _inspect(cell, "cap_locate", "--image", image, "--json"),
    ):
        assert done.returncode == 0, done.stdout + done.stderr
        result = json.loads(done.stdout)
        assert result["image"] == image
        assert result["data"]["count"] == 2


@pytest.mark.parametrize("key", ["16.png", "16.tif"])
def test_a_16_bit_colour_image_is_refused_naming_the_file(
    cell: Server, files: dict[str, Path], key: str
) -> None:
    image = str(files[key])
    for done in (
        _run(cell.config, "bright", "--image", image, "--json"),
        _inspect(cell, "bright", "--image", image, "--json"),
    ):
        assert done.returncode == 2, done.stdout + done.stderr
        message = json.loads(done.stdout)["error"]["message"]
        assert image in message
        assert "16-bit" in message
        assert "8-bit" in message


def test_depth_frames_in_any_16_bit_format_give_the_same_pose(cell: Server, tmp_path: Path) -> None:
    """A depth inspection takes 16-bit gray in TIFF or PGM as it does in PNG."""
    colour = STATION / "images" / "frontal_0.8m.png"
    depth_png = sorted((STATION / "images").glob("frontal_0.8m.depth*.png"))
    depth_other = []
    for index, path in enumerate(depth_png):
        other = tmp_path / f"depth{index}{('.tif', '.pgm')[index % 2]}"
        assert cv2.imwrite(str(other), cv2.imread(str(path), cv2.IMREAD_UNCHANGED))
        depth_other.append(other)
    poses = []
    for depth in (depth_png, depth_other):
        args = [a for d in depth for a in ("--depth", str(d))]
        done = _run(cell.config, "station_pose", "--image", str(colour), *args, "--json")
        assert done.returncode == 0, done.stdout + done.stderr
        poses.append(json.loads(done.stdout)["data"]["camera_from_qr"])
    assert poses[0] == poses[1]


def test_run_inspects_each_image_and_exits_with_the_worst(cell: Server) -> None:
    """``run --image a --image b`` used only b."""
    done = _run(
        cell.config, "cap_locate", "--image", str(TWO_CAPS), "--image", str(EMPTY_BELT), "--json"
    )
    assert done.returncode == 1, done.stderr
    results = _json_lines(done.stdout)
    assert [(r["image"], r["verdict"]) for r in results] == [
        (str(TWO_CAPS), "pass"),
        (str(EMPTY_BELT), "fail"),
    ]
    human = _run(cell.config, "cap_locate", "--image", str(TWO_CAPS), "--image", str(EMPTY_BELT))
    assert human.returncode == 1
    assert f"{TWO_CAPS}: PASS" in human.stdout
    assert f"{EMPTY_BELT}: FAIL" in human.stdout


def test_a_folder_camera_says_which_file_it_read(cell: Server) -> None:
    done = _inspect(cell, "replayed", "--json")
    assert done.returncode == 0, done.stdout + done.stderr
    result = json.loads(done.stdout)
    assert result["image"] is None
    assert result["data"]["source_files"] == ["first.png"]


# ----------------------------------------------------------------------------- point 8


def test_run_honours_the_configured_pixel_limit(tmp_path: Path, files: dict[str, Path]) -> None:
    """``run`` ignored ``server.max_image_pixels`` (512x384 = 196608 pixels here)."""
    config = _cell(tmp_path, CELL.replace("port: 0,", "port: 0, max_image_pixels: 100000,"))
    for image in (TWO_CAPS, files[".bmp"]):  # checked from the header, or the raw size
        done = _run(config, "cap_locate", "--image", str(image), "--json")
        assert done.returncode == 4, done.stdout + done.stderr
        error = json.loads(done.stdout)["error"]
        assert error["code"] == "IMAGE_TOO_LARGE", error


# ----------------------------------------------------------------------------- point 9


def test_square_brackets_in_messages_are_shown(tmp_path: Path) -> None:
    """Rich markup ate ``[u, v, width, height]``."""
    config = _cell(
        tmp_path,
        CELL.replace(
            "measure: mean_intensity, min: 100}",
            "roi: [1, 2, 3], measure: mean_intensity, min: 100}",
            1,
        ),
    )
    done = tool("vision-server", "check-config", str(config))
    assert done.returncode == 2
    assert "expected [u, v, width, height]" in " ".join(done.stderr.split())


# ----------------------------------------------------------------------------- point 10


def test_results_for_people_are_rounded_tables(cell: Server) -> None:
    """``run`` printed 15-digit floats, ``inspect`` Python reprs."""
    for done in (
        _run(cell.config, "cap_locate", "--image", str(TWO_CAPS)),
        _inspect(cell, "cap_locate", "--image", str(TWO_CAPS)),
    ):
        assert done.returncode == 0, done.stderr
        out = done.stdout
        assert "{'u'" not in out, out
        assert not re.search(r"\d\.\d{5,}", out), out
        header = next(line for line in out.splitlines() if " u " in line and " v " in line)
        assert "score" in header
        assert "angle (deg)" in header
        assert re.search(r"\b115\.49\b.*\b194\.81\b.*\b0\.961\b", out), out


# ----------------------------------------------------------------------------- point 13


@pytest.fixture
def reloadable(tmp_path: Path) -> Iterator[tuple[Server, subprocess.Popen[bytes]]]:
    """A server and its process, whose pipes are unbuffered: a line read from them takes no
    more than that line, so the rest is all in ``communicate()``."""
    config = _cell(tmp_path)
    proc = subprocess.Popen(
        [*TOOLS["vision-server"], "serve", "--config", str(config)],
        cwd=REPO_ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        bufsize=0,
        env=_env(),
    )
    try:
        assert proc.stdout is not None
        match = LISTENING.fullmatch(proc.stdout.readline().decode())
        assert match, proc.communicate(timeout=30)
        yield Server(f"127.0.0.1:{match[2]}", config), proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=30)


def _stop(proc: subprocess.Popen[str] | subprocess.Popen[bytes]) -> tuple[str, str]:
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    decode = (lambda x: x.decode()) if isinstance(out, bytes) else (lambda x: x)
    return decode(out), decode(err)


def test_a_reload_is_said_by_the_server_and_its_notes_reach_the_client(
    reloadable: tuple[Server, subprocess.Popen[bytes]],
) -> None:
    server, proc = reloadable
    text = server.config.read_text()
    server.config.write_text(
        text.replace("allow_reload: true", "allow_reload: true, max_in_flight: 7")
    )
    done = tool("vision-server", "reload", "--server", server.address, "--json")
    assert done.returncode == 0, done.stderr
    notes = json.loads(done.stdout)["notes"]
    assert notes == ["cell.yaml: changes under 'server:' take effect after a restart"]
    human = tool("vision-server", "reload", "--server", server.address)
    assert "note: cell.yaml: changes under 'server:' take effect after a restart" in human.stdout
    out, _ = _stop(proc)
    assert out.count("configuration reloaded") == 2, out


def test_a_refused_sighup_reload_is_logged_once(
    reloadable: tuple[Server, subprocess.Popen[bytes]],
) -> None:
    server, proc = reloadable
    server.config.write_text(
        server.config.read_text() + "  - {name: broken, type: qr, camera: nope}\n"
    )
    proc.send_signal(signal.SIGHUP)
    assert proc.stderr is not None
    while b"reload refused" not in proc.stderr.readline():  # anything more comes at once
        assert proc.poll() is None, "the server stopped"
    _, rest = _stop(proc)
    assert "reload refused" not in rest, rest


# ----------------------------------------------------------------------------- point 14


@pytest.mark.parametrize("name", sorted(TOOLS))
def test_version(name: str) -> None:
    done = tool(name, "--version")
    assert done.returncode == 0, done.stderr
    assert re.fullmatch(rf"{name} \S+ \(protocol 1\.1\)\n", done.stdout), done.stdout


def test_opencv_says_nothing_of_its_own(cell: Server, files: dict[str, Path]) -> None:
    """OpenCV's ``[ WARN:...]``/``[ERROR:...]`` lines came before our own error."""
    for done in (
        _run(cell.config, "bright", "--image", str(files["broken.tif"])),
        _inspect(cell, "bright", "--image", str(files["broken.tif"])),
    ):
        assert done.returncode == 2, done.stderr
        assert "broken.tif" in done.stderr
        assert not re.search(r"\[ ?(WARN|ERROR|INFO):", done.stderr), done.stderr


@pytest.mark.parametrize(
    "command",
    [
        ["vision-server", "check-config", "examples/cell.yaml"],
        ["vision-server", "test-inspections", "test_inspections/magnet_presence"],
        ["robot-client", "skills"],
    ],
)
def test_a_closed_pipe_ends_quietly(command: list[str]) -> None:
    """``| head`` printed a BrokenPipeError traceback."""
    proc = subprocess.Popen(
        [*TOOLS[command[0]], *command[1:]],
        cwd=REPO_ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=_env(),
    )
    assert proc.stdout is not None
    assert proc.stderr is not None
    proc.stdout.close()  # the reader is gone before the first line
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 128 + signal.SIGPIPE, err
    assert "Traceback" not in err, err
    assert "BrokenPipe" not in err, err


def _commands(name: str) -> list[list[str]]:
    if name == "vision-server":
        subs = ["serve", "check-config", "run", "test-inspections", "results", "ping", "reload"]
    else:
        subs = ["ping", "inspections", "inspect", "skills", "teach", "run", "taught list"]
        subs += ["taught show", "task run"]
    return [[], *(s.split() for s in subs)]


@pytest.mark.parametrize("name", sorted(TOOLS))
def test_help_has_no_literal_double_backticks(name: str) -> None:
    for command in _commands(name):
        done = tool(name, *command, "--help")
        assert done.returncode == 0, done.stderr
        assert "``" not in done.stdout, f"{name} {' '.join(command)} --help:\n{done.stdout}"


def test_serve_without_a_configuration_says_it_serves_the_demo() -> None:
    proc = subprocess.Popen(
        [*TOOLS["vision-server"], "serve", "--port", "0"],
        cwd=REPO_ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
    )
    try:
        assert proc.stdout is not None
        assert LISTENING.fullmatch(proc.stdout.readline())
        _, err = _stop(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=30)
    assert "built-in demo inspection (brightness" in err, err
