"""The OPC UA front-end: OPC 40100-1 (OPC UA for Machine Vision) over the inspection service,
with asyncua (the optional extra ``opcua``). docs/opcua.md maps the specification's objects to
cellvision's.

- :mod:`.frontend`: :class:`OpcUaFrontend`: its start and stop, the state machine's methods and
  the jobs (:mod:`.job`);
- :mod:`.queries`: the answers about recipes, results and the configuration;
- :mod:`.model`: the specification's nodeset (:mod:`.nodeset`, loaded unchanged) and the
  ``VisionSystem`` instance;
- :mod:`.states`: the vision state machine and its automatic mode, without OPC UA;
- :mod:`.results`: results readable by id, in a bounded ring;
- :mod:`.access`: users, roles and rights; :mod:`.pki`: certificates and trust lists as files;
- :mod:`.wire`: asyncua's connections behind the front door's byte and time rules;
  :mod:`.hardening`: asyncua's server held to the door's promises where it trusts clients.

Public API: :class:`OpcUaFrontend`, the namespace URIs, :class:`Machines` (the state rules).
"""

from .frontend import FRONTEND, OpcUaFrontend
from .model import CELL_URI, MV_URI
from .states import AutomaticState, InvalidState, Machines, VisionState

__all__ = [
    "CELL_URI",
    "FRONTEND",
    "MV_URI",
    "AutomaticState",
    "InvalidState",
    "Machines",
    "OpcUaFrontend",
    "VisionState",
]
