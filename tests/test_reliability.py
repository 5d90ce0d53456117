"""Quick runs of the reliability scripts (issue #8, items 1 and 2; issue 13's attack soak)
against a live server process.

The full runs (100,000 hostile frames; 64 clients x 500 requests) are measured by hand for
docs/bench/reliability.md. Here the scripts run small and without the 1 s answer bound (a test
makes no wall-clock assertions on a shared machine); hangs are still failures (10 s).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]


def _script(name: str, *args: str, out: Path) -> dict:
    done = subprocess.run(
        [sys.executable, str(REPO_ROOT / "scripts" / name), *args, "--json", str(out)],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    summary: dict = json.loads(out.read_text())
    assert summary["passed"], summary["problems"]
    return summary


def test_quick_soak_hostile_frames_and_good_clients(tmp_path: Path) -> None:
    frames = 1000
    s = _script(
        "soak.py",
        "--frames",
        str(frames),
        "--hostile",
        "3",
        "--good",
        "1",
        "--no-timing",
        out=tmp_path / "soak.json",
    )
    assert s["hostile_frames"] == frames
    assert s["hangs"] == 0
    assert s["untyped_errors"] == 0
    assert set(s["units_by_kind"]) >= {"bitflip", "truncate", "wrong_length", "huge_length"}
    assert set(s["units_by_kind"]) >= {"bad_json", "bad_blob", "bad_header", "garbage"}
    # Fatal framing errors and recoverable ones both happened, and were typed.
    assert {"MALFORMED_FRAME", "FRAME_TOO_LARGE", "BAD_METADATA", "BAD_IMAGE"} <= set(
        s["error_codes"]
    )
    good = s["good"]
    assert good["correct"] > 0
    assert (good["wrong"], good["errors"]) == (0, {})
    server = s["server"]
    assert (server["crashed"], server["exit_code"], server["tracebacks"]) == (False, 0, 0)
    assert s["alive_after"]


def test_quick_load_pipelined_clients_busy_and_a_slow_reader(tmp_path: Path) -> None:
    clients, requests = 8, 60
    s = _script(
        "load.py",
        "--clients",
        str(clients),
        "--requests",
        str(requests),
        out=tmp_path / "load.json",
    )
    assert s["answered_correctly"] == clients * requests
    assert (s["lost"], s["mismatched"]) == (0, 0)
    probe = s["busy_probe"]
    # Each answered once, by a RESULT or BUSY: beyond max_in_flight the server either refuses
    # or, under backpressure, reads the next request only once an earlier one is answered.
    assert probe["answered"] == probe["sent"]
    assert probe["busy"] + probe["results"] == probe["sent"]
    assert s["slow_reader"]["stopped_by_backpressure"]
    assert s["slow_reader"]["accepted_bytes"] < s["slow_reader"]["offered_bytes"]
    assert s["server"]["exit_code"] == 0


def test_quick_attack_soak_every_hole_of_issue_13(tmp_path: Path) -> None:
    """scripts/attack.py --quick: one bounded phase per attack against a `serve` process whose
    limits are small; `make soak` runs the long form. Per-phase results are checked here; the
    script itself fails on a wrong answer, a hang, a traceback, a bad exit or a VmHWM over the
    memory bound."""
    s = _script("attack.py", "--quick", out=tmp_path / "attack.json")
    phases = s["phases"]
    assert set(phases) >= {
        "image_bombs",
        "pre_hello_large",
        "half_bodies",
        "silent",
        "slow_bodies",
        "non_readers",
        "flood",
        "reload",
        "disk_full",
        # Issue 28's front door: the console, the line protocol and Modbus.
        "console_flood",
        "login_bodies",
        "line_before_token",
        "unread_answers",
        "modbus_idle",
        "token_guessing",
    }
    for name, phase in phases.items():
        assert (phase["wrong"], phase["hangs"]) == (0, 0), (name, phase["problems"])
        assert phase["correct"] > 0, name
        if name != "warmup":
            assert phase["figures"].get("good_after", True), name
    assert s["vm_hwm_kib"] <= s["memory_bound_kib"]["bound"]
    # Hidden or misstated image sizes refused before decoding; valid images at the limit served.
    assert {"IMAGE_TOO_LARGE", "BAD_IMAGE"} <= set(phases["image_bombs"]["errors"])
    # Bodies beyond the byte budget were refused at their header, the budget never exceeded.
    budget = s["limits"]["max_buffered_bytes"]
    assert phases["half_bodies"]["busy"] > 0
    assert phases["half_bodies"]["figures"]["buffered_bytes_peak"] <= budget
    assert phases["non_readers"]["figures"]["buffered_bytes_peak"] <= budget
    assert phases["non_readers"]["figures"]["dropped_all"]
    # Slots held by silent clients: a good client was refused, then served after the timeout.
    assert phases["silent"]["refused"] >= 1
    assert phases["flood"]["refused"] > 0
    assert phases["reload"]["figures"]["camera_unavailable"] == 0
    disk = phases["disk_full"]["figures"]
    assert disk["stored"]["false"] > 0
    assert disk["health_ok"] is False
    assert disk["rows_in_log"] == disk["stored"].get("true", 0)
    # Console connections past its limit closed at once, the robot served meanwhile.
    console = phases["console_flood"]["figures"]
    assert console["closed_at_once"] >= console["connections"] - s["limits"]["console_connections"]
    assert console["robot_requests"] > 0
    logins = phases["login_bodies"]["ends"]
    assert logins.get("huge:413")
    assert logins.get("stalled:408")
    assert phases["line_before_token"]["ends"].get("ER 8 no A <token> within")
    # Dropped, each: with a FIN, or with a RST when the server dropped it while requests the
    # client had sent were still unread on its side (the kernel resets such a close).
    unread = phases["unread_answers"]["ends"]
    assert set(unread) <= {"closed", "reset"}, unread
    assert sum(unread.values()) == phases["unread_answers"]["sent"] - 1
    assert phases["modbus_idle"]["figures"]["plc_polls"] > 1
    # Wrong tokens answered slowly (the per-guess delays are checked by the script), the right
    # one at once.
    guessing = phases["token_guessing"]["figures"]
    assert guessing["guesses_per_s"] < 5
    assert max(guessing["right_token_s"].values()) < 1.0
    assert (s["server"]["exit_code"], s["server"]["tracebacks"]) == (0, 0)
