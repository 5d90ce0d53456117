"""A running cell configuration: the cameras it opened, the catalog it serves, its result log.

``reload`` re-reads the file. A valid new configuration becomes the catalog for new requests;
cameras whose settings did not change are kept open (no reconnect, no gap in frames), changed
ones are opened anew and the old ones closed. An invalid configuration changes nothing: the
error is raised (and logged by the caller) and the old catalog keeps serving.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import replace
from pathlib import Path

from .cameras import Camera, CameraSettings, make_camera
from .catalog import Catalog
from .config import CellConfig, ConfigError, load_config
from .configfile import read_document
from .results import ResultLog, ResultLogError, check_creatable

log = logging.getLogger("vision_server")


class CellRuntime:
    """Owns the cameras and the result log of the configuration at ``path``."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        self.config = load_config(self.path)
        self._started = self.config  # what `server:` and `results:` run with until a restart
        self._cameras: dict[str, tuple[CameraSettings, Camera]] = {}
        self.results: ResultLog | None = None
        self.catalog = self._build(self.config)
        self.results = self._open_results(self.config)

    def _open_results(self, config: CellConfig) -> ResultLog | None:
        """The configured log, opened for writing; a log that cannot be opened is a
        configuration error (one line naming the file, the key and the cause), not a crash."""
        if config.results.path is None:
            return None
        try:
            return ResultLog(
                config.results.path,
                store_images=config.results.store_images,  # type: ignore[arg-type]
                max_image_bytes=config.results.max_image_bytes,
            )
        except ResultLogError as exc:
            self.close()  # the cameras opened by _build
            raise result_log_error(config, str(exc)) from None

    def _build(self, config: CellConfig) -> Catalog:
        """Cameras for ``config`` (reusing unchanged ones), then the catalog."""
        kept: dict[str, tuple[CameraSettings, Camera]] = {}
        opened: list[Camera] = []
        try:
            for name, settings in config.cameras.items():
                previous = self._cameras.get(name)
                if previous is not None and previous[0] == settings:
                    kept[name] = previous
                    continue
                try:
                    camera = make_camera(name, settings, base_dir=config.base_dir)
                except ValueError as exc:
                    raise ConfigError(f"camera {name!r}: {exc}", source=str(self.path)) from None
                camera.open()
                opened.append(camera)
                kept[name] = (settings, camera)
            catalog = Catalog.build(
                [camera for _, camera in kept.values()],
                list(config.inspections),
                config_hash=config.config_hash,
            )
        except BaseException:
            for camera in opened:
                camera.close()
            raise
        retired = [
            cam
            for name, (_, cam) in self._cameras.items()
            if kept.get(name, (None, None))[1] is not cam
        ]
        self._cameras = kept
        for camera in retired:
            camera.close()
        return catalog

    def reload(self) -> Catalog:
        """Re-read the file; returns the new catalog or raises ConfigError (nothing changed).

        The catalog's ``notes`` name the sections whose changes wait for a restart, compared
        with what the process started with (so a second reload still says so)."""
        with self._lock:
            config = load_config(self.path)
            notes = tuple(
                f"{self.path.name}: changes under '{section}:' take effect after a restart"
                for section in ("server", "results")
                if getattr(config, section) != getattr(self._started, section)
            )
            for note in notes:
                log.warning("%s", note)
            self.catalog = replace(self._build(config), notes=notes)
            self.config = config
            return self.catalog

    def close(self) -> None:
        for _, camera in self._cameras.values():
            camera.close()
        self._cameras = {}
        if self.results is not None:
            self.results.close()


def check_result_log(config: CellConfig) -> None:
    """Raise :class:`ConfigError` when the configured result log could not be created or
    written (``check-config``: creates nothing)."""
    if config.results.path is None:
        return
    try:
        check_creatable(
            config.results.path,
            store_images=config.results.store_images,  # type: ignore[arg-type]
        )
    except ResultLogError as exc:
        raise result_log_error(config, str(exc)) from None


def result_log_error(config: CellConfig, message: str) -> ConfigError:
    """``message`` as an error at ``results -> path`` of the configuration file, with the
    key's line (the line of the top level when the path is the default)."""
    if config.source is None:
        return ConfigError(message, path="results -> path")
    try:
        root, _ = read_document(config.source)
        return root.sub("results").error(message, "path")
    except ConfigError:  # the file changed or vanished since it was loaded
        return ConfigError(message, source=config.source.name, path="results -> path")


__all__ = ["CellRuntime", "check_result_log", "result_log_error"]
