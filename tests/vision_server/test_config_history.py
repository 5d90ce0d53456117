"""The configuration file's history (vision_server/config/history.py) and the one writer of the
file (``http_save.write_version``): versions with who, when and why, bounded on disk, no
half version after a failing write, edits made outside the console recorded, and ``undo``."""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path
from typing import Any

import pytest

from vision_server.config import files, history
from vision_server.frontends import http_save

ONE = """\
# the cell
inspections:
  - name: a
    type: presence
    camera: qc
    threshold: 90
  - name: b
    type: presence
    camera: qc
"""
TWO = ONE.replace("threshold: 90", "threshold: 100")


@pytest.fixture
def config(tmp_path: Path) -> Path:
    path = tmp_path / "cell.yaml"
    path.write_text(ONE, encoding="utf-8")
    return path


def write(path: Path, text: str, **kw: Any) -> history.Version:
    return http_save.write_version(path, text, **kw)


def test_the_first_write_records_the_file_as_found_then_the_new_text(config: Path) -> None:
    version = write(config, TWO, who="integrator", why="darker magnets")
    assert config.read_text() == TWO
    kept = history.History(config)
    assert kept.numbers() == [1, 2]
    first, second = kept.get(1), kept.get(2)
    assert (first.kind, first.who, first.why) == ("original", "unknown", "")
    assert kept.text(1).decode() == ONE
    assert (second.kind, second.who, second.why) == ("save", "integrator", "darker magnets")
    assert version == second
    assert second.inspections == ("a",)  # b unchanged
    assert second.config_hash == history.config_hash(TWO.encode())
    assert kept.text(2).decode() == TWO
    assert [v.number for v in kept.versions()] == [2, 1]  # newest first
    diff = kept.diff(2)
    assert "-    threshold: 90\n" in diff
    assert "+    threshold: 100\n" in diff
    assert diff.startswith("--- version 1\n+++ version 2\n")
    # The history's folder is beside the file, the owner's alone.
    assert kept.folder == config.with_name("cell.yaml.history")
    assert kept.folder.stat().st_mode & 0o777 == 0o700


def test_an_edit_made_outside_the_console_is_recorded_before_the_next_save(config: Path) -> None:
    write(config, TWO, who="integrator", why="first")
    by_hand = TWO + "  - name: c\n    type: presence\n    camera: qc\n"
    config.write_text(by_hand, encoding="utf-8")
    write(config, by_hand.replace("threshold: 100", "threshold: 110"), who="admin", why="again")
    kept = history.History(config)
    assert kept.numbers() == [1, 2, 3, 4]
    outside = kept.get(3)
    assert (outside.kind, outside.who) == ("edited_outside", "unknown")
    assert outside.inspections == ("c",)
    assert kept.text(3).decode() == by_hand
    assert kept.get(4).inspections == ("a",)
    # No edit since: no extra version.
    write(config, ONE, who="admin", why="back")
    assert kept.numbers() == [1, 2, 3, 4, 5]
    assert kept.get(5).inspections == ("a", "c")  # changed, removed


def test_a_text_that_does_not_parse_is_kept_and_said_so(config: Path) -> None:
    config.write_text("inspections: [\n", encoding="utf-8")
    write(config, ONE, who="admin", why="fixed the file")
    kept = history.History(config)
    assert not kept.get(1).parsed
    assert kept.get(1).inspections == ()
    assert kept.get(2).parsed
    assert kept.get(2).inspections == ()


@pytest.mark.parametrize(
    ("bounds", "kept_count"),
    [(history.Bounds(max_versions=5), 5), (history.Bounds(max_bytes=2000), None)],
)
def test_bounds_drop_the_oldest_and_nothing_else(
    config: Path, bounds: history.Bounds, kept_count: int | None
) -> None:
    history.set_bounds(config, bounds)
    folder = config.with_name("cell.yaml.history")
    folder.mkdir()
    (folder / "notes.txt").write_text("mine")
    (folder / "v1.version").write_text("not ours: the name has too few digits")
    outside = config.parent / "v000001.version"
    outside.write_text("beside the folder")
    texts = {}
    for i in range(12):
        text = ONE.replace("threshold: 90", f"threshold: {91 + i}")
        texts[write(config, text, who="w", why=f"step {i}").number] = text
    kept = history.History(config)
    numbers = kept.numbers()
    assert numbers[-1] == 13  # the file as found was 1
    assert numbers == list(range(numbers[0], 14))  # the oldest went first
    if kept_count is not None:
        assert len(numbers) == kept_count
    else:
        sizes = sum((folder / f"v{n:06d}.version").stat().st_size for n in numbers)
        one = (folder / f"v{numbers[0]:06d}.version").stat().st_size
        assert sizes <= 2000 < sizes + one  # one more (as large) would not fit
        assert 1 < len(numbers) < 13
    for number in numbers:
        assert kept.text(number).decode() == texts[number]
    assert (folder / "notes.txt").read_text() == "mine"
    assert (folder / "v1.version").exists()
    assert outside.read_text() == "beside the folder"


