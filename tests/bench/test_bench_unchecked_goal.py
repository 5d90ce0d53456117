"""The QR pose bench judges the unchecked sensor (nothing configured) as a goal of its own,
beside the sensor-checked one (issue 18 part 3): on the worst systematic sensor, and the
perfect sensor against its figure before the unchecked fusion."""

from __future__ import annotations

from typing import Any

from bench.calibration import (
    CHECK_KEYS,
    GOAL_T_MM,
    PERFECT_BEFORE_R_DEG,
    PERFECT_BEFORE_T_MM,
    SENSORS,
    UNCHECKED,
    _unchecked_goals,
)
from bench.common import Section


def _rows(t_mm: float, r_deg: float) -> dict[str, Any]:
    return {m: {"t": [t_mm] * 20, "r": [r_deg] * 20} for m in CHECK_KEYS}


def _goals(worst_t_mm: float, perfect_t_mm: float, perfect_r_deg: float = 0.1) -> list[Any]:
    checked = {
        s: _rows(0.2, 0.1) if s.systematic else _rows(perfect_t_mm, perfect_r_deg) for s in SENSORS
    }
    checked[SENSORS[-1]] = _rows(worst_t_mm, 0.1)  # one systematic sensor is the worst
    section = Section("calibration", "t")
    _unchecked_goals(section, checked)
    return [g for g in section.goals if "nothing configured" in g.what]


def test_the_worst_unchecked_sensor_decides_the_goal() -> None:
    met, perfect = _goals(GOAL_T_MM - 0.01, PERFECT_BEFORE_T_MM)
    assert met.met
    assert perfect.met
    assert SENSORS[-1].label in met.figure
    failed, _ = _goals(GOAL_T_MM + 0.01, PERFECT_BEFORE_T_MM)
    assert not failed.met  # one sensor over the goal fails it, however good the others
    assert UNCHECKED in CHECK_KEYS


def test_a_perfect_sensor_worse_than_before_fails_its_goal() -> None:
    _, perfect = _goals(0.2, PERFECT_BEFORE_T_MM + 0.01)
    assert not perfect.met


def test_the_perfect_sensor_is_judged_at_the_figures_precision() -> None:
    # the figures before were the report's, rounded to 3 decimals: the same rotation read
    # 0.1110x must not fail against 0.111
    _, perfect = _goals(GOAL_T_MM - 0.01, PERFECT_BEFORE_T_MM, PERFECT_BEFORE_R_DEG + 4e-4)
    assert perfect.met
    _, worse = _goals(GOAL_T_MM - 0.01, PERFECT_BEFORE_T_MM, PERFECT_BEFORE_R_DEG + 6e-4)
    assert not worse.met
