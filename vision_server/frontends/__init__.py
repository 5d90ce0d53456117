"""Front-ends: thin adapters that parse their own wire format into the inspection service's
requests, call :class:`vision_server.service.InspectionService`, and render its replies.

- :mod:`.tcp`: the cellvision binary protocol (SPEC.md) over TCP, with TLS and a token.
- :mod:`.line`: the line protocol for robot controllers (protocol/LINE.md).
- :mod:`.modbus`: Modbus TCP for PLCs (protocol/MODBUS.md; pymodbus, the optional extra
  ``modbus``), with its register map (:mod:`.modbus_map`), hand-shake state machine
  (:mod:`.modbus_handshake`) and framing (:mod:`.modbus_frames`), which need no pymodbus.
- :mod:`.images`: image payloads (the protocol's, also image files) decoded into arrays.
"""
