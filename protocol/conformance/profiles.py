"""Profiles: what a server under test need not offer.

SPEC.md lets a server leave some things out: it MAY have no server-side camera (every image
arrives in the request) and MAY refuse RELOAD. A check that exercises such a feature names it in
``Check.needs``; under a profile that leaves the feature out the check is not run and is
reported "not applicable (profile NAME)", never as passed.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum


class Feature(StrEnum):
    """Something a server MAY offer that some checks need."""

    SERVER_CAMERAS = "server cameras"
    """Cameras whose ``source`` is not ``"request"``: CAPTURE and INSPECT without images."""
    RELOAD = "reload"
    """RELOAD re-reads the configuration (§6.5)."""


@dataclass(frozen=True)
class Profile:
    name: str
    description: str
    omits: frozenset[Feature]


PROFILES: dict[str, Profile] = {
    p.name: p
    for p in (
        Profile("full", "everything SPEC.md describes (the default)", frozenset()),
        Profile(
            "minimal",
            "no server-side cameras and no RELOAD: every image arrives in the request",
            frozenset({Feature.SERVER_CAMERAS, Feature.RELOAD}),
        ),
    )
}

DEFAULT_PROFILE = PROFILES["full"]
