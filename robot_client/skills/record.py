"""Typed skill parameters and the taught record (what the teach phase produces).

In a record, parameter values are plain YAML/JSON values: a pose is ``{xyz: [x, y, z],
rpy: [roll, pitch, yaw]}`` (metres, radians; ``R = Rz(yaw) Ry(pitch) Rx(roll)``) or
``{matrix: 4x4 rows}``; a position is ``[x, y, z]``. :meth:`Param.decode` gives the typed value
(a 4x4 float64 array for a pose, a (3,) array for a position).
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray

from geometry import transform_from_xyz_rpy, xyz_rpy_from_transform

__all__ = [
    "REQUIRED",
    "Param",
    "ParamError",
    "ParamType",
    "TaughtRecord",
    "pose_to_yaml",
    "pose_from_yaml",
    "utc_now_iso",
]

FloatArray = NDArray[np.float64]
REQUIRED: Any = object()  # sentinel: a parameter without a default
_DIGITS = 9  # nanometres / nanoradians: readable files, no information lost that matters


class ParamError(ValueError):
    """A parameter value that does not fit its declaration (the message names the parameter)."""


class ParamType(StrEnum):
    FLOAT = "float"
    INT = "int"
    STR = "str"
    BOOL = "bool"
    POSE = "pose"  # 4x4 frame_from_tool
    POSITION = "position"  # (3,) point
    FLOATS = "floats"  # list of numbers


def _round(x: float) -> float:
    return round(float(x), _DIGITS) + 0.0  # + 0.0 turns -0.0 into 0.0


def pose_to_yaml(pose: ArrayLike) -> dict[str, list[float]]:
    """A 4x4 pose as ``{xyz: [...], rpy: [...]}``."""
    xyz, rpy = xyz_rpy_from_transform(np.asarray(pose, np.float64))
    return {"xyz": [_round(v) for v in xyz], "rpy": [_round(v) for v in rpy]}


def _numbers(value: Any, n: int | None, what: str) -> list[float]:
    if not isinstance(value, list | tuple | np.ndarray):
        raise ParamError(f"{what}: expected a list of numbers, got {value!r}")
    out = []
    for v in value:
        if (
            isinstance(v, bool)
            or not isinstance(v, int | float | np.number)
            or not math.isfinite(float(v))
        ):
            raise ParamError(f"{what}: expected finite numbers, got {v!r}")
        out.append(float(v))
    if n is not None and len(out) != n:
        raise ParamError(f"{what}: expected {n} numbers, got {len(out)}")
    return out


def pose_from_yaml(value: Any, what: str = "pose") -> FloatArray:
    """``{xyz, rpy}``, ``{matrix}`` or a 4x4 nested list → 4x4 float64 (ParamError if bad)."""
    if isinstance(value, np.ndarray) and value.shape == (4, 4):
        mat = value.astype(np.float64)
    elif isinstance(value, Mapping):
        keys = set(value)
        if keys == {"xyz", "rpy"}:
            xyz = _numbers(value["xyz"], 3, f"{what}.xyz")
            rpy = _numbers(value["rpy"], 3, f"{what}.rpy")
            return transform_from_xyz_rpy(xyz, rpy)
        if keys == {"matrix"}:
            return pose_from_yaml(value["matrix"], f"{what}.matrix")
        raise ParamError(
            f"{what}: a pose has keys xyz and rpy (or matrix), got "
            f"{', '.join(sorted(keys)) or 'none'}"
        )
    elif isinstance(value, list | tuple) and len(value) == 4:
        mat = np.array([_numbers(row, 4, f"{what} row {i}") for i, row in enumerate(value)])
    else:
        raise ParamError(f"{what}: expected a pose {{xyz: [...], rpy: [...]}}, got {value!r}")
    rot = mat[:3, :3]
    if (
        not np.all(np.isfinite(mat))
        or not np.allclose(mat[3], [0, 0, 0, 1])
        or not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6)
        or np.linalg.det(rot) < 0
    ):
        raise ParamError(f"{what}: not a rigid transform")
    return mat


@dataclass(frozen=True)
class Param:
    """One skill parameter: ``name``, ``type``, ``unit`` ("m", "rad", "s", "" …), ``doc``, a
    ``default`` (REQUIRED: none), and for numbers optional ``minimum``/``maximum``."""

    name: str
    type: ParamType
    doc: str = ""
    unit: str = ""
    default: Any = REQUIRED
    minimum: float | None = None
    maximum: float | None = None

    @property
    def required(self) -> bool:
        return self.default is REQUIRED

    def encode(self, value: Any) -> Any:
        """A typed or plain value → the plain YAML value stored in a record (validated)."""
        what = f"parameter {self.name!r}"
        if value is None and self.default is None:
            return None  # an optional parameter left unset
        match self.type:
            case ParamType.POSE:
                return pose_to_yaml(pose_from_yaml(value, what))
            case ParamType.POSITION:
                seq = value.reshape(-1).tolist() if isinstance(value, np.ndarray) else value
                return [_round(v) for v in _numbers(seq, 3, what)]
            case ParamType.FLOATS:
                return [_round(v) for v in _numbers(value, None, what)]
            case ParamType.FLOAT:
                if isinstance(value, bool) or not isinstance(value, int | float | np.number):
                    raise ParamError(f"{what}: expected a number, got {value!r}")
                x = float(value)
                if not math.isfinite(x):
                    raise ParamError(f"{what}: expected a finite number, got {value!r}")
                self._check_range(x, what)
                return _round(x)
            case ParamType.INT:
                if isinstance(value, bool) or not isinstance(value, int | np.integer):
                    raise ParamError(f"{what}: expected an integer, got {value!r}")
                self._check_range(float(value), what)
                return int(value)
            case ParamType.BOOL:
                if not isinstance(value, bool):
                    raise ParamError(f"{what}: expected true or false, got {value!r}")
                return value
            case ParamType.STR:
                if not isinstance(value, str):
                    raise ParamError(f"{what}: expected a string, got {value!r}")
                return value
        raise AssertionError(self.type)  # pragma: no cover

    def _check_range(self, x: float, what: str) -> None:
        if self.minimum is not None and x < self.minimum:
            raise ParamError(f"{what}: {x:g} is below the minimum {self.minimum:g} {self.unit}")
        if self.maximum is not None and x > self.maximum:
            raise ParamError(f"{what}: {x:g} is above the maximum {self.maximum:g} {self.unit}")

    def decode(self, plain: Any) -> Any:
        """The stored plain value → the typed value skills use."""
        value = self.encode(plain)
        if value is None:
            return None
        if self.type is ParamType.POSE:
            return pose_from_yaml(value)
        if self.type is ParamType.POSITION:
            return np.array(value, np.float64)
        return value

    def parse_text(self, text: str) -> Any:
        """A value typed on the command line → plain value. Poses: ``x,y,z,roll,pitch,yaw``
        or YAML (``{xyz: [..], rpy: [..]}``); numbers and lists: YAML."""
        if self.type is ParamType.STR:
            return text
        if self.type is ParamType.POSE and "{" not in text and "[" not in text:
            numbers = [t for t in text.replace(",", " ").split() if t]
            try:
                values = [float(t) for t in numbers]
            except ValueError:
                raise ParamError(
                    f"parameter {self.name!r}: a pose is x,y,z,roll,pitch,yaw (m, rad), "
                    f"got {text!r}"
                ) from None
            if len(values) != 6:
                raise ParamError(
                    f"parameter {self.name!r}: a pose is 6 numbers x,y,z,roll,pitch,yaw"
                )
            return {"xyz": values[:3], "rpy": values[3:]}
        if self.type in (ParamType.POSITION, ParamType.FLOATS) and "[" not in text:
            text = f"[{text}]"
        try:
            return yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise ParamError(f"parameter {self.name!r}: cannot read {text!r}: {exc}") from None

    def describe(self) -> str:
        unit = f" [{self.unit}]" if self.unit else ""
        default = "" if self.required else f" (default {self.default!r})"
        return f"{self.name}: {self.type.value}{unit}{default} — {self.doc}"


def utc_now_iso() -> str:
    return dt.datetime.now(dt.UTC).replace(microsecond=0).isoformat().replace("+00:00", "Z")


@dataclass(frozen=True)
class TaughtRecord:
    """What teaching a skill produces, executed many times afterwards.

    ``skill`` and ``name`` identify it (``place``/``bin_l2``); ``params`` hold plain YAML values
    (see the module docstring); ``frame`` is the frame the poses are relative to: ``"base"``
    (the robot's mount) or a calibrated frame such as ``"qr:station-1"``; ``revision`` counts
    re-teachings (the store sets it); ``taught_at`` is UTC ISO 8601; ``notes`` free text.
    """

    skill: str
    name: str
    params: Mapping[str, Any] = field(default_factory=dict)
    frame: str = "base"
    revision: int = 1
    taught_at: str = ""
    notes: str = ""

    @property
    def key(self) -> str:
        return f"{self.skill}/{self.name}"

    def to_dict(self) -> dict[str, Any]:
        return {
            "skill": self.skill,
            "name": self.name,
            "revision": self.revision,
            "frame": self.frame,
            "taught_at": self.taught_at,
            "notes": self.notes,
            "params": dict(self.params),
        }
