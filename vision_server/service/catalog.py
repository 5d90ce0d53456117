"""What a server offers: its cameras and named inspections, as one immutable catalog.

A catalog is swapped whole on a configuration reload, so a request sees either the old or the
new configuration, never a mix.

Lifetime: a request *leases* the catalog it runs on (:meth:`Catalog.lease_newest`) and keeps
the lease until its last use of the catalog's cameras and inspections, including work still
running in a worker thread after the client was answered (a passed deadline). The owner of the
resources (:class:`vision_server.service.runtime.CellRuntime`) *retires* a catalog when a reload
replaces it; once it is retired and its last lease is released, the catalog is *released*: its
``on_release`` callbacks run, and only then may the owner close what no newer catalog uses. So
every resource of an old catalog outlives the requests that use it.
"""

from __future__ import annotations

import hashlib
import json
import logging
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any

from protocol import InvalidArgument, UnknownCamera, UnknownInspection

from ..cameras import Camera
from ..inspections import Inspection

log = logging.getLogger("vision_server")


class CatalogReleased(RuntimeError):
    """A lease was asked of a catalog whose resources are already released."""


class _Leases:
    """The mutable lifetime state of one catalog (not part of its value)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.count = 0
        self.retired = False
        self.released = False
        self.successor: Catalog | None = None
        self.callbacks: list[Callable[[], None]] = []


def _run_callbacks(callbacks: list[Callable[[], None]]) -> None:
    for callback in callbacks:
        try:
            callback()
        except Exception:  # one owner's failure must not keep the others' resources
            log.exception("a catalog release callback failed")


class CatalogLease:
    """One user's hold on a catalog: its resources stay until :meth:`release` (idempotent).

    Also a context manager that releases on exit.
    """

    def __init__(self, catalog: Catalog) -> None:
        self.catalog = catalog
        self._lock = threading.Lock()
        self._held = True

    def release(self) -> None:
        with self._lock:
            if not self._held:
                return
            self._held = False
        self.catalog._drop_lease()

    def __enter__(self) -> CatalogLease:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.release()


@dataclass(frozen=True)
class Catalog:
    """Cameras and inspections by name, and the hash of the configuration they came from.

    The value is immutable; its lifetime (leases, retirement, release) is the one mutable part,
    kept out of comparisons: see the module.
    """

    cameras: Mapping[str, Camera]
    inspections: Mapping[str, Inspection]
    config_hash: str = ""
    tune: Callable[[str, Mapping[str, Any]], Inspection] | None = field(
        default=None, compare=False, repr=False
    )
    """Rebuilds a configured inspection with request options (raises ConfigError); None when
    the inspections do not come from a configuration file."""
    notes: tuple[str, ...] = ()
    """What the configuration's reader should know that serving it does not show, e.g. that
    changed ``server:`` settings take effect after a restart (sent in RELOADED)."""
    _leases: _Leases = field(default_factory=_Leases, compare=False, repr=False)

    @classmethod
    def build(
        cls,
        cameras: Sequence[Camera],
        inspections: Sequence[Inspection],
        *,
        config_hash: str | None = None,
        tune: Callable[[str, Mapping[str, Any]], Inspection] | None = None,
        notes: tuple[str, ...] = (),
    ) -> Catalog:
        cams = {c.name: c for c in cameras}
        insp = {i.name: i for i in inspections}
        for inspection in inspections:
            if inspection.camera not in cams:
                raise ValueError(
                    f"inspection {inspection.name!r} uses camera {inspection.camera!r}, "
                    f"which is not configured"
                )
        if config_hash is None:
            summary = json.dumps(
                {
                    "cameras": [c.descriptor() for c in cameras],
                    "inspections": [[i.name, i.type, i.camera] for i in inspections],
                },
                sort_keys=True,
            )
            config_hash = hashlib.sha256(summary.encode()).hexdigest()[:16]
        return cls(cams, insp, config_hash, tune=tune, notes=notes)

    # ------------------------------------------------------------------ lifetime

    def tuned(self, inspection: Inspection, options: Mapping[str, Any]) -> Inspection:
        """``inspection`` with the request's ``options`` (SPEC §6.3), validated by the same
        rules as the configuration file; INVALID_ARGUMENT names the option that is wrong."""
        if not options:
            return inspection
        if self.tune is None:
            raise InvalidArgument(
                f"inspection {inspection.name!r} takes no options on this server (its "
                "inspections do not come from a configuration file)"
            )
        try:
            return self.tune(inspection.name, options)
        except ValueError as exc:  # ConfigError
            where = getattr(exc, "path", "") or "options"
            reason = getattr(exc, "reason", str(exc))
            raise InvalidArgument(
                f"inspection {inspection.name!r}: {where}: {reason}",
                details={"option": where.removeprefix("options -> ")},
            ) from None

    def acquire(self) -> CatalogLease:
        """A lease on this catalog. Raises :class:`CatalogReleased` when it is released
        (retired and no lease left); a retired catalog that is still leased may lend more,
        for work a lease holder hands on (its resources are alive anyway)."""
        leases = self._leases
        with leases.lock:
            if leases.released:
                raise CatalogReleased(f"catalog {self.config_hash or id(self)} is released")
            leases.count += 1
        return CatalogLease(self)

    def lease_newest(self) -> CatalogLease:
        """A lease on this catalog, or on its newest successor when this one is released
        (a request that read the catalog just before a reload published the next one)."""
        catalog: Catalog | None = self
        while catalog is not None:
            try:
                return catalog.acquire()
            except CatalogReleased:
                catalog = catalog._leases.successor
        raise CatalogReleased("the catalog was released and has no successor")

    def retire(self, successor: Catalog | None = None) -> None:
        """Take no new users from the server's next requests (they go to ``successor``); once
        the last lease is released, run the ``on_release`` callbacks. Idempotent."""
        leases = self._leases
        with leases.lock:
            if leases.retired:
                return
            leases.retired = True
            leases.successor = successor
            callbacks = self._release_if_idle()
        _run_callbacks(callbacks)

    def on_release(self, callback: Callable[[], None]) -> None:
        """Call ``callback`` once, when the catalog is released (at once if it already is).
        It runs in the thread that released the last lease, or that retired the catalog."""
        leases = self._leases
        with leases.lock:
            if not leases.released:
                leases.callbacks.append(callback)
                return
        _run_callbacks([callback])

    @property
    def leases(self) -> int:
        """Leases held right now."""
        with self._leases.lock:
            return self._leases.count

    @property
    def retired(self) -> bool:
        return self._leases.retired

    @property
    def released(self) -> bool:
        return self._leases.released

    def _drop_lease(self) -> None:
        leases = self._leases
        with leases.lock:
            leases.count -= 1
            callbacks = self._release_if_idle()
        _run_callbacks(callbacks)

    def _release_if_idle(self) -> list[Callable[[], None]]:
        """Mark released when retired and idle; the callbacks to run (caller holds the lock
        and runs them after letting it go)."""
        leases = self._leases
        if not leases.retired or leases.count > 0 or leases.released:
            return []
        leases.released = True
        callbacks, leases.callbacks = leases.callbacks, []
        return callbacks

    # ------------------------------------------------------------------ lookup

    def inspection(self, name: str) -> Inspection:
        try:
            return self.inspections[name]
        except KeyError:
            raise UnknownInspection(
                f"no inspection named {name!r}; configured: "
                f"{', '.join(sorted(self.inspections)) or 'none'}"
            ) from None

    def camera(self, name: str) -> Camera:
        try:
            return self.cameras[name]
        except KeyError:
            raise UnknownCamera(
                f"no camera named {name!r}; configured: {', '.join(sorted(self.cameras)) or 'none'}"
            ) from None

    def inspection_descriptors(self) -> tuple[dict[str, Any], ...]:
        out = []
        for inspection in self.inspections.values():
            camera = self.cameras[inspection.camera]
            out.append(
                {
                    "name": inspection.name,
                    "type": inspection.type,
                    "camera": inspection.camera,
                    "camera_source": camera.source,
                    "depth": inspection.uses_depth,
                }
            )
        return tuple(out)

    def camera_descriptors(self) -> tuple[dict[str, Any], ...]:
        return tuple(c.descriptor() for c in self.cameras.values())