def test_the_newest_is_kept_whatever_its_size(config: Path) -> None:
    history.set_bounds(config, history.Bounds(max_bytes=10))
    write(config, TWO, who="w", why="big")
    assert history.History(config).numbers() == [2]


class FailingFsync:
    """``os`` whose fsync of the ``nth`` temporary file fails after cutting it in half (a disk
    that filled up mid-write)."""

    def __init__(self, nth: int) -> None:
        self.nth = nth
        self.seen = 0

    def __getattr__(self, name: str) -> Any:
        return getattr(os, name)

    def fsync(self, fd: int) -> None:
        if os.readlink(f"/proc/self/fd/{fd}").endswith(".tmp"):
            self.seen += 1
            if self.seen == self.nth:
                os.ftruncate(fd, os.fstat(fd).st_size // 2)
                raise OSError(errno.ENOSPC, "No space left on device")
        os.fsync(fd)


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="needs /proc/self/fd")
@pytest.mark.parametrize("nth", [1, 2])
def test_a_failing_write_leaves_no_half_version_and_the_file_as_it_was(
    config: Path, monkeypatch: pytest.MonkeyPatch, nth: int
) -> None:
    """1: the new version's write fails; 2: the configuration's (after the version)."""
    write(config, TWO, who="w", why="first")
    folder = config.with_name("cell.yaml.history")
    listed = sorted(p.name for p in folder.iterdir())
    failing = FailingFsync(nth)
    monkeypatch.setattr(files, "os", failing)
    with pytest.raises(OSError, match="No space left"):
        write(config, ONE, who="w", why="fails")
    monkeypatch.undo()
    assert config.read_text() == TWO
    assert sorted(p.name for p in folder.iterdir()) == listed  # no temporary file either
    assert not [p for p in config.parent.iterdir() if p.name.endswith(".tmp")]
    assert write(config, ONE, who="w", why="works").number == 3


def test_undo_puts_the_old_text_back_and_drops_the_version(config: Path) -> None:
    write(config, TWO, who="w", why="first")
    old = config.read_bytes()
    version = write(config, ONE, old=old, who="w", why="the server refuses it")
    http_save.undo(http_save.Saved(config, old, version))
    assert config.read_bytes() == old
    kept = history.History(config)
    assert kept.numbers() == [1, 2]
    # The history ends with the file's text: the next write records no "edited outside".
    assert write(config, ONE, who="w", why="again").number == 3
    assert kept.numbers() == [1, 2, 3]


def test_a_version_file_is_metadata_then_the_text_byte_for_byte(config: Path) -> None:
    text = ONE + "# ünïcode, a tab\t and \\r\\n\r\n"
    write(config, text, who="w" * 300, why="é" * 900)
    raw = (config.with_name("cell.yaml.history") / "v000002.version").read_bytes()
    header, _, body = raw.partition(b"\n")
    meta = json.loads(header)
    assert body == text.encode("utf-8")
    assert len(meta["who"]) == 100
    assert len(meta["why"]) == history.MAX_WHY


def test_reading_never_writes_and_unknown_versions_are_named(tmp_path: Path) -> None:
    kept = history.History(tmp_path / "cell.yaml")
    assert kept.versions() == []
    assert kept.newest() is None
    assert not kept.folder.exists()
    with pytest.raises(history.UnknownVersion, match="no version 4"):
        kept.text(4)
    with pytest.raises(history.UnknownVersion):
        kept.get(0)


def test_a_history_folder_that_is_a_link_is_refused(config: Path, tmp_path: Path) -> None:
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    config.with_name("cell.yaml.history").symlink_to(elsewhere)
    with pytest.raises(history.HistoryError, match="symbolic link"):
        write(config, TWO, who="w", why="x")
    assert config.read_text() == ONE
    assert list(elsewhere.iterdir()) == []


def test_paging_newest_first(config: Path) -> None:
    for i in range(7):
        write(config, ONE.replace("90", str(i)), who="w", why=str(i))
    kept = history.History(config)
    assert [v.number for v in kept.versions(limit=3)] == [8, 7, 6]
    assert [v.number for v in kept.versions(before=6, limit=3)] == [5, 4, 3]
    assert [v.number for v in kept.versions(before=3, limit=3)] == [2, 1]


def test_a_write_a_crash_cut_short_leaves_a_temporary_file_the_next_write_sweeps(
    config: Path,
) -> None:
    write(config, TWO, who="w", why="first")
    folder = config.with_name("cell.yaml.history")
    stale = folder / ".abc123.tmp"
    stale.write_bytes(b'{"version": 3')  # half a version, never listed
    fresh = folder / ".def456.tmp"  # a write in progress elsewhere: left alone
    fresh.write_bytes(b"")
    old = stale.stat().st_mtime - history.STALE_TMP_S - 10
    os.utime(stale, (old, old))
    assert history.History(config).numbers() == [1, 2]
    write(config, ONE, who="w", why="next")
    assert not stale.exists()
    assert fresh.exists()
    assert history.History(config).numbers() == [1, 2, 3]
