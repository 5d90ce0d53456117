"""Golden inspection cases (test_inspections/): the corpus passes through the serving code path,
and the runner reports regressions (exit 1), rewrites expectations with --update and shows the
difference, and names file, line and key of a bad case file (exit 2)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from vision_server.commands import main
from vision_server.commands.golden import (
    Expectation,
    Got,
    Tolerances,
    compare,
    load_case,
    pose_error,
    run_cases,
)

REPO = Path(__file__).resolve().parents[2]
CORPUS = REPO / "test_inspections"


def _json_run(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, dict]:
    code = main(["test-inspections", "--json", *args])
    return code, json.loads(capsys.readouterr().out)


@pytest.fixture
def presence_copy(tmp_path: Path) -> Path:
    """A copy of the magnet_presence case and the image pool it points at."""
    shutil.copytree(CORPUS / "qc_images", tmp_path / "qc_images")
    shutil.copytree(CORPUS / "magnet_presence", tmp_path / "magnet_presence")
    return tmp_path / "magnet_presence"


def _flat(text: str) -> str:
    """Console output with the terminal's line wrapping undone."""
    return " ".join(text.split())


def _edit(path: Path, old: str, new: str) -> None:
    text = path.read_text(encoding="utf-8")
    assert old in text, (old, path)
    path.write_text(text.replace(old, new), encoding="utf-8")


# --- the corpus ---------------------------------------------------------------------------------


def test_the_corpus_passes_and_covers_every_type_and_method() -> None:
    report = run_cases([CORPUS])
    bad = [(c.name, c.error) for c in report.cases if c.error]
    assert not bad
    failures = [
        (c.name, i.image, i.problems) for c in report.cases for i in c.images if i.status != "pass"
    ]
    assert not failures
    assert report.exit_code == 0
    kinds = set()
    for case in report.cases:
        if case.skipped:  # only the real photographs may be absent, and they say where
            assert case.name == "qr_real_photos"
            assert "qr_real" in case.skipped
            assert "not found" in case.skipped
            continue
        loaded = load_case(case.path)
        kinds.add((loaded.inspection.type, getattr(loaded.inspection, "method", None)))
        images = [i.image for i in case.images]
        assert len(images) == len(loaded.expectations) >= 2, case.name
        verdicts = {i.result.verdict for i in case.images if i.result is not None}
        assert verdicts == {"pass", "fail"} or case.name == "qr_real_photos", case.name
    assert {
        ("locate", "template"),
        ("locate", "circle"),
        ("locate", "blob"),
        ("presence", None),
        ("qr", None),
        ("qr_pose", "plane"),
        ("anomaly", None),
    } <= kinds
    assert sum(f.stat().st_size for f in CORPUS.rglob("*.png")) < 3_000_000


def test_the_real_photographs_run_where_present(qr_real_dir: Path) -> None:
    report = run_cases([CORPUS / "qr_real_photos"])
    (case,) = report.cases
    assert case.skipped is None
    assert case.error is None
    assert len(case.images) >= 10
    assert all(i.status == "pass" for i in case.images)


# --- the runner -------------------------------------------------------------------------------


