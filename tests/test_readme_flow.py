"""The README's "Using it by hand" flow, run as a user runs it: every command of its shell block,
in order, through subprocess, in a temporary copy of the checkout (a git repository of its own),
on a fresh checkout and after ``make demo`` (``python -m robot_client.demo``, what the Makefile
runs). The task must end ``done`` both times, the magnet check must say what the README says,
and nothing the tools wrote may show in ``git status``.

The only change to the commands: ``vision-server serve`` gets ``--port 0`` and port 0 for each
front-end its configuration enables, ``--console-port 0`` for the example's console (the
README's 7878 and 7880 may be taken on a shared machine, by the very server this section leaves
running among others), and the client finds it through ``$CELLVISION_SERVER``, the way the
README says both tools find the server."""

from __future__ import annotations

import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from example_servers import on_any_port_as_typed, readme_commands

REPO = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent  # where the project's console scripts are installed
# What the flow needs from the checkout: the code, the example cell, the ignore rules.
COPIED = (
    "protocol",
    "vision_server",
    "robot_client",
    "simulation",
    "geometry",
    "wireio",
    "examples",
)
TIMEOUT_S = 300  # a hung process fails the test instead of blocking it; no verdict depends on it

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(shutil.which("git") is None, reason="needs git (to copy the checkout)"),
]


def executable(word: str) -> str:
    """``.venv/bin/robot-client`` -> the console script of the Python running the tests."""
    name = word.removeprefix(".venv/bin/")
    assert name != word, f"README command does not start with .venv/bin/: {word}"
    path = BIN / name
    assert path.exists(), f"{name}: not installed beside {sys.executable}"
    return str(path)


def checkout_copy(root: Path) -> Path:
    """The checkout's tracked and new files (as they are on disk) copied into a fresh git
    repository with one commit, so ``git status`` there shows exactly what the flow wrote."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard", "--", *COPIED],
        cwd=REPO,
        capture_output=True,
        check=True,
    ).stdout.split(b"\0")
    copy = root / "checkout"
    for raw in filter(None, listed):
        source = REPO / os.fsdecode(raw)
        if source.is_file():  # a deleted file is still listed until the deletion is staged
            (copy / source.relative_to(REPO)).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, copy / source.relative_to(REPO))
    for name in ("README.md", ".gitignore", "pyproject.toml"):
        shutil.copy2(REPO / name, copy / name)
    git(copy, "init", "-q")
    git(copy, "add", "-A")
    git(copy, "commit", "-q", "-m", "checkout")
    return copy


def git(cwd: Path, *args: str) -> str:
    env = {**os.environ, "GIT_CONFIG_GLOBAL": os.devnull, "GIT_CONFIG_NOSYSTEM": "1"}
    command = ["git", "-c", "user.name=test", "-c", "user.email=test@example.invalid", *args]
    return subprocess.run(
        command, cwd=cwd, env=env, capture_output=True, text=True, check=True
    ).stdout


def user_env(copy: Path) -> dict[str, str]:
    """The user's environment: the copy's code first, no cellvision settings of our own."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("CELLVISION_")}
    env["PYTHONPATH"] = str(copy)
    env["COLUMNS"] = "200"  # keep Rich's lines whole in the captured output
    return env


