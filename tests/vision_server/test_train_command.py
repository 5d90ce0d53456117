"""``vision-server train`` end to end in a folder of its own: it writes models/NAME.v1.npz, points
the inspection's ``model:`` at it (the file's history records the change, ``vision-server
history`` lists it), and a second training writes v2; ``--json`` reports the threshold, its
false-reject rate and the held-out scores; too few images, an unreadable image, a pattern that
matches nothing, an unknown or untrainable inspection are exit 2 with a code naming the cause,
and leave the configuration and the models folder as they were."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from anomaly_synthetic import SIZE, defective_part, good_part

from vision_server import InspectionInput
from vision_server.analysis.anomaly import image_digest, load_model
from vision_server.commands import main
from vision_server.config import ConfigError, load_config

ROI = (10, 6, SIZE, SIZE)
CONFIG = f"""\
# the press line's camera 2
cameras:
  cam: {{source: request}}
inspections:
  - name: surface
    type: anomaly
    camera: cam
    roi: [{ROI[0]}, {ROI[1]}, {ROI[2]}, {ROI[3]}]
    method: variation   # aligned parts
  - name: dark
    type: presence
    camera: cam
    roi: [0, 0, 10, 10]
    measure: dark_fraction
    threshold: 100
    min: 0.5
"""


def scene(part: np.ndarray) -> np.ndarray:
    image = np.full((250, 250, 3), 40, np.uint8)
    u, v, w, h = ROI
    image[v : v + h, u : u + w] = part
    return image


@pytest.fixture
def cell(tmp_path: Path) -> Path:
    """A cell folder: cell.yaml and good/00.png .. good/11.png (whole camera images)."""
    (tmp_path / "cell.yaml").write_text(CONFIG, encoding="utf-8")
    good = tmp_path / "good"
    good.mkdir()
    rng = np.random.default_rng(4)
    for index in range(12):
        cv2.imwrite(str(good / f"{index:02d}.png"), scene(good_part(rng)))
    return tmp_path


def clean_env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k != "CELLVISION_CONFIG"}


def cli(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "vision_server", *args],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
        cwd=cwd,
        env=clean_env(),
    )


def test_train_writes_the_model_points_the_configuration_at_it_and_records_history(
    cell: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = load_config(cell / "cell.yaml")
    done = cli(
        cell, "train", "surface", "--config", "cell.yaml", "--images", "good/*.png", "--json"
    )
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report["inspection"] == "surface"
    assert report["model"] == "models/surface.v1.npz"
    assert report["method"] == "variation"
    assert report["version"] == 1
    assert report["images"] == 12
    assert report["false_reject"] == 0.01
    assert len(report["held_out_scores"]) == 12
    assert report["threshold"] >= max(report["held_out_scores"]) * 0.5
    assert 0.0 <= report["held_out_rejected"] <= 1.0
    assert report["skipped"] == []
    assert report["seconds"] >= 0
    model_file = cell / "models" / "surface.v1.npz"
    model = load_model(model_file)
    assert model.threshold == report["threshold"]
    # The model was trained on the ROIs cut from the whole images, as the inspection cuts them.
    u, v, w, h = ROI
    cut = [
        np.ascontiguousarray(cv2.imread(str(p))[v : v + h, u : u + w])
        for p in sorted((cell / "good").glob("*.png"))
    ]
    assert model.meta["images"] == [image_digest(image) for image in cut]
    text = (cell / "cell.yaml").read_text(encoding="utf-8")
    assert '    model: "models/surface.v1.npz"\n' in text
    assert text.replace('    model: "models/surface.v1.npz"\n', "") == CONFIG
    after = load_config(cell / "cell.yaml")
    assert after.config_hash != before.config_hash
    (inspection, _) = after.inspections
    rng = np.random.default_rng(40)
    assert inspection.run(InspectionInput(scene(good_part(rng))), overlay=False).passed
    scratched, _ = defective_part(rng, "scratch")
    assert not inspection.run(InspectionInput(scene(scratched)), overlay=False).passed

    listed = cli(cell, "history", "--config", "cell.yaml", "--json")
    assert listed.returncode == 0, listed.stderr
    versions = [json.loads(line) for line in listed.stdout.splitlines()]  # newest first
    newest = versions[0]
    assert newest["why"] == "trained models/surface.v1.npz on 12 images"
    assert newest["who"] == "vision-server train"
    assert newest["config_hash"] == after.config_hash

    # A second training, in process: v2, the configuration moves on, v1 stays.
    code = main(
        [
            "train",
            "surface",
            "--config",
            str(cell / "cell.yaml"),
            "--images",
            str(cell / "good") + "/0*.png",
        ]
    )
    out = capsys.readouterr()
    assert code == 0, out.err
    assert "threshold" in out.out
    assert "false-reject rate of 0.01" in out.out
    assert "models/surface.v2.npz" in out.out
    assert "vision-server reload" in out.out
    assert model_file.is_file()
    assert load_model(cell / "models" / "surface.v2.npz").version == 2
    text = (cell / "cell.yaml").read_text(encoding="utf-8")
    assert '    model: "models/surface.v2.npz"\n' in text
    assert "surface.v1.npz" not in text
    assert load_config(cell / "cell.yaml").config_hash not in (
        before.config_hash,
        after.config_hash,
    )
    listed = cli(cell, "history", "--config", "cell.yaml")
    assert listed.returncode == 0, listed.stderr
    assert "trained models/surface.v2.npz on 10 images" in listed.stdout
    assert "trained models/surface.v1.npz on 12 images" in listed.stdout


def run_json(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, dict[str, Any]]:
    code = main(["train", *args, "--json"])
    return code, json.loads(capsys.readouterr().out)


def unchanged(cell: Path) -> None:
    assert (cell / "cell.yaml").read_text(encoding="utf-8") == CONFIG
    assert not (cell / "models").exists() or not any((cell / "models").iterdir())


def test_too_few_images_exit_2_with_too_few_images(
    cell: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, report = run_json(
        capsys,
        "surface",
        "--config",
        str(cell / "cell.yaml"),
        "--images",
        f"{cell}/good/0[0-6].png",
    )
    assert code == 2
    assert report["error"]["code"] == "TOO_FEW_IMAGES"
    assert "7 images: training needs at least 8" in report["error"]["message"]
    assert report["error"]["kind"] == "usage"
    unchanged(cell)


def test_an_unreadable_image_exits_2_naming_the_file(
    cell: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    broken = cell / "good" / "05.png"
    broken.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    code, report = run_json(
        capsys, "surface", "--config", str(cell / "cell.yaml"), "--images", f"{cell}/good/*.png"
    )
    assert code == 2
    assert report["error"]["code"] == "BAD_IMAGE"
    assert "05.png" in report["error"]["message"]
    assert "not an image" in report["error"]["message"]
    unchanged(cell)


def test_an_image_smaller_than_the_roi_is_left_out_and_named(
    cell: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cv2.imwrite(str(cell / "good" / "small.png"), np.zeros((100, 100, 3), np.uint8))
    code, report = run_json(
        capsys, "surface", "--config", str(cell / "cell.yaml"), "--images", f"{cell}/good/*.png"
    )
    assert code == 0, report
    assert report["images"] == 12
    (skipped,) = report["skipped"]
    assert "small.png" in skipped
    assert "reaches past the 100x100 image" in skipped


@pytest.mark.parametrize(
    ("args", "code_name", "cause"),
    [
        (["surface", "--images", "nothing/*.png"], "NO_IMAGES", "no file matches"),
        (["nobody", "--images", "good/*.png"], "NOT_FOUND", "no inspection 'nobody'"),
        (["dark", "--images", "good/*.png"], "NOT_TRAINABLE", "is a presence inspection"),
        (["surface", "--images", "good/*.png", "--step", "x"], "NOT_TRAINABLE", "has no steps"),
        (["surface", "--images", "good/*.png", "--false-reject", "0.7"], "USAGE", "(0, 0.5)"),
    ],
    ids=["no-match", "unknown", "presence", "step-of-non-job", "rate"],
)
def test_what_cannot_be_trained_exits_2_naming_the_cause(
    cell: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    args: list[str],
    code_name: str,
    cause: str,
) -> None:
    monkeypatch.chdir(cell)
    code, report = run_json(capsys, *args, "--config", "cell.yaml")
    assert code == 2
    assert report["error"]["code"] == code_name
    assert cause in report["error"]["message"]
    unchanged(cell)


def test_a_broken_configuration_or_none_exits_2(
    cell: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("CELLVISION_CONFIG", raising=False)
    monkeypatch.chdir(cell)
    code, report = run_json(capsys, "surface", "--images", "good/*.png")
    assert code == 2
    assert report["error"]["code"] == "USAGE"
    (cell / "bad.yaml").write_text("inspections: [", encoding="utf-8")
    code, report = run_json(capsys, "surface", "--images", "good/*.png", "--config", "bad.yaml")
    assert code == 2
    assert report["error"]["code"] == "CONFIG_INVALID"
    # Without --json the code and the cause go to stderr.
    assert main(["train", "surface", "--images", "none/*.png", "--config", "cell.yaml"]) == 2
    assert "NO_IMAGES" in capsys.readouterr().err


JOB = f"""\
cameras:
  cam: {{source: request}}
