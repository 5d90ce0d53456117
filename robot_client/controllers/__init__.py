"""Robot controllers as the line protocol sees them (protocol/LINE.md): how a controller's own
functions read answers. :mod:`.urscript` reads as a Universal Robots controller does; the
line-protocol demo (:mod:`robot_client.demo.line`) drives the simulated robot with it, and the
tests' controller clients (tests/helpers/controllers.py) use it too."""

from .urscript import pose_to_str, read_line, socket_read_ascii_float, ur_pose

__all__ = ["pose_to_str", "read_line", "socket_read_ascii_float", "ur_pose"]