@contextmanager
def serving(command: list[str], copy: Path, env: dict[str, str]) -> Iterator[str]:
    """The README's ``serve`` command on port 0 (its console too) in the background: yields
    HOST:PORT from its first line; stopped with SIGTERM (what Ctrl-C in the second terminal
    amounts to)."""
    process = subprocess.Popen(
        on_any_port_as_typed(command, copy),
        cwd=copy,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        assert process.stdout is not None
        line = process.stdout.readline()  # returns at the first line, or "" if it died
        match = re.search(r"listening on (\S+:\d+)", line)
        assert match, f"the vision server did not start: {line!r}"
        yield match.group(1)
    finally:
        process.send_signal(signal.SIGTERM)
        try:
            process.communicate(timeout=TIMEOUT_S)
        except subprocess.TimeoutExpired:
            process.kill()
            process.communicate()


def run_readme_flow(copy: Path) -> list[subprocess.CompletedProcess[str]]:
    """Every README command in order; the server in the background from its line on."""
    env = user_env(copy)
    commands = [[executable(c[0]), *c[1:]] for c in readme_commands()]
    serve = next(i for i, c in enumerate(commands) if c[1:2] == ["serve"])
    done = [
        subprocess.run(c, cwd=copy, env=env, capture_output=True, text=True, timeout=TIMEOUT_S)
        for c in commands[:serve]
    ]
    with serving(commands[serve], copy, env) as address:
        env["CELLVISION_SERVER"] = address
        for c in commands[serve + 1 :]:
            done.append(
                subprocess.run(
                    c, cwd=copy, env=env, capture_output=True, text=True, timeout=TIMEOUT_S
                )
            )
    return done


def by_name(done: list[subprocess.CompletedProcess[str]]) -> dict[str, list[int]]:
    """Exit codes per command (``task run``, ``inspect``, ...), in order."""
    codes: dict[str, list[int]] = {}
    for p in done:
        words = [w for w in p.args[1:3] if not w.startswith("-")]
        name = " ".join(words[:2]) if words[:1] == ["task"] else words[0]
        codes.setdefault(name, []).append(p.returncode)
    return codes


def explain(done: list[subprocess.CompletedProcess[str]]) -> str:
    return "\n".join(
        f"$ {shlex.join(p.args)}\n-> {p.returncode}\n{p.stdout}{p.stderr}" for p in done
    )


def test_the_readme_shows_the_flow_this_test_runs() -> None:
    commands = readme_commands()
    names = [c[1] if c[0].endswith("vision-server") else " ".join(c[1:3]) for c in commands]
    assert names[:2] == ["check-config", "serve"]
    assert any(n.startswith("task run") for n in names)


def test_by_hand_on_a_fresh_checkout(tmp_path: Path) -> None:
    copy = checkout_copy(tmp_path)
    done = run_readme_flow(copy)
    codes = by_name(done)
    assert codes["check-config"] == [0], explain(done)
    assert codes["ping"] == [0], explain(done)
    assert codes["inspections"] == [0], explain(done)
    # The magnet waits in its feeder until the task's fresh cell has it delivered.
    assert codes["inspect"] == [1, 0], explain(done)
    assert codes["task run"] == [0], explain(done)
    task = next(p for p in done if "task" in p.args)
    assert "task grundfos-demo: done, 12 steps, 0 failed" in task.stdout, explain(done)
    assert (copy / "demo-output" / "magnet.png").stat().st_size > 0  # the overlay was written
    assert git(copy, "status", "--porcelain", "--untracked-files=all") == ""

    # By hand once more, on the world the first run left (caps in the bin): --fresh again.
    again = by_name(run_readme_flow(copy))
    assert again["task run"] == [0]
    assert again["inspect"] == [0, 0]
    assert git(copy, "status", "--porcelain", "--untracked-files=all") == ""


def test_by_hand_after_make_demo(tmp_path: Path) -> None:
    copy = checkout_copy(tmp_path)
    demo = subprocess.run(
        [sys.executable, "-m", "robot_client.demo", "--no-live"],
        cwd=copy,
        env=user_env(copy),
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
    )
    assert demo.returncode == 0, demo.stdout + demo.stderr
    assert (copy / "demo-output" / "world-state.json").exists()  # the state the flow continues
    done = run_readme_flow(copy)
    codes = by_name(done)
    assert codes["inspect"] == [0, 0], explain(done)  # the demo's station delivered the magnet
    assert codes["task run"] == [0], explain(done)
    task = next(p for p in done if "task" in p.args)
    assert "task grundfos-demo: done, 12 steps, 0 failed" in task.stdout, explain(done)
    assert git(copy, "status", "--porcelain", "--untracked-files=all") == ""
