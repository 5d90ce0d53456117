"""What a running skill is given: its decoded parameters (:class:`Args`) and everything it may
use (:class:`SkillContext`: the devices, the world model, the teach store, progress and the
operator). Kept apart from the skill model (:mod:`.base`) so that the conditions, which read
both, do not import the model that lists them."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import NDArray

from ..devices import Camera, Clock, Devices, Gripper, Robot, Vision
from .camera_mounts import HAND_EYE_SKILL, CalibratedCamera, stored_hand_eye
from .outcome import FailureReason, fail
from .record import Param, TaughtRecord
from .world import WorldModel

if TYPE_CHECKING:
    from ..teach_store import TeachStore

FloatArray = NDArray[np.float64]


class SpecView(Protocol):
    """What :class:`Args` needs of a skill's spec (:class:`~.base.SkillSpec` is one)."""

    @property
    def name(self) -> str: ...

    def param(self, name: str) -> Param: ...


class Args(Mapping[str, Any]):
    """A record's parameters decoded to their types (poses 4x4 arrays, positions (3,) arrays),
    with the record itself (``args.record.frame``: the frame the poses are in)."""

    def __init__(self, spec: SpecView, record: TaughtRecord, values: dict[str, Any]) -> None:
        self.spec, self.record, self._values = spec, record, values

    def __getitem__(self, key: str) -> Any:
        try:
            return self._values[key]
        except KeyError:
            raise KeyError(f"skill {self.spec.name!r} has no parameter {key!r}") from None

    def __iter__(self) -> Iterator[str]:
        return iter(self._values)

    def __len__(self) -> int:
        return len(self._values)

    def spec_param(self, name: str) -> Param:
        return self.spec.param(name)

    def pose(self, name: str) -> FloatArray:
        value = self[name]
        if not (isinstance(value, np.ndarray) and value.shape == (4, 4)):
            raise TypeError(f"parameter {name!r} is not a pose")
        return value.copy()

    def position(self, name: str) -> FloatArray:
        value = self[name]
        if not (isinstance(value, np.ndarray) and value.shape == (3,)):
            raise TypeError(f"parameter {name!r} is not a position")
        return value.copy()

    def number(self, name: str) -> float:
        return float(self[name])

    def integer(self, name: str) -> int:
        return int(self[name])

    def text(self, name: str) -> str:
        return str(self[name])

    def flag(self, name: str) -> bool:
        return bool(self[name])


@dataclass(frozen=True)
class Progress:
    """A progress report while a skill runs: ``message``, ``fraction`` done in [0, 1] if
    known, and ``data`` (JSON-able numbers)."""

    skill: str
    record: str
    message: str
    fraction: float | None = None
    data: Mapping[str, Any] = field(default_factory=dict)


ProgressCallback = Callable[[Progress], None]

OperatorCallback = Callable[[str, Mapping[str, Any]], str]
"""Asks a person (``message``, ``data``) when a skill cannot go on by itself; the answer is
``"retry"``, ``"continue"`` (the operator fixed it or accepts it) or ``"abort"``."""


@dataclass
class SkillContext:
    """Everything a skill may use: the devices, the world model, the teach store (may be
    None), a progress callback and the operator (None: unattended). ``clock`` is the
    devices' clock (simulated in the sim)."""

    devices: Devices
    world: WorldModel
    store: TeachStore | None = None
    progress: ProgressCallback | None = None
    _current: tuple[str, str] = ("", "")
    operator: OperatorCallback | None = None

    @classmethod
    def create(
        cls,
        devices: Devices,
        *,
        store: TeachStore | None = None,
        progress: ProgressCallback | None = None,
        calibration_max_age_s: float | None = None,
        operator: OperatorCallback | None = None,
    ) -> SkillContext:
        world = WorldModel(devices, calibration_max_age_s=calibration_max_age_s)
        return cls(devices, world, store, progress, operator=operator)

    @property
    def robot(self) -> Robot:
        return self.devices.robot

    @property
    def gripper(self) -> Gripper:
        return self.devices.gripper

    @property
    def clock(self) -> Clock:
        return self.devices.clock

    @property
    def vision(self) -> Vision:
        """The vision client; a skill that needs it fails ``vision_unavailable`` without it."""
        if self.devices.vision is None:
            fail(FailureReason.VISION_UNAVAILABLE, "this robot has no vision server configured")
        return self.devices.vision

    def camera(self, name: str) -> Camera:
        """The device camera ``name``, with its hand-eye calibration from the teach store
        when there is one (:mod:`robot_client.skills.camera_mounts`)."""
        camera = self.devices.camera(name)
        if self.store is None:
            return camera
        try:
            stored = stored_hand_eye(self.store.records(HAND_EYE_SKILL), name)
            return camera if stored is None else CalibratedCamera(camera, stored)
        except ValueError as exc:
            fail(FailureReason.BAD_RECORD, f"{self.store.path}: {exc}")

    def report(self, message: str, fraction: float | None = None, **data: Any) -> None:
        """Tell the progress callback (the CLI's progress bar) what the skill is doing."""
        if self.progress is not None:
            skill, record = self._current
            self.progress(Progress(skill, record, message, fraction, data))

    def sleep(self, seconds: float) -> None:
        self.clock.sleep(seconds)


__all__ = [
    "Args",
    "OperatorCallback",
    "Progress",
    "ProgressCallback",
    "SkillContext",
    "SpecView",
]
