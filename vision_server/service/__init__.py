"""The inspection service: the one path to an inspection, under every front-end.

- :mod:`.core`: :class:`InspectionService` (``inspect``, ``capture``, ``admit``, ``reload``,
  ``subscribe``) and its records :class:`InspectRequest`, :class:`Images`,
  :class:`InspectReply`, :class:`CaptureRequest`, :class:`CaptureReply`.
- :mod:`.admission`: the worker lanes, their cost model and the byte budget
  (:class:`Admission`, :class:`Slot`, :class:`Waiter`).
- :mod:`.process_lane`: inspections run in worker processes (``server: process_inspections``).
- :mod:`.catalog`: the cameras and inspections a configuration offers, swapped whole on reload.
- :mod:`.runtime`: :class:`CellRuntime`, a running configuration's cameras, catalog and result
  log, and its reload.
- :mod:`.door`: the front door: :class:`FrontDoor` admits every front-end's connections
  (per front-end and server-wide) and slows down failed sign-ins.
- :mod:`.operator_desk`: robots' calls waiting for a person (SPEC §6.6).
- :mod:`.builtin`: :func:`builtin_catalog`, what ``serve`` offers without a configuration.
- :mod:`.replay`: impact before save: a pending change replayed over an inspection's stored
  images (:func:`replay`), for the console's impact preview and ``vision-server replay``.
- :mod:`.training`: training an anomaly inspection from good whole images
  (:func:`train_inspection`), for ``vision-server train`` and the console.

It speaks arrays and plain records, never a front-end's wire types.
"""

from .admission import Admission, Slot, Waiter
from .builtin import builtin_catalog
from .catalog import Catalog, CatalogReleased
from .core import (
    CaptureReply,
    CaptureRequest,
    FrameEncoding,
    ImageLoader,
    ImageNeeds,
    Images,
    InspectionRecord,
    InspectionService,
    InspectReply,
    InspectRequest,
    RequestClass,
    capture_key,
    check_image_size,
    check_images,
    deadline_after,
)
from .door import FrontDoor, Pass, Refusal, failure_key, peer_host, peer_name
from .operator_desk import (
    MAX_REASON_CHARS,
    CallClosed,
    OperatorDesk,
    call_json,
    closed_json,
    desk_image,
)
from .replay import (
    DEFAULT_LAST,
    MAX_LAST,
    Change,
    ChangeRefused,
    ImpactReport,
    changed_inspection,
    replay,
    stored_image_loader,
)
from .runtime import CellRuntime, check_result_log
from .training import (
    MODELS_FOLDER,
    Trained,
    TrainingError,
    check_usable,
    next_model_file,
    train_inspection,
    training_patches,
)

__all__ = [
    "MODELS_FOLDER",
    "Trained",
    "TrainingError",
    "check_usable",
    "next_model_file",
    "train_inspection",
    "training_patches",
    "stored_image_loader",
    "DEFAULT_LAST",
    "MAX_LAST",
    "Admission",
    "CallClosed",
    "CaptureReply",
    "CaptureRequest",
    "Catalog",
    "CatalogReleased",
    "CellRuntime",
    "Change",
    "ChangeRefused",
    "FrameEncoding",
    "FrontDoor",
    "ImageLoader",
    "ImageNeeds",
    "Images",
    "ImpactReport",
    "InspectReply",
    "InspectRequest",
    "InspectionRecord",
    "InspectionService",
    "MAX_REASON_CHARS",
    "OperatorDesk",
    "Pass",
    "Refusal",
    "RequestClass",
    "Slot",
    "Waiter",
    "builtin_catalog",
    "call_json",
    "capture_key",
    "changed_inspection",
    "check_image_size",
    "check_images",
    "check_result_log",
    "closed_json",
    "deadline_after",
    "desk_image",
    "failure_key",
    "peer_host",
    "peer_name",
    "replay",
]
