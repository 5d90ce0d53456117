"""simulation: the simulated robot cell (numpy, OpenCV and ``geometry`` only).

Scenes are YAML (``load_scene``); ``SimCell`` owns the world state, the robot, the gripper and
the cameras, and renders frames with exact ground truth. See simulation/README.md for the
world-state file that lets a second process (the vision server's ``sim`` camera) see what the
robot did.

Public API:

- ``SimCell(scene, *, seed=None, state_path=None)``, ``SimCell.from_yaml(path, ...)``:
  ``render(camera) -> Frame``, ``world_from_camera(camera)``, ``robot``, ``gripper``,
  ``world``, ``clock``, ``sync()``, ``publish()``, ``dock()``.
- ``Frame(camera, color, depth, truth)``; ``GroundTruth`` (poses, ``features``, ``qr_codes``,
  ``parts``, ``labels``/``mask(name)``, ``depth_true_m``); ``FeatureTruth``, ``QRTruth``,
  ``PartTruth``.
- ``SimRobot`` (``move_linear``, ``tool_pose``, ``set_user_frame``, ``in_workspace``),
  ``Gripper`` (``grasp``, ``release``/``place``, ``held``), ``SimClock``, ``WorkspaceError``.
- ``Scene`` and its specs, ``load_scene(path)``, ``scene_from_text(text)``, ``SceneError``,
  ``camera_preset(model)``.
- ``World``, ``PartState``, ``WorldStateFile``.
- ``qr_modules(text)``, ``BOARD_FROM_QR``.
"""

from simulation.cell import FeatureTruth, Frame, GroundTruth, PartTruth, QRTruth, SimCell
from simulation.qr import BOARD_FROM_QR, qr_modules
from simulation.robot import Gripper, SimClock, SimRobot, WorkspaceError
from simulation.scene import (
    CameraSpec,
    DepthSpec,
    PartSpec,
    Scene,
    SceneError,
    camera_preset,
    load_scene,
    scene_from_text,
)
from simulation.world import PartState, World, WorldStateFile

__all__ = [
    "BOARD_FROM_QR",
    "CameraSpec",
    "DepthSpec",
    "FeatureTruth",
    "Frame",
    "Gripper",
    "GroundTruth",
    "PartSpec",
    "PartState",
    "PartTruth",
    "QRTruth",
    "Scene",
    "SceneError",
    "SimCell",
    "SimClock",
    "SimRobot",
    "World",
    "WorldStateFile",
    "WorkspaceError",
    "camera_preset",
    "load_scene",
    "qr_modules",
    "scene_from_text",
]
