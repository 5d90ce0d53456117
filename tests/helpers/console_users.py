"""The example cell with named console users (``server: users:``) and preset reasons for the
operator's answers (``console: operator_reasons``), for the tests of named operators."""

from __future__ import annotations

from pathlib import Path

from console_server import TOKEN, example_config

from vision_server.config import hash_secret

ANNA_PIN = "4711"
BEN_BADGE = "04A1B2C3D4"
CARLA_PIN = "93817"
DORA_BADGE = "badge-of-dora-0001"
PRESETS = ["cosmetic only", "within drawing tolerance"]


def users_yaml() -> str:
    """anna: operator, hashed PIN; ben: operator, plain badge; Carla: integrator, plain PIN;
    dora: operator, hashed badge."""
    return (
        "[{name: anna, role: operator, pin_hash: '" + hash_secret(ANNA_PIN) + "'}, "
        "{name: ben, badge: '" + BEN_BADGE + "'}, "
        "{name: Carla, role: integrator, pin: '" + CARLA_PIN + "'}, "
        "{name: dora, role: operator, badge_hash: '" + hash_secret(DORA_BADGE) + "'}]"
    )


def config_with_users(folder: Path, *, token: str | None = TOKEN) -> Path:
    """The example cell in ``folder`` with the users above and the preset reasons."""
    path = example_config(folder, token=token, extra_server=f"  users: {users_yaml()}\n")
    text = path.read_text(encoding="utf-8").replace(
        "  max_view_fps: 30\n",
        "  max_view_fps: 30\n  operator_reasons: [" + ", ".join(PRESETS) + "]\n",
        1,
    )
    path.write_text(text, encoding="utf-8")
    return path
