"""The demos on the simulated cell (``make demo``; ``python -m robot_client.demo``).

- :mod:`.task`: :func:`main` and :func:`run_demo` (→ :class:`DemoResult`), the paper's task
  from an uncalibrated cell: commissioning, QR calibration, vision picks and quality control,
  against a ``vision-server`` it starts;
- :mod:`.cell`: that server, started as a process, and the ground truth the demos check;
- :mod:`.commission`: the demo's commissioning (intrinsics and hand-eye);
- :mod:`.line`: the same picks by a robot controller through the line protocol alone
  (``--via line``).

Nothing else in robot_client imports this room.
"""

from .task import Check, DemoResult, main, run_demo

__all__ = ["Check", "DemoResult", "main", "run_demo"]
