"""The cell configuration: one YAML file read, validated and frozen (docs/configuration.md).

- :mod:`.cell`: :func:`load_config` → :class:`CellConfig` (server, console, line, Modbus,
  MQTT, results, cameras, inspections); :class:`Tuner` re-reads an inspection with a request's
  options.
- :mod:`.document`: the YAML reading, every error a :class:`ConfigError` naming file, line and
  key path.
- :mod:`.settings`: the records the service and each front-end run with.
- :mod:`.listeners`: the addresses the front-ends listen on, and that no two share one.
- :mod:`.changes`: what a reload changed, in words.
- :mod:`.users`: named console users (``server: users:``), their PINs, badges and hashes.
- :mod:`.exposure`: warnings for front-ends open beyond loopback without authentication.
- :mod:`.drafts`: a whole inspection mapping (the console's edit or draft) read by the loader.
- :mod:`.schema`: every key of every inspection and job step type, for the console's editor.
- :mod:`.redaction`: a configuration text with its tokens, passwords and PINs hidden.
- :mod:`.files`: the files beside the configuration written atomically (the file, versions,
  templates).
- :mod:`.model_key`: pointing an inspection's ``model:`` at a newly trained file, in the text.
- :mod:`.history`: the configuration file's versions (who, when, why, a diff), bounded on disk.
"""

from . import files, history
from .cell import (
    FIXED_BY_THE_CONFIGURATION,
    CellConfig,
    ResultsConfig,
    Tuner,
    load_config,
    load_server_settings,
    parse_config,
    settings_from_node,
)
from .changes import NOTHING_CHANGED, changed_inspections, describe_changes
from .document import ConfigError, Node, parse_document, read_document
from .drafts import check_files, file_keys, parse_draft
from .exposure import exposure_warnings
from .listeners import Listener, ListenError, PortClash, check_distinct, enabled_listeners
from .model_key import ModelKeyError, set_model_key
from .redaction import redact_secrets
from .schema import inspection_schema
from .settings import (
    DEFAULT_CONSOLE_PORT,
    DEFAULT_LINE_PORT,
    DEFAULT_MODBUS_PORT,
    DEFAULT_MQTT_PORT,
    DEFAULT_MQTTS_PORT,
    DEFAULT_OPCUA_PORT,
    LINE_FORMATS,
    MODBUS_WORD_ORDERS,
    SERVER_VERSION,
    ConsoleSettings,
    LineSettings,
    ModbusSettings,
    MqttSettings,
    OpcUaCertificateUser,
    OpcUaSettings,
    ServerSettings,
    ServiceSettings,
    TcpSettings,
    welcome_limits,
)
from .users import (
    MIN_BADGE_CHARS,
    MIN_PIN_CHARS,
    USER_ROLES,
    Secret,
    User,
    hash_secret,
    users_by_name,
)

__all__ = [
    "ModelKeyError",
    "set_model_key",
    "DEFAULT_CONSOLE_PORT",
    "DEFAULT_LINE_PORT",
    "DEFAULT_MODBUS_PORT",
    "DEFAULT_MQTT_PORT",
    "DEFAULT_MQTTS_PORT",
    "FIXED_BY_THE_CONFIGURATION",
    "LINE_FORMATS",
    "MODBUS_WORD_ORDERS",
    "NOTHING_CHANGED",
    "SERVER_VERSION",
    "CellConfig",
    "ConfigError",
    "ConsoleSettings",
    "LineSettings",
    "MIN_BADGE_CHARS",
    "MIN_PIN_CHARS",
    "Secret",
    "USER_ROLES",
    "User",
    "hash_secret",
    "users_by_name",
    "ListenError",
    "Listener",
    "ModbusSettings",
    "DEFAULT_OPCUA_PORT",
    "OpcUaCertificateUser",
    "OpcUaSettings",
    "MqttSettings",
    "Node",
    "PortClash",
    "ResultsConfig",
    "ServerSettings",
    "ServiceSettings",
    "TcpSettings",
    "Tuner",
    "changed_inspections",
    "check_files",
    "check_distinct",
    "describe_changes",
    "enabled_listeners",
    "exposure_warnings",
    "file_keys",
    "inspection_schema",
    "files",
    "history",
    "load_config",
    "load_server_settings",
    "parse_config",
    "parse_document",
    "parse_draft",
    "read_document",
    "redact_secrets",
    "settings_from_node",
    "welcome_limits",
]
