"""Conformance suite: checks any cellvision server over TCP against SPEC.md.

``python -m protocol.conformance HOST:PORT [--json] [--profile minimal]`` runs every check and
exits non-zero on a failure. From Python: :func:`run_checks`. A profile (``profiles``) names
what a server need not offer; checks that need it are "not applicable", never passed. Unlike
the rest of ``protocol``, this tool does I/O (blocking sockets): it is a client, not part of the
sans-IO core.
"""

from __future__ import annotations

import time
import traceback
from dataclasses import dataclass

from ..constants import MessageType
from . import schema_checks  # noqa: F401  (registers the metadata_schemas check, §6.3.1)
from .checks import CHECKS, Check, Context, Skip
from .peer import CheckFailed, Peer, Target
from .profiles import DEFAULT_PROFILE, PROFILES, Feature, Profile


@dataclass(frozen=True)
class CheckResult:
    name: str
    section: str
    description: str
    status: str
    """"pass", "fail", "skip" (the server offers nothing to check it on), "n/a" (the profile
    leaves out a feature it needs: not run) or "error" (the check raised something unexpected)."""
    detail: str
    duration_s: float


def discover(target: Target) -> Context:
    """One handshake to learn the server's limits, inspections and cameras."""
    with Peer(target) as peer:
        welcome = peer.handshake()
        if welcome.type != MessageType.WELCOME:
            raise CheckFailed("no WELCOME")
        meta = welcome.metadata
        return Context(
            target,
            dict(meta.get("limits", {})),
            tuple(meta.get("inspections", [])),
            tuple(meta.get("cameras", [])),
        )


def run_check(check: Check, context: Context, profile: Profile = DEFAULT_PROFILE) -> CheckResult:
    t0 = time.perf_counter()
    left_out = sorted(f.value for f in check.needs & profile.omits)
    if left_out:
        detail = f"not applicable (profile {profile.name}: no {', no '.join(left_out)})"
        return CheckResult(check.name, check.section, check.description, "n/a", detail, 0.0)
    try:
        note = check.run(context)
        status, detail = "pass", note or ""
    except Skip as exc:
        status, detail = "skip", str(exc)
    except CheckFailed as exc:
        status, detail = "fail", str(exc)
    except OSError as exc:
        status, detail = "fail", f"{type(exc).__name__}: {exc}"
    except Exception as exc:
        status = "error"
        detail = f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=3)}"
    return CheckResult(
        check.name, check.section, check.description, status, detail, time.perf_counter() - t0
    )


def run_checks(
    target: Target, *, select: str | None = None, profile: Profile = DEFAULT_PROFILE
) -> list[CheckResult]:
    """Run every check (or those whose name contains ``select``) against ``target``; those
    that need a feature ``profile`` leaves out are reported "n/a" without being run."""
    context = discover(target)
    chosen = [c for c in CHECKS if select is None or select in c.name]
    return [run_check(c, context, profile) for c in chosen]


__all__ = [
    "CHECKS",
    "Check",
    "CheckFailed",
    "CheckResult",
    "DEFAULT_PROFILE",
    "Feature",
    "PROFILES",
    "Profile",
    "Target",
    "discover",
    "run_check",
    "run_checks",
]
