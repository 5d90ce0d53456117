"""The ``mqtt:`` section (docs/configuration.md): defaults, secrets, and every mistake a clear
error naming the file, the line and the key; a spool that cannot be used stops the start,
naming the file; topics that no name can break."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
from loopback import run

from vision_server.app import App
from vision_server.config import ConfigError, ServerSettings, load_config
from vision_server.frontends import MqttSpoolError
from vision_server.frontends.mqtt import Outbox, OutboxRow, Topics, topic_level
from vision_server.service import builtin_catalog

HEAD = """\
cameras:
  tool: {source: request}
inspections:
  - {name: a, type: presence, camera: tool, measure: mean_intensity, min: 1}
"""


def cell(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "cell.yaml"
    path.write_text(HEAD + text, encoding="utf-8")
    return path


def test_defaults_and_the_spool_beside_the_configuration(tmp_path: Path) -> None:
    config = load_config(cell(tmp_path, "server: {name: press-3}\nmqtt: {enabled: true}\n"))
    mqtt = config.mqtt
    assert (mqtt.enabled, mqtt.host, mqtt.port, mqtt.cell) == (True, "127.0.0.1", 1883, "press-3")
    assert (mqtt.topic_prefix, mqtt.identifier) == ("cellvision", "cellvision-press-3")
    assert mqtt.spool == str(tmp_path / "mqtt-spool.sqlite")
    assert mqtt.spool_max_bytes == 100 * 2**20
    assert not load_config(cell(tmp_path, "")).mqtt.enabled


def test_tls_defaults_to_port_8883_and_the_password_comes_from_its_file(tmp_path: Path) -> None:
    (tmp_path / "pw").write_text("  hunter22\n")
    config = load_config(
        cell(tmp_path, "mqtt:\n  tls: {}\n  username: u\n  password_file: pw\n  spool: s/x.db\n")
    )
    assert (config.mqtt.tls, config.mqtt.port, config.mqtt.password) == (True, 8883, "hunter22")
    assert config.mqtt.spool == str(tmp_path / "s" / "x.db")


@pytest.mark.parametrize(
    ("section", "error"),
    [
        ("mqtt: {enabled: true, bogus: 1}", r"cell\.yaml:5 mqtt -> bogus: unknown key"),
        ("mqtt: {port: 70000}", r"mqtt -> port: expected a port in 1\.\.65535, got 70000"),
        ("mqtt: {port: 0}", r"mqtt -> port: expected a port in 1\.\.65535"),
        ("mqtt: {port: x}", r"mqtt -> port"),
        (
            "mqtt: {username: u, password_file: nowhere}",
            r"mqtt -> password_file: cannot read the token file .*nowhere",
        ),
        ("mqtt: {password: p}", r"mqtt -> username: a password needs its username"),
        (
            "mqtt: {username: u, password_env: CELLVISION_NO_SUCH_VARIABLE}",
            r"mqtt -> password_env: the environment variable 'CELLVISION_NO_SUCH_VARIABLE' is",
        ),
        ("mqtt: {cell: a/b}", r"mqtt -> cell: cell 'a/b' contains '/'"),
        ("mqtt: {cell: 'x+'}", r"mqtt -> cell: cell 'x\+' contains '\+'"),
        ("mqtt: {cell: ''}", r"mqtt -> cell: expected a non-empty string"),
        ("mqtt: {cell: $SYS}", r"mqtt -> cell: .*starts with '\$'"),
        ("mqtt: {topic_prefix: a//b}", r"mqtt -> topic_prefix: a level of the prefix is empty"),
        ("mqtt: {topic_prefix: 'a/#'}", r"mqtt -> topic_prefix: .*contains '#'"),
        (
            "server: {name: 'cell #1'}\nmqtt: {enabled: true}",
            r"mqtt -> cell: the cell's topic level defaults to server\.name.*give mqtt\.cell",
        ),
        ("mqtt: {tls: {ca: missing.pem}}", r"mqtt -> tls -> ca: no such file"),
        ("mqtt: {tls: {cert: c.pem}}", r"mqtt -> tls: a client certificate needs both"),
        ("mqtt: {tls: {ca: cell.yaml}}", r"mqtt -> tls -> ca: the files cannot make a TLS client"),
        ("mqtt: {spool_max_mb: 0}", r"mqtt -> spool_max_mb"),
        (
            "mqtt: {reconnect_min_s: 5, reconnect_max_s: 1}",
            r"mqtt -> reconnect_max_s: reconnect_max_s \(1\.0\) is less than",
        ),
    ],
)
def test_mistakes_are_configuration_errors_naming_the_key(
    tmp_path: Path, section: str, error: str
) -> None:
    with pytest.raises(ConfigError, match=error):
        load_config(cell(tmp_path, section + "\n"))


def test_without_the_extra_an_enabled_mqtt_is_a_configuration_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import vision_server.config.cell

    monkeypatch.setattr(vision_server.config.cell, "find_spec", lambda name: None)
    with pytest.raises(ConfigError, match=r"mqtt -> enabled: .*cellvision\[mqtt\]"):
        load_config(cell(tmp_path, "mqtt: {enabled: true}\n"))


def test_the_password_is_hidden_in_the_consoles_history() -> None:
    from vision_server.config import redact_secrets

    shown = redact_secrets("mqtt:\n  username: u\n  password: hunter22\n", lambda v: "f")
    assert "hunter22" not in shown
    assert "username: u" in shown


def test_a_corrupt_spool_stops_the_start_naming_the_file(tmp_path: Path) -> None:
    spool = tmp_path / "mqtt-spool.sqlite"
    spool.write_bytes(b"this is not a database, " * 100)
    config = load_config(cell(tmp_path, "mqtt: {enabled: true}\n"))
    app = App(builtin_catalog(), ServerSettings(port=0), mqtt=config.mqtt)
    with pytest.raises(MqttSpoolError, match=re.escape(str(spool))):
        run(app.start())
    # serve says it on stderr and exits 2 (a problem of the environment: nothing started).
    done = subprocess.run(
        [sys.executable, "-m", "vision_server", "serve", "--config", str(tmp_path / "cell.yaml")],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 2, done
    assert str(spool) in done.stderr
    assert "Traceback" not in done.stderr


def test_an_unwritable_spool_is_refused_naming_it(tmp_path: Path) -> None:
    blocker = tmp_path / "not-a-directory"
    blocker.write_text("x")
    with pytest.raises(MqttSpoolError, match="not-a-directory"):
        Outbox(blocker / "spool.sqlite", 1 << 20)


def test_topics_escape_what_would_add_a_level_or_match_as_a_wildcard() -> None:
    topics = Topics("plant/hall-2", "line-7")
    assert topics.state == "plant/hall-2/line-7/state"
    assert topics.result("bright") == "plant/hall-2/line-7/results/bright"
    assert topics.result("a/b+c#d%") == "plant/hall-2/line-7/results/a%2Fb%2Bc%23d%25"
    assert topic_level("") == "%"
    assert topic_level("$SYS") == "%24SYS"
    assert topics.results_filter == "plant/hall-2/line-7/results/+"


def test_the_outbox_keeps_order_and_seq_over_a_reopen_and_drops_the_oldest(
    tmp_path: Path,
) -> None:
    path = tmp_path / "o.sqlite"
    outbox = Outbox(path, 1000)
    for _ in range(3):
        seq = outbox.next_seq()
        assert outbox.add(OutboxRow(seq, f"u{seq}", "t", b"x" * 100)) == 0
    assert outbox.remove(2)
    assert not outbox.remove(2)
    outbox.close()
    outbox = Outbox(path, 1000)
    assert [r.seq for r in outbox.after(0, 10)] == [1, 3]
    assert outbox.next_seq() == 4
    # Rows of 100 + 1 + 64 bytes: 6 fit in 1000 (990); one of 365 more makes 1355, and the
    # three oldest (495 bytes) go.
    dropped = sum(outbox.add(OutboxRow(s, f"u{s}", "t", b"x" * 100)) for s in range(4, 8))
    assert dropped == outbox.dropped == 0  # 6 x 165 = 990
    assert outbox.add(OutboxRow(8, "u8", "t", b"x" * 300)) == 3
    assert [r.seq for r in outbox.after(0, 10)] == [5, 6, 7, 8]
    assert outbox.bytes <= 1000
    outbox.close()
    outbox = Outbox(path, 1000)
    assert outbox.next_seq() == 9
    outbox.close()


def test_the_server_does_not_import_aiomqtt_unless_mqtt_is_enabled() -> None:
    """aiomqtt is an optional extra: nothing else may need it."""
    code = (
        "import sys, vision_server.app, vision_server.commands.program, "
        "vision_server.frontends.mqtt; "
        "print('aiomqtt' in sys.modules, 'paho' in sys.modules)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert out.stdout.strip() == "False False"


def test_the_editors_schema_lists_exactly_the_keys_the_loader_takes(tmp_path: Path) -> None:
    """GET /api/schema's ``sections.mqtt``: each key (``tls.ca``: a key of ``tls:``) is one the
    loader accepts, every key it accepts is listed, and each bound is refused one beyond."""
    from vision_server.config import inspection_schema

    keys = inspection_schema()["sections"]["mqtt"]["keys"]
    listed = {k["key"] for k in keys}
    allowed: set[str] = set()
    for where, text in (("mqtt", "mqtt: {bogus: 1}\n"), ("mqtt.tls", "mqtt: {tls: {bogus: 1}}\n")):
        with pytest.raises(ConfigError) as error:
            load_config(cell(tmp_path, text))
        names = re.search(r"allowed here: (.*)\)", str(error.value))
        assert names is not None
        prefix = "" if where == "mqtt" else "tls."
        allowed |= {prefix + n for n in names.group(1).split(", ")}
    assert listed == allowed - {"tls"} | {"tls.ca", "tls.cert", "tls.key"}
    for k in keys:
        for bound, beyond in (("min", -1), ("max", 1)):
            if k[bound] is not None and k["kind"] == "integer":
                with pytest.raises(ConfigError, match=f"mqtt -> {k['key']}"):
                    load_config(cell(tmp_path, f"mqtt: {{{k['key']}: {k[bound] + beyond}}}\n"))


def test_ping_says_the_mqtt_state() -> None:
    from vision_server.commands.results import describe_health

    mqtt = {
        **{"ok": False, "broker": "b:1883", "connected": False, "spooled": 7, "published": 3},
        **{"dropped": 2, "spool_errors": 0, "last_error": "no connection to the broker b:1883"},
    }
    text = describe_health({"ok": False, "mqtt": mqtt})
    assert text == (
        "not ok; MQTT to b:1883 NOT CONNECTED, 7 spooled, 3 published, 2 dropped "
        "(no connection to the broker b:1883)"
    )


def test_a_payload_too_large_for_brokers_leaves_its_data_out_and_says_so() -> None:
    """A broker refusing a packet would get it again and again, holding back the results after
    it: past MAX_PAYLOAD_BYTES the data is left out, its size said; NaN is null."""
    import json
    import math

    from protocol import schema
    from vision_server.frontends.mqtt import MAX_PAYLOAD_BYTES, encode_result, result_payload
    from vision_server.service import InspectionRecord, InspectReply, InspectRequest

    def payload(data: dict[str, object]) -> dict[str, object]:
        reply = InspectReply("a", "tool", True, data, 1.0, 2.0, "abc", result_id=5)
        record = InspectionRecord(InspectRequest("a", peer="plc"), reply)
        uid = "0d8f3b4e-4b1d-4c53-9a53-3f1f0c8a9d2e"
        return result_payload(record, uid=uid, seq=1, cell="c", server="s", time_s=1.5e9)

    small = json.loads(encode_result(payload({"value": math.nan, "xs": (1, 2)})))
    schema.validate_mqtt("result", small)
    assert small["data"] == {"value": None, "xs": [1, 2]}
    assert "data_omitted" not in small
    huge = encode_result(payload({"values": list(range(MAX_PAYLOAD_BYTES // 4))}))
    assert len(huge) < 1000
    cut = json.loads(huge)
    schema.validate_mqtt("result", cut)
    assert cut["data"] == {}
    assert cut["data_omitted"] > MAX_PAYLOAD_BYTES
    assert cut["result_id"] == 5


def test_a_reload_says_that_mqtt_changes_wait_for_a_restart(tmp_path: Path) -> None:
    from vision_server.service import CellRuntime

    path = cell(tmp_path, "mqtt: {enabled: true, port: 1883}\n")
    runtime = CellRuntime(path)
    try:
        path.write_text(HEAD + "mqtt: {enabled: true, port: 1884}\n", encoding="utf-8")
        notes = runtime.reload().notes
    finally:
        runtime.close()
    assert "cell.yaml: changes under 'mqtt:' take effect after a restart" in notes


def test_two_servers_never_share_a_spool(tmp_path: Path) -> None:
    from vision_server.frontends.mqtt import Outbox, OutboxError

    first = Outbox(tmp_path / "mqtt-spool.sqlite", 1 << 20)
    try:
        with pytest.raises(OutboxError, match="in use by another running server"):
            Outbox(tmp_path / "mqtt-spool.sqlite", 1 << 20)
    finally:
        first.close()
    Outbox(tmp_path / "mqtt-spool.sqlite", 1 << 20).close()  # given back at close


def test_the_password_is_not_in_the_settings_repr() -> None:
    from vision_server.config import MqttSettings

    assert "s3cret" not in repr(MqttSettings(password="s3cret"))


def test_an_acknowledged_row_the_disk_cannot_delete_is_not_sent_again(tmp_path: Path) -> None:
    """A full disk made every delete fail: the session ended and every row went out again at
    each reconnect, for ever. An acknowledged row is now remembered and skipped, and deleted
    when the disk lets it."""
    import sqlite3

    from vision_server.frontends.mqtt import Outbox, OutboxRow

    outbox = Outbox(tmp_path / "mqtt-spool.sqlite", 1 << 20)
    try:
        for n in range(3):
            outbox.add(OutboxRow(outbox.next_seq(), f"uid-{n}", "cellvision/c/results/x", b"{}"))
        first, second, third = outbox.after(0, 10)
        real = outbox._conn

        class FullDisk:
            def execute(self, sql: str, *args: object) -> object:
                if sql.lstrip().startswith("DELETE"):
                    raise sqlite3.OperationalError("database or disk is full")
                return real.execute(sql, *args)

        outbox._conn = FullDisk()  # type: ignore[assignment]
        assert outbox.remove(first.seq) is True
        assert outbox.delete_errors == 1
        assert [r.seq for r in outbox.after(0, 10)] == [second.seq, third.seq]
        outbox._conn = real
        assert outbox.remove(second.seq) is True  # and the first one with it
        assert [r.seq for r in outbox.after(0, 10)] == [third.seq]
        assert outbox.rows == 1
    finally:
        outbox.close()