inspections:
  - name: line
    type: job
    camera: cam
    steps:
      - name: face
        type: anomaly
        roi: [{ROI[0]}, {ROI[1]}, {ROI[2]}, {ROI[3]}]
        method: variation
      - name: edge
        type: anomaly
        roi: [0, 0, 64, 64]
        method: variation
"""


def test_a_jobs_anomaly_step_is_trained_with_step(
    cell: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = cell / "job.yaml"
    config.write_text(JOB, encoding="utf-8")
    args = ["line", "--config", str(config), "--images", f"{cell}/good/*.png"]
    code, report = run_json(capsys, *args)
    assert code == 2
    assert report["error"]["code"] == "NOT_TRAINABLE"
    assert "2 anomaly steps (face, edge): name one with --step" in report["error"]["message"]
    code, report = run_json(capsys, *args, "--step", "face")
    assert code == 0, report
    assert report["model"] == "models/line.face.v1.npz"
    text = config.read_text(encoding="utf-8")
    assert text.count("model:") == 1
    assert '        model: "models/line.face.v1.npz"\n' in text
    (job,) = load_config(config).inspections
    assert job.steps[0].settings.model.image_size == ROI[2:]  # type: ignore[attr-defined]
    assert job.steps[1].settings.model is None  # type: ignore[attr-defined]


@pytest.mark.parametrize("damage", ["roi", "file"])
def test_retraining_cures_a_model_the_configuration_refuses(
    cell: Path, capsys: pytest.CaptureFixture[str], damage: str
) -> None:
    """The configuration error says "retrain it": training must then work (a resized ROI, a
    damaged model file), and the new model makes the configuration load again."""
    config = cell / "cell.yaml"
    args = ["surface", "--config", str(config), "--images", f"{cell}/good/*.png"]
    assert run_json(capsys, *args)[0] == 0
    if damage == "roi":
        text = config.read_text(encoding="utf-8")
        config.write_text(text.replace(f"roi: [10, 6, {SIZE}", "roi: [10, 6, 200"), "utf-8")
    else:
        (cell / "models" / "surface.v1.npz").write_bytes(b"not a model")
    with pytest.raises(ConfigError, match="surface.v1.npz"):
        load_config(config)
    code, report = run_json(capsys, *args)
    assert code == 0, report
    assert report["model"] == "models/surface.v2.npz"
    (inspection, _) = load_config(config).inspections
    size = (200, SIZE) if damage == "roi" else (SIZE, SIZE)
    assert inspection.settings.model.image_size == size  # type: ignore[attr-defined]
    # Another inspection's error is not excused: the configuration stays refused.
    text = config.read_text(encoding="utf-8")
    config.write_text(text.replace("min: 0.5", "min: 7"), "utf-8")
    code, report = run_json(capsys, *args)
    assert code == 2
    assert report["error"]["code"] == "CONFIG_INVALID"


def test_a_running_server_takes_the_model_on_reload_without_a_restart(cell: Path) -> None:
    """serve → the untrained inspection fails with INSPECTION_FAILED → train --reload → the
    same server process judges with the model: a good part passes, a scratched one fails."""
    from cli_tools import LISTENING, TOOLS, _env, tool

    config = cell / "cell.yaml"
    config.write_text(
        "server: {port: 0, allow_reload: true}\nresults: {enabled: false}\n" + CONFIG, "utf-8"
    )
    rng = np.random.default_rng(41)
    cv2.imwrite(str(cell / "part.png"), scene(good_part(rng)))
    cv2.imwrite(str(cell / "scratched.png"), scene(defective_part(rng, "scratch")[0]))
    proc = subprocess.Popen(
        [*TOOLS["vision-server"], "serve", "--config", str(config)],
        cwd=cell,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        bufsize=0,
        env=_env(),
    )
    try:
        assert proc.stdout is not None
        match = LISTENING.fullmatch(proc.stdout.readline().decode())
        assert match, proc.communicate(timeout=30)
        address = f"127.0.0.1:{match[2]}"

        def inspect(image: str) -> dict[str, Any]:
            done = tool(
                "robot-client",
                "--server",
                address,
                "inspect",
                "surface",
                "--json",
                "--image",
                str(cell / image),
            )
            answer: dict[str, Any] = json.loads(done.stdout.splitlines()[-1])
            return answer

        untrained = inspect("part.png")
        assert untrained["error"]["code"] == "INSPECTION_FAILED", untrained
        assert "vision-server train surface" in untrained["error"]["message"]
        trained = tool(
            "vision-server",
            "train",
            "surface",
            "--config",
            str(config),
            "--images",
            f"{cell}/good/*.png",
            # 12 good images cannot set a 1 % tail below this faint scratch: ask for 5 %
            "--false-reject",
            "0.05",
            "--reload",
            "--server",
            address,
            "--json",
        )
        assert trained.returncode == 0, trained.stderr
        lines = trained.stdout.splitlines()
        assert len(lines) == 1, "--json prints one object"
        report = json.loads(lines[0])
        assert report["model"] == "models/surface.v1.npz"
        assert report["reload"]["config_hash"] == load_config(config).config_hash
        assert "surface" in report["reload"]["inspections"]
        good = inspect("part.png")
        assert good["verdict"] == "pass", good
        assert good["data"]["model_version"] == 1
        bad = inspect("scratched.png")
        assert bad["verdict"] == "fail", bad
        assert proc.poll() is None  # the same process throughout
        # A reload that reaches no server: exit 3, the model written, one object still.
        proc.kill()
        proc.communicate(timeout=30)
        again = tool(
            "vision-server",
            "train",
            "surface",
            "--config",
            str(config),
            "--images",
            f"{cell}/good/*.png",
            # 12 good images cannot set a 1 % tail below this faint scratch: ask for 5 %
            "--false-reject",
            "0.05",
            "--reload",
            "--server",
            address,
            "--json",
        )
        assert again.returncode == 3, again.stderr
        (line,) = again.stdout.splitlines()
        report = json.loads(line)
        assert report["model"] == "models/surface.v2.npz"
        assert report["reload"]["error"]["kind"] == "connection"
        assert (cell / "models" / "surface.v2.npz").is_file()
    finally:
        proc.kill()
        proc.communicate(timeout=30)


def test_images_whose_fixture_finds_no_part_are_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from anomaly_synthetic import PLATE_WINDOW, placed_plate

    config = tmp_path / "job.yaml"
    config.write_text(
        f"""\
