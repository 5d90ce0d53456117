"""``results: {url: postgresql://...}`` in the configuration: what is accepted, and a clear error
naming the key for what is not (no database is needed to check a configuration)."""

from __future__ import annotations

from pathlib import Path

import pytest

from vision_server.commands.results import describe_health
from vision_server.config import ConfigError, load_config
from vision_server.results import redact_url
from vision_server.service import check_result_log

CELL = """\
{results}
cameras: {{tool: {{source: request}}}}
inspections:
  - {{name: bright, type: presence, camera: tool, measure: mean_intensity, min: 0}}
"""
URL = "postgresql://cell@db.plant:5432/vision"


def load(tmp_path: Path, results: str) -> object:
    path = tmp_path / "cell.yaml"
    path.write_text(CELL.format(results=results))
    return load_config(path)


def test_a_url_selects_postgresql_with_a_spool_beside_the_configuration(tmp_path: Path) -> None:
    config = load(tmp_path, f"results: {{url: '{URL}'}}")
    results = config.results  # type: ignore[attr-defined]
    assert (results.url, results.path, results.store_images) == (URL, None, "none")
    assert results.spool == tmp_path / "results-spool.sqlite3"
    assert results.enabled
    check_result_log(config)  # type: ignore[arg-type]  # creates nothing, connects nowhere
    assert not results.spool.exists()
    off = load(tmp_path, f"results: {{url: '{URL}', enabled: false}}")
    assert not off.results.enabled  # type: ignore[attr-defined]


@pytest.mark.parametrize(
    ("results", "key", "cause"),
    [
        ("results: {url: 'mysql://x/y'}", "url", "expected a PostgreSQL URL"),
        (f"results: {{url: '{URL}', path: r.sqlite3}}", "path", "not both"),
        (f"results: {{url: '{URL}', store_images: failures}}", "store_images", "keeps no images"),
        (f"results: {{url: '{URL}', max_image_mb: 5}}", "max_image_mb", "keeps no images"),
        ("results: {spool: s.sqlite3}", "spool", "give url too"),
    ],
)
def test_a_wrong_results_section_names_its_key(
    tmp_path: Path, results: str, key: str, cause: str
) -> None:
    with pytest.raises(ConfigError, match=cause) as caught:
        load(tmp_path, results)
    assert f"results -> {key}" in str(caught.value)


def test_a_spool_that_cannot_be_created_is_a_configuration_error(tmp_path: Path) -> None:
    (tmp_path / "blocker").write_text("a file where the spool's folder should be")
    config = load(tmp_path, f"results: {{url: '{URL}', spool: blocker/spool.sqlite3}}")
    with pytest.raises(ConfigError, match="results -> url.*Not a directory"):
        check_result_log(config)  # type: ignore[arg-type]


def test_passwords_stay_out_of_messages_and_ping_shows_the_spool() -> None:
    assert redact_url("postgresql://cell:s3cret@db:5432/v") == "postgresql://cell:***@db:5432/v"
    assert redact_url(URL) == URL
    health = {"ok": True, "result_log": {"ok": True, "written": 4, "failed": 0, "spooled": 7}}
    assert "7 spooled for the database (DOWN)" in describe_health(health)
