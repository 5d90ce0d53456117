"""The integrator guide's commissioning chapter works on a copy outside git's view (integrator
finding 14): following it must not rewrite the tracked examples/commissioning.yaml nor leave
files that show in ``git status``, and the example must work from the copy's folder."""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest

from vision_server.cameras import SimCameraSettings
from vision_server.config import load_config

ROOT = Path(__file__).resolve().parents[2]
GUIDE = ROOT / "docs" / "integrator-guide.md"
EXAMPLE = ROOT / "examples" / "commissioning.yaml"
WRITTEN_BY_TOOLS = ("--config", "--store")  # the files the commissioning commands write


def _chapter_7_commands() -> list[list[str]]:
    """The shell commands of the guide's chapter 7 (continuation lines joined)."""
    text = GUIDE.read_text(encoding="utf-8")
    chapter = text[text.index("## 7. Commissioning") :]
    chapter = chapter[: chapter.index("\n## ", 1)] if "\n## " in chapter[1:] else chapter
    commands = []
    for block in re.findall(r"```sh\n(.*?)```", chapter, flags=re.S):
        for line in block.replace("\\\n", " ").splitlines():
            if line.strip():
                commands.append(shlex.split(line.rstrip("&")))
    return commands


def test_the_commissioning_commands_write_only_into_an_ignored_copy() -> None:
    commands = _chapter_7_commands()
    copies = [c for c in commands if c[:1] == ["mkdir"] or "cp" in c]
    assert copies, "chapter 7 must copy the example before it is commissioned"
    written = []
    for words in commands:
        if words[:1] not in (["robot-client"], ["vision-server"]):
            continue
        for option in WRITTEN_BY_TOOLS:
            if option in words:
                written.append(words[words.index(option) + 1])
    assert written, "no commissioning command found in chapter 7"
    for path in written:
        assert not path.startswith("examples/"), f"the guide writes into the tracked {path}"
    # The files written and their backups are ignored by git: `git status` stays clean.
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("no git checkout to ask")
    names = sorted({*written, *(f"{p}.bak" for p in written)})
    ignored = subprocess.run(
        ["git", "check-ignore", "--no-index", *names],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=False,
    ).stdout.split()
    assert sorted(ignored) == names, f"not ignored by git: {set(names) - set(ignored)}"


def test_the_example_works_from_its_copy_in_demo_output(tmp_path: Path) -> None:
    """The copy's relative paths (the fixed camera's scene, its state file) still resolve."""
    (tmp_path / "examples").symlink_to(ROOT / "examples", target_is_directory=True)
    (tmp_path / "demo-output").mkdir()
    copy = tmp_path / "demo-output" / "commissioning.yaml"
    shutil.copy(EXAMPLE, copy)
    for config in (load_config(EXAMPLE), load_config(copy)):
        overhead = config.cameras["overhead"]
        assert isinstance(overhead, SimCameraSettings)
        scene = config.base_dir / overhead.scene
        assert scene.is_file(), scene
        assert (config.base_dir / overhead.state_file).parent.name == "demo-output"