cameras:
  cam: {{source: request}}
inspections:
  - name: plate
    type: job
    camera: cam
    steps:
      - name: hole
        type: locate
        method: circle
        circle: {{min_radius_px: 10, max_radius_px: 15, polarity: dark}}
        max_count: 1
      - name: part
        type: fixture
        origin: hole
      - name: surface
        type: anomaly
        fixture: part
        roi: {list(PLATE_WINDOW)}
        method: variation
""",
        "utf-8",
    )
    rng = np.random.default_rng(5)
    for index in range(10):
        image = (
            placed_plate(rng, 130.0, 120.0, 0.0)[0]
            if index < 3
            else np.full((240, 320), 40, np.uint8)
        )
        cv2.imwrite(str(tmp_path / f"{index:02d}.png"), image)
    code, report = run_json(
        capsys, "plate", "--config", str(config), "--images", f"{tmp_path}/*.png"
    )
    assert code == 2
    assert report["error"]["code"] == "NOT_TRAINABLE"
    message = report["error"]["message"]
    assert "7 of 10 images could not be used" in message
    assert "03.png" in message
    assert "fixture 'part' was not made" in message or "found nothing" in message
    assert not (tmp_path / "models").exists()


def test_a_save_made_while_the_training_ran_is_kept(
    cell: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Found by an attack: train wrote model: into the text it read at the start, so a save
    made meanwhile (by the console, by hand) was silently undone."""
    from vision_server.commands import train as train_module

    config = cell / "cell.yaml"
    original = train_module.train_inspection

    def train_while_someone_saves(*args: Any, **kwargs: Any) -> Any:
        trained = original(*args, **kwargs)
        text = config.read_text(encoding="utf-8")
        config.write_text(text.replace("min: 0.5", "min: 0.25  # saved meanwhile"), "utf-8")
        return trained

    monkeypatch.setattr(train_module, "train_inspection", train_while_someone_saves)
    monkeypatch.delenv("CELLVISION_CONFIG", raising=False)
    monkeypatch.chdir(cell)
    status = main(["train", "surface", "--config", "cell.yaml", "--images", "good/*.png"])
    capsys.readouterr()
    assert status == 0
    text = config.read_text(encoding="utf-8")
    assert "min: 0.25  # saved meanwhile" in text
    assert 'model: "models/surface.v1.npz"' in text
    load_config(config)
