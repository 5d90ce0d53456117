"""Front-ends: thin adapters that parse their own wire format into the inspection service's
requests, call :class:`vision_server.service.InspectionService`, and render its replies.

- :mod:`.tcp`: the cellvision binary protocol (SPEC.md) over TCP, with TLS and a token.
- :mod:`.images`: image payloads (the protocol's, also image files) decoded into arrays.
"""
