"""The ``robot-client`` command line: one module per group of subcommands.

- :mod:`.program`: :func:`main`, the parser, ``ping``, ``inspections``, ``inspect``, ``capture``;
- :mod:`.skills`: ``skills``, ``teach``, ``run``, ``task run``, ``taught``, and the device
  options every robot command shares;
- :mod:`.commission`: ``calibrate-intrinsics``; :mod:`.hand_eye`: ``hand-eye``;
  :mod:`.sensor_check`: ``sensor-check``.

Nothing else in robot_client imports this room.
"""

from .program import main

__all__ = ["main"]
