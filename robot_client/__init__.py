"""cellvision robot client: the protocol client and, on top of it, the robot's vision skills.

Public API:

- :class:`VisionClient` (asyncio: ``connect``, ``ping``, ``list_inspections``, ``inspect``,
  ``capture``, ``close``), :class:`SyncVisionClient` (the same, blocking),
  :class:`ReconnectPolicy`, :func:`overlay_image`, :func:`wait_for_server`.
- Local errors: :class:`ClientError`, :class:`ConnectionLost` (:class:`NotCellvision`: the
  address speaks another protocol), :class:`RequestTimeout`,
  :class:`ClientClosed`. Errors the server sends are :class:`protocol.CellvisionError`
  subclasses (``protocol.UnknownInspection``, ``protocol.Busy``, ...).
- :func:`resolve_server`, :func:`parse_address`: where the server is.

Robot side (the paper's device primitives → skills → tasks):

- :mod:`robot_client.devices`: :class:`Robot`, :class:`Gripper`, :class:`Camera` (→
  :class:`Capture`), :class:`Vision` protocols, the :class:`Devices` bundle, :class:`DeviceError`
  / :class:`Unreachable`; backends :func:`sim_devices` (:mod:`robot_client.devices.sim`, the
  default) and :func:`robot_client.devices.ur.connect_ur` (ur_rtde, optional extra ``ur``);
  :class:`LazyVision`, :class:`ServerCamera`.
- :mod:`robot_client.skills`: :class:`SkillSpec`, :class:`Param`/:class:`ParamType`,
  :class:`Skill`, :class:`TaughtRecord`, :class:`Outcome`, :class:`FailureReason`,
  :func:`fail`, :class:`WorldModel`, :class:`Calibration`, conditions (:class:`Holding`,
  :class:`GripperEmpty`, :class:`NearTaught`, :class:`CalibrationValid`, :class:`Predicate`),
  :class:`SkillContext`, :func:`execute`, :class:`SkillRegistry`, :func:`register_skill`,
  :func:`default_registry`; basic skills ``move_to``, ``place``, ``press``.
- :class:`TeachStore` (:mod:`robot_client.teach_store`): taught records in YAML.
- :mod:`robot_client.tasks`: :func:`load_task`, :class:`Task`, :class:`TaskRunner`,
  :class:`TaskReport`.

The command line is ``robot-client`` (:mod:`robot_client.commands`): ping, inspections, inspect,
skills, teach, run, task run, taught list/show.
"""

from .address import parse_address, resolve_server
from .client import ReconnectPolicy, SyncVisionClient, VisionClient, overlay_image, wait_for_server
from .devices import (
    Camera,
    Capture,
    DeviceError,
    Devices,
    Gripper,
    Robot,
    Unreachable,
    Vision,
)
from .devices.sim import sim_devices
from .devices.vision import LazyVision, ServerCamera
from .errors import ClientClosed, ClientError, ConnectionLost, NotCellvision, RequestTimeout
from .skills import (
    Calibration,
    CalibrationValid,
    FailureReason,
    GripperEmpty,
    Holding,
    NearTaught,
    Outcome,
    Param,
    ParamType,
    Predicate,
    Skill,
    SkillContext,
    SkillRegistry,
    SkillSpec,
    TaughtRecord,
    WorldModel,
    default_registry,
    execute,
    fail,
    register_skill,
)
from .tasks import Task, TaskReport, TaskRunner, load_task
from .teach_store import TeachStore

__all__ = [
    "Calibration",
    "CalibrationValid",
    "Camera",
    "Capture",
    "DeviceError",
    "Devices",
    "FailureReason",
    "Gripper",
    "GripperEmpty",
    "Holding",
    "LazyVision",
    "NearTaught",
    "Outcome",
    "Param",
    "ParamType",
    "Predicate",
    "Robot",
    "ServerCamera",
    "Skill",
    "SkillContext",
    "SkillRegistry",
    "SkillSpec",
    "Task",
    "TaskReport",
    "TaskRunner",
    "TaughtRecord",
    "TeachStore",
    "Unreachable",
    "Vision",
    "WorldModel",
    "default_registry",
    "execute",
    "fail",
    "load_task",
    "register_skill",
    "sim_devices",
    "ClientClosed",
    "ClientError",
    "ConnectionLost",
    "NotCellvision",
    "ReconnectPolicy",
    "RequestTimeout",
    "SyncVisionClient",
    "VisionClient",
    "overlay_image",
    "parse_address",
    "resolve_server",
    "wait_for_server",
]
