"""What people do through the console is in ``vision-server serve``'s log without
``--verbose`` (the ``vision_server.audit`` logger): a save with its who and why, here from the
real command, its console found on the line it prints."""

from __future__ import annotations

import re
import signal
import subprocess
from pathlib import Path

from cli_tools import LISTENING, REPO_ROOT, TOOLS, _env
from console_server import TOKEN, Browserless, example_config

CONSOLE = re.compile(r".*web console on (http://\S+)\n")


def test_a_save_is_in_the_servers_log_with_who_and_why(tmp_path: Path) -> None:
    config = example_config(tmp_path)
    proc = subprocess.Popen(
        [*TOOLS["vision-server"], "serve", "--config", str(config)],
        cwd=REPO_ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
    )
    try:
        assert proc.stdout is not None
        assert LISTENING.fullmatch(proc.stdout.readline())
        console = CONSOLE.fullmatch(proc.stdout.readline())
        assert console, "no console address printed"
        client = Browserless(console[1])
        assert client.login(TOKEN).status == 200
        saved = client.post_json(
            "/api/inspections/magnet_check/save",
            {"options": {"threshold": 101}, "why": "darker magnets from the new supplier"},
        )
        assert saved.status == 200, saved.body
    finally:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    line = next((ln for ln in err.splitlines() if "vision_server.audit" in ln), "")
    assert "admin saved threshold of 'magnet_check' as version" in line, err
    assert '"darker magnets from the new supplier"' in line