def test_a_broken_roi_is_a_regression(
    presence_copy: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The integrator moves the ROI off the slot: the magnet is never seen.
    _edit(presence_copy / "inspection.yaml", "roi: [137, 100, 46, 56]", "roi: [10, 10, 46, 56]")
    code, report = _json_run(capsys, str(presence_copy))
    assert code == 1
    assert report["ok"] is False
    images = {i["image"]: i for i in report["cases"][0]["images"]}
    broken = images["in_slot.png"]
    assert broken["status"] == "regression"
    assert "verdict fail, expected pass" in broken["problems"]
    assert any(p.startswith("value 0.0, expected") for p in broken["problems"])
    assert images["empty.png"]["status"] == "pass"  # still absent, still failing
    assert report["summary"]["regressions"] >= 5

    # The table for people says the same.
    assert main(["test-inspections", str(presence_copy)]) == 1
    out = capsys.readouterr().out
    assert "6 regressions" in out
    assert "✗" in out


def test_a_threshold_change_is_caught(
    presence_copy: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Everything but the brightest table counts as dark: the empty slot passes.
    _edit(presence_copy / "inspection.yaml", "threshold: 60", "threshold: 200")
    code, report = _json_run(capsys, str(presence_copy))
    assert code == 1
    images = {i["image"]: i for i in report["cases"][0]["images"]}
    assert "verdict pass, expected fail" in images["empty.png"]["problems"]


def test_update_rewrites_and_shows_the_difference(
    presence_copy: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    expected = presence_copy / "expected.yaml"
    before = expected.read_text(encoding="utf-8")
    _edit(presence_copy / "inspection.yaml", "min: 0.2", "min: 0.9")  # a deliberate change
    code, report = _json_run(capsys, str(presence_copy), "--update")
    assert code == 0
    diff = report["cases"][0]["diff"]
    assert "-    verdict: pass" in diff
    assert "+    verdict: fail" in diff
    after = expected.read_text(encoding="utf-8")
    assert after != before
    assert "tolerance_value: 0.05" in after  # tolerances, notes and the header are kept
    assert 'note: "magnet in its slot"' in after
    assert after.startswith("# Written by test_inspections/generate.py")
    # The table shows the diff too, and the updated case now passes.
    assert main(["test-inspections", str(presence_copy)]) == 0
    _edit(presence_copy / "inspection.yaml", "min: 0.9", "min: 0.2")
    assert main(["test-inspections", str(presence_copy), "--update"]) == 0
    shown = capsys.readouterr().out
    assert "expected.yaml updated" in shown
    assert "+    verdict: pass" in shown
    # Back to the original verdicts; the values are now the measured ones, no longer the
    # ground truth that generate.py wrote (within the tolerance of it).
    restored = expected.read_text(encoding="utf-8")
    verdicts = [line for line in before.splitlines() if "verdict" in line]
    assert [line for line in restored.splitlines() if "verdict" in line] == verdicts
    assert main(["test-inspections", str(presence_copy)]) == 0


def test_a_new_image_is_reported_then_recorded(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    case = tmp_path / "caps"
    shutil.copytree(CORPUS / "cap_locate_circle", case)
    shutil.copy(case / "images" / "two_caps.png", case / "images" / "another.png")
    code, report = _json_run(capsys, str(case))
    assert code == 1
    new = [i for i in report["cases"][0]["images"] if i["status"] == "new"]
    assert [i["image"] for i in new] == ["another.png"]
    code, report = _json_run(capsys, str(case), "--update")
    assert code == 0
    assert "+  another.png:" in report["cases"][0]["diff"]
    assert load_case(case).expectations["another.png"].count == 2
    assert main(["test-inspections", str(case)]) == 0


def test_bad_case_files_name_file_line_and_key(
    presence_copy: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _edit(presence_copy / "inspection.yaml", "threshold: 60", "threshold: high")
    code, report = _json_run(capsys, str(presence_copy))
    assert code == 2
    error = report["cases"][0]["error"]
    assert "magnet_presence/inspection.yaml:11 inspection -> threshold" in error
    assert "expected a number, got 'high'" in error

    _edit(presence_copy / "inspection.yaml", "threshold: high", "threshold: 60")
    _edit(presence_copy / "expected.yaml", "    verdict: fail", "    verdict: fial")
    code, report = _json_run(capsys, str(presence_copy))
    assert code == 2
    error = report["cases"][0]["error"]
    assert "magnet_presence/expected.yaml:" in error
    assert "images -> beside_slot.png -> verdict: expected one of pass, fail, error" in error

    _edit(presence_copy / "expected.yaml", "    verdict: fial", "    verdict: fail")
    _edit(presence_copy / "expected.yaml", "    value: 0.0\n", "    value: 0.0\n    count: 1\n")
    code, report = _json_run(capsys, str(presence_copy))
    assert code == 2
    assert "'count' is not a result of a presence inspection" in report["cases"][0]["error"]

    assert main(["test-inspections", str(presence_copy.parent / "no_such_case")]) == 2
    assert "not a case (no such folder)" in _flat(capsys.readouterr().out)


def test_shared_images_marked_skip_if_absent_skip_the_case(
    presence_copy: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    case = tmp_path / "elsewhere"
    shutil.copytree(CORPUS / "qr_real_photos", case)
    code, report = _json_run(capsys, str(case), str(presence_copy))
    assert code == 0
    skipped = {c["case"]: c["skipped"] for c in report["cases"]}
    assert "not found" in skipped["elsewhere"]
    assert skipped["magnet_presence"] is None
    # Alone, it tests nothing: that is no pass.
    code, report = _json_run(capsys, str(case))
    assert code == 2
    assert report["errors"][0].startswith("nothing was tested: every case was skipped")


# --- green means tested: the command as a user runs it -----------------------------------------


def cli(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """``vision-server test-inspections ARGS`` as a process in ``cwd``, with this checkout's
    code."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "200"}
    return subprocess.run(
        [sys.executable, "-m", "vision_server", "test-inspections", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


def test_without_a_path_only_the_working_folder_s_cases_run(tmp_path: Path) -> None:
    done = cli(cwd=tmp_path)  # no test_inspections/ here: never the project's own cases
    assert done.returncode == 2, done.stdout
    assert f"{tmp_path / 'test_inspections'}: no such folder" in _flat(done.stdout)
    assert "cap_locate_circle" not in done.stdout
    assert "0 cases, 0 images" in done.stdout

    (tmp_path / "test_inspections").mkdir()
    shutil.copytree(CORPUS / "qc_images", tmp_path / "test_inspections" / "qc_images")
    shutil.copytree(CORPUS / "magnet_presence", tmp_path / "test_inspections" / "presence")
    done = cli(cwd=tmp_path)
    assert done.returncode == 0, done.stdout
    assert "1 case, 9 images: 9 passed, 0 regressions, 0 new, 0 cases skipped, 0 bad cases" in (
        done.stdout
    )


def test_a_folder_without_cases_is_an_error(tmp_path: Path) -> None:
    (tmp_path / "cases").mkdir()
    (tmp_path / "cases" / "notes.txt").write_text("no case here", encoding="utf-8")
    done = cli("cases", "--json", cwd=tmp_path)
    assert done.returncode == 2
    report = json.loads(done.stdout)
    (case,) = report["cases"]
    assert case["error"].startswith("cases: not a case (no inspection.yaml here or below)")


def test_a_typo_in_the_images_path_is_an_error(presence_copy: Path) -> None:
    _edit(presence_copy / "inspection.yaml", "images: ../qc_images", "images: ../qc_imgaes")
    done = cli(str(presence_copy), "--json", cwd=presence_copy.parent)
    assert done.returncode == 2
    error = json.loads(done.stdout)["cases"][0]["error"]
    assert "magnet_presence/inspection.yaml:4 images: no such images directory" in error
    assert "qc_imgaes" in error


def test_a_case_without_images_or_expected_results_is_an_error(tmp_path: Path) -> None:
    case = tmp_path / "caps"
    shutil.copytree(CORPUS / "cap_locate_circle", case)
    (case / "expected.yaml").unlink()
    done = cli(str(case), cwd=tmp_path)
    assert done.returncode == 2
    out = _flat(done.stdout)
    assert "BAD CASE" in out  # listed, not silently passed
    assert "caps/expected.yaml: no expected.yaml" in out
    assert "1 bad case" in out
    # --update is how a new case gets its expected.yaml (to be checked, then committed).
    done = cli(str(case), "--update", cwd=tmp_path)
    assert done.returncode == 0, done.stdout
    assert len(load_case(case).expectations) == 6

    shutil.rmtree(case / "images")
    (case / "images").mkdir()
    (case / "expected.yaml").write_text("images: {}\n", encoding="utf-8")
    done = cli(str(case), "--json", cwd=tmp_path)
    assert done.returncode == 2
    error = json.loads(done.stdout)["cases"][0]["error"]
    assert error.startswith(f"{case / 'inspection.yaml'}: no images to test: {case / 'images'}")
    # --update records nothing for a case with nothing to record.
    done = cli(str(case), "--update", "--json", cwd=tmp_path)
    assert done.returncode == 2
    assert (case / "expected.yaml").read_text(encoding="utf-8") == "images: {}\n"


def test_a_pool_case_without_expectations_runs_the_whole_pool(presence_copy: Path) -> None:
    (presence_copy / "expected.yaml").write_text("images: {}\n", encoding="utf-8")
    done = cli(str(presence_copy), "--json", cwd=presence_copy.parent)
    assert done.returncode == 1  # new images, not a silent pass with 0 images
    images = json.loads(done.stdout)["cases"][0]["images"]
    assert len(images) == 9
    assert {i["status"] for i in images} == {"new"}
    done = cli(str(presence_copy), "--update", cwd=presence_copy.parent)
    assert done.returncode == 0, done.stdout
    written = load_case(presence_copy)
    assert len(written.expectations) == 9
    assert written.expectations["in_slot.png"].verdict == "pass"
    assert cli(str(presence_copy), cwd=presence_copy.parent).returncode == 0

    # A pool that is empty gives nothing to test: an error, and --update writes nothing.
    for image in (presence_copy.parent / "qc_images").iterdir():
        image.unlink()
    (presence_copy / "expected.yaml").write_text("images: {}\n", encoding="utf-8")
    done = cli(str(presence_copy), "--update", cwd=presence_copy.parent)
    assert done.returncode == 2
    assert "no images to test" in _flat(done.stdout)
    assert (presence_copy / "expected.yaml").read_text(encoding="utf-8") == "images: {}\n"


def test_a_case_may_name_an_inspection_of_a_cell_configuration(tmp_path: Path) -> None:
    case = load_case(CORPUS / "example_cell_magnet_check")
    assert case.inspection.name == "magnet_check"
    assert case.base_dir == (REPO / "examples").resolve()
    (tmp_path / "inspection.yaml").write_text(
        f"config: {REPO / 'examples' / 'cell.yaml'}\ninspection: no_such\n", encoding="utf-8"
    )
    with pytest.raises(Exception, match=r"inspection.yaml:2 inspection: cell.yaml has no"):
        load_case(tmp_path)


# --- comparisons ------------------------------------------------------------------------------


def test_features_are_matched_one_to_one_within_the_tolerance() -> None:
    expected = Expectation("x.png", "pass", features=((10.0, 10.0), (50.0, 50.0)))
    found = {"count": 2, "features": [{"u": 10.4, "v": 10.0}, {"u": 10.6, "v": 10.0}]}
    problems = compare(expected, Got("pass", found))
    assert problems == ["feature (50.0, 50.0) not found within 1.0 px (nearest 56.15 px)"]
    found["features"][1] = {"u": 50.5, "v": 49.5}
    assert compare(expected, Got("pass", found)) == []


def test_pose_and_value_tolerances() -> None:
    pose = np.eye(4)
    turned = np.eye(4)
    c, s = np.cos(0.05), np.sin(0.05)
    turned[:2, :2] = [[c, -s], [s, c]]
    turned[2, 3] = 0.003
    dt, dr = pose_error(pose, turned)
    assert dt == pytest.approx(0.003)
    assert dr == pytest.approx(0.05)
    tol = Tolerances(m=0.005, rad=0.02)
    expected = Expectation("p.png", "pass", camera_from_qr=tuple(map(tuple, pose)), tolerances=tol)
    problems = compare(expected, Got("pass", {"camera_from_qr": turned.tolist()}))
    assert problems == ["rotation off by 0.0500 rad (tolerance 0.02 rad)"]
    value = Expectation("v.png", "pass", value=0.5, tolerances=Tolerances(value=0.05))
    assert compare(value, Got("pass", {"value": 0.54})) == []
    assert compare(value, Got("error", {}, "BAD_IMAGE", "ROI outside"))[0].startswith(
        "verdict error, expected pass (BAD_IMAGE"
    )


def test_run_shares_the_offline_serving_path(capsys: pytest.CaptureFixture[str]) -> None:
    image = CORPUS / "example_cell_magnet_check" / "images" / "in_slot.png"
    config = REPO / "examples" / "cell.yaml"
    assert (
        main(["run", "--config", str(config), "magnet_check", "--image", str(image), "--json"]) == 0
    )
    result = json.loads(capsys.readouterr().out)
    assert result["verdict"] == "pass"
    assert result["data"]["measure"] == "dark_fraction"


# ----------------------------------------------------------------------------- per-type shapes


def test_each_inspection_type_declares_its_result_shape() -> None:
    """The golden runner and the summary readers (a PLC, a line protocol) take what a type's
    results hold from the type itself, for every configurable type."""
    from vision_server.inspections import INSPECTION_TYPES, RESULT_KINDS

    assert set(RESULT_KINDS) == set(INSPECTION_TYPES)
    located = {"count": 1, "features": [{"u": 10.123, "v": 20.0, "score": 0.9}]}
    assert RESULT_KINDS["locate"].expected(located) == {"count": 1, "features": [[10.12, 20.0]]}
    assert RESULT_KINDS["locate"].summary(located) == {"count": 1.0, "u": 10.123, "v": 20.0}
    assert RESULT_KINDS["presence"].summary({"value": 0.5}) == {"value": 0.5}
    assert RESULT_KINDS["qr"].expected({"found": False, "reason": "none"}) == {}
    pose = [[1.0, 0.0, 0.0, 0.1], [0.0, 1.0, 0.0, 0.2], [0.0, 0.0, 1.0, 0.3], [0, 0, 0, 1]]
    found = {"found": True, "text": "A", "corners": [[1, 2]] * 4, "camera_from_qr": pose}
    assert RESULT_KINDS["qr_pose"].summary(found) == {"found": 1.0, "x": 0.1, "y": 0.2, "z": 0.3}
    assert set(RESULT_KINDS["qr_pose"].expected(found)) == {"text", "corners", "camera_from_qr"}
