"""The ``vision-server`` command line: one module per group of subcommands.

- :mod:`.program`: :func:`main`, the parser, ``serve``, ``check-config``, ``run``, ``ping`` and
  ``reload``;
- :mod:`.results`: ``results``; :mod:`.modbus_map`: ``modbus-map``; :mod:`.sensor_check`:
  ``sensor-check``; :mod:`.record`: ``record`` (a camera's frames to a recording);
  :mod:`.golden`: ``test-inspections`` and the golden cases' runner;
  :mod:`.replay`: ``replay`` (a changed configuration over the stored images);
  :mod:`.offline`: the service without a server, for ``run`` and the golden cases;
  :mod:`.hash_secret`: ``hash-secret`` (a PIN's or badge's hash for ``server: users:``);
  :mod:`.admin`: the small blocking client behind ``ping`` and ``reload``.

Nothing below imports this room.
"""

from .program import main

__all__ = ["main"]
