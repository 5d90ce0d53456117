"""The MQTT topics one cell publishes under (docs/mqtt.md, "Topics").

::

    {prefix}/{cell}/state                  retained: online, or offline (also the last will)
    {prefix}/{cell}/results/{inspection}   each production result, QoS 1, not retained

The configuration refuses a cell name or a prefix level that is empty, holds a wildcard
(``+`` ``#``), a ``/`` or NUL, or starts with ``$`` (vision_server/config/cell.py). A name known
only at run time (an inspection's, which the configuration already restricts to letters, digits,
``_`` ``-`` ``.``) is still escaped here, so that no name can ever add a level or subscribe-match
as a wildcard: ``%`` ``/`` ``+`` ``#`` and NUL become ``%25`` ``%2F`` ``%2B`` ``%23`` ``%00``
(percent-encoding, reversible), and an empty name ``%``.
"""

from __future__ import annotations

from dataclasses import dataclass

_ESCAPES = {"%": "%25", "/": "%2F", "+": "%2B", "#": "%23", "\0": "%00"}


def topic_level(name: str) -> str:
    """``name`` as one safe topic level (see the module)."""
    if not name:
        return "%"
    escaped = "".join(_ESCAPES.get(c, c) for c in name)
    # A leading $ marks the broker's own topics ($SYS): never at a level we make.
    return "%24" + escaped[1:] if escaped.startswith("$") else escaped


@dataclass(frozen=True)
class Topics:
    """The topics of one cell: ``prefix`` (one or more levels, as configured) and ``cell``."""

    prefix: str
    cell: str

    @property
    def base(self) -> str:
        return f"{self.prefix}/{topic_level(self.cell)}"

    @property
    def state(self) -> str:
        """Retained online/offline, and the last will."""
        return f"{self.base}/state"

    def result(self, inspection: str) -> str:
        """Where ``inspection``'s results go."""
        return f"{self.base}/results/{topic_level(inspection)}"

    @property
    def results_filter(self) -> str:
        """The subscription that gets every result of this cell."""
        return f"{self.base}/results/+"
