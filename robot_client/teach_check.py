"""Checks at teach time against the vision server: a record that names an inspection the
server does not have would only fail when the robot runs it, on the line.

A skill parameter names a server inspection when it is called ``inspection`` or ends in
``_inspection`` (``quality_control.inspection``, ``vision_pick.inspection``,
``qr_calibration.pose_inspection``). When the server answers, every such name must be one of
its inspections; when it cannot be reached the record is taught anyway (teaching offline is
allowed) and :func:`check_inspection_names` says that nothing was checked.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from protocol import CellvisionError

from .devices import DeviceError, Vision
from .errors import ClientError
from .skills.record import ParamError

__all__ = ["UnknownInspection", "check_inspection_names", "inspection_params"]


class UnknownInspection(ParamError):
    """A taught parameter names an inspection the server does not have."""


def inspection_params(params: Mapping[str, Any]) -> dict[str, str]:
    """The parameters of a record that name a server inspection (set, non-empty strings)."""
    return {
        key: value
        for key, value in params.items()
        if (key == "inspection" or key.endswith("_inspection")) and isinstance(value, str) and value
    }


def check_inspection_names(
    skill: str, params: Mapping[str, Any], vision: Vision | None
) -> str | None:
    """Refuse (:class:`UnknownInspection`) a parameter naming an inspection the server does not
    have. Returns None when checked (or nothing to check), else why it could not be checked
    (no vision server configured, or it cannot be reached)."""
    wanted = inspection_params(params)
    if not wanted:
        return None
    if vision is None:
        return "no vision server configured"
    try:
        listed = vision.list_inspections()
    except (ClientError, OSError, DeviceError, CellvisionError) as exc:
        return f"the vision server cannot be asked: {exc}"
    known = sorted(str(item.get("name")) for item in listed)
    for key, name in wanted.items():
        if name not in known:
            raise UnknownInspection(
                f"skill {skill!r}: {key}={name!r} is not an inspection of the vision server "
                f"(it has: {', '.join(known) or 'none'})"
            )
    return None
