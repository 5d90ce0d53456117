"""A running cell configuration: the cameras it opened, the catalog it serves, its result log.

``reload`` re-reads the file. A valid new configuration becomes the catalog for new requests;
cameras whose settings did not change are kept open (no reconnect, no gap in frames), changed
ones are opened anew. An invalid configuration changes nothing: the error is raised (and logged
by the caller) and the old catalog keeps serving.

A camera that a reload replaced or removed is closed only when no catalog that holds it is in
use any more: the old catalog is retired, and once the last request leasing it is done (see
:mod:`.catalog`) the cameras that no newer catalog holds are closed, in a thread of their own,
because closing a camera joins its reader (up to ``read_timeout_s`` + 5 s for a hung driver)
and must neither block the event loop (SIGHUP) nor a worker thread.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable
from pathlib import Path

from ..cameras import Camera, CameraSettings, make_camera
from ..config import (
    NOTHING_CHANGED,
    CellConfig,
    ConfigError,
    describe_changes,
    load_config,
    read_document,
)
from ..results import ResultLogError, ResultStore, check_result_store, open_result_store
from .catalog import Catalog

log = logging.getLogger("vision_server")

CameraFactory = Callable[[str, CameraSettings, Path], Camera]
"""Builds a camera, not yet opened: ``(name, settings, base_dir) -> Camera``."""


def _make_camera(name: str, settings: CameraSettings, base_dir: Path) -> Camera:
    return make_camera(name, settings, base_dir=base_dir)


class CellRuntime:
    """Owns the cameras and the result log of the configuration at ``path``.

    ``camera_factory`` builds the cameras (``make_camera`` unless a test wraps it).
    """

    def __init__(self, path: Path | str, *, camera_factory: CameraFactory | None = None) -> None:
        self.path = Path(path)
        self._make_camera = camera_factory or _make_camera
        self._lock = threading.Lock()
        """Serialises reload and close."""
        self._owners_lock = threading.Lock()
        self._owners: dict[Camera, int] = {}
        """Each camera -> how many unreleased catalogs hold it; closed when it drops to 0."""
        self._closers: list[threading.Thread] = []
        self._closed = False
        self.config = load_config(self.path)
        self._started = self.config  # what `server:` and `results:` run with until a restart
        self._cameras: dict[str, tuple[CameraSettings, Camera]] = {}
        self.results: ResultStore | None = None
        self.catalog = self._build(self.config)
        self.results = self._open_results(self.config)

    def _open_results(self, config: CellConfig) -> ResultStore | None:
        """The configured log (SQLite or PostgreSQL), opened for writing; a log that cannot be
        opened is a configuration error (one line naming the file, the key and the cause), not
        a crash."""
        try:
            return open_result_store(config.results)
        except ResultLogError as exc:
            self.close()  # the cameras opened by _build
            raise result_log_error(config, str(exc)) from None

    def _build(self, config: CellConfig, notes: tuple[str, ...] = ()) -> Catalog:
        """Cameras for ``config`` (reusing unchanged ones), then the catalog, whose cameras
        this runtime closes once the catalog is released."""
        kept: dict[str, tuple[CameraSettings, Camera]] = {}
        opened: list[Camera] = []
        try:
            for name, settings in config.cameras.items():
                previous = self._cameras.get(name)
                if previous is not None and previous[0] == settings:
                    kept[name] = previous
                    continue
                try:
                    camera = self._make_camera(name, settings, config.base_dir)
                except ValueError as exc:
                    raise ConfigError(f"camera {name!r}: {exc}", source=str(self.path)) from None
                camera.open()
                opened.append(camera)
                kept[name] = (settings, camera)
            catalog = Catalog.build(
                [camera for _, camera in kept.values()],
                list(config.inspections),
                config_hash=config.config_hash,
                tune=config.tune,
                notes=notes,
            )
        except BaseException:
            for camera in opened:  # never served: nobody can be using them
                camera.close()
            raise
        self._cameras = kept
        cameras = list(catalog.cameras.values())
        with self._owners_lock:
            for camera in cameras:
                self._owners[camera] = self._owners.get(camera, 0) + 1
        catalog.on_release(lambda: self._disown(cameras))
        return catalog

    def _disown(self, cameras: Iterable[Camera]) -> None:
        """A catalog holding ``cameras`` is released: close those no other catalog holds."""
        unused = []
        with self._owners_lock:
            for camera in cameras:
                left = self._owners.get(camera, 0) - 1
                if left > 0:
                    self._owners[camera] = left
                elif camera in self._owners:
                    del self._owners[camera]
                    unused.append(camera)
            if not unused or self._closed:
                return  # after close() every camera is closed already
            closer = threading.Thread(
                target=_close_all, args=(unused,), name="camera-closer", daemon=True
            )
            self._closers = [t for t in self._closers if t.is_alive()]
            self._closers.append(closer)
            closer.start()

    def reload(self) -> Catalog:
        """Re-read the file; returns the new catalog or raises ConfigError (nothing changed).

        The previous catalog is retired with the new one as its successor: requests running
        on it finish with its cameras, which are closed after the last of them if the new
        catalog does not keep them. Never waits for a camera to close.

        The catalog's ``notes`` say what the reload changed (inspections and cameras changed,
        added, removed: vision_server.config.changes), then the sections whose changes wait
        for a restart, compared with what the process started with (so a second reload
        still says so); "no inspection or camera changed" when there is nothing to say.
        """
        with self._lock:
            if self._closed:
                raise RuntimeError("the cell runtime is closed")
            config = load_config(self.path)
            # What the reload applies (also hand edits made since the last one), then what
            # waits for a restart; a reload that changes nothing says so.
            changes = describe_changes(self.config, config)
            restart = tuple(
                f"{self.path.name}: changes under '{section}:' take effect after a restart"
                for section in ("server", "results", "line", "mqtt", "opcua")
                if getattr(config, section) != getattr(self._started, section)
            )
            for note in restart:
                log.warning("%s", note)
            notes = changes + restart or (NOTHING_CHANGED,)
            previous = self.catalog
            self.catalog = self._build(config, notes)
            self.config = config
            previous.retire(successor=self.catalog)
            return self.catalog

    def close(self) -> None:
        """Close every camera, also those of catalogs still leased (the server has stopped),
        wait for the closing of replaced ones, close the result log."""
        with self._lock:
            with self._owners_lock:
                self._closed = True
                cameras = list(self._owners)
                self._owners.clear()
                closers, self._closers = self._closers, []
            self.catalog.retire()
            _close_all(cameras)
            for closer in closers:
                closer.join()
            self._cameras = {}
            if self.results is not None:
                self.results.close()


def _close_all(cameras: Iterable[Camera]) -> None:
    for camera in cameras:
        try:
            camera.close()
        except Exception:  # one camera's failure must not leave the others open
            log.exception("closing camera %r failed", camera.name)
        else:
            log.info("camera %r closed", camera.name)


def check_result_log(config: CellConfig) -> None:
    """Raise :class:`ConfigError` when the configured result log could not be created or
    written (``check-config``: creates nothing)."""
    try:
        check_result_store(config.results)
    except ResultLogError as exc:
        raise result_log_error(config, str(exc)) from None


def result_log_error(config: CellConfig, message: str) -> ConfigError:
    """``message`` as an error at ``results -> path`` (``url`` for PostgreSQL) of the
    configuration file, with the key's line (the line of the top level when the path is the
    default)."""
    key = "url" if config.results.url is not None else "path"
    if config.source is None:
        return ConfigError(message, path=f"results -> {key}")
    try:
        root, _ = read_document(config.source)
        return root.sub("results").error(message, key)
    except ConfigError:  # the file changed or vanished since it was loaded
        return ConfigError(message, source=config.source.name, path=f"results -> {key}")


__all__ = ["CameraFactory", "CellRuntime", "check_result_log", "result_log_error"]
