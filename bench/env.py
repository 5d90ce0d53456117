"""What the benchmarks of one run share: the configuration file, the rendered sample images,
the catalog (in this process, for in-process references) and the server processes, each
started on first use and stopped at the end of the run."""

from __future__ import annotations

from functools import cached_property
from pathlib import Path

from .cell import BenchCatalog, Samples, load_catalog, render_samples, write_config
from .common import RunConfig
from .servers import ServerProcess


class Env:
    def __init__(self, cfg: RunConfig) -> None:
        self.cfg = cfg
        self._servers: dict[str, ServerProcess] = {}

    @cached_property
    def config_path(self) -> Path:
        return write_config(self.cfg.workdir)

    @cached_property
    def catalog(self) -> BenchCatalog:
        return load_catalog(self.config_path)

    @cached_property
    def samples(self) -> Samples:
        return render_samples(depth_frames=5)

    def start(self, *kinds: str) -> None:
        """Launch the servers of ``kinds`` that are not running yet, all at once."""
        for kind in kinds:
            if kind not in self._servers:
                args = [] if kind == "echo" else ["--config", str(self.config_path)]
                self._servers[kind] = ServerProcess(kind, self.cfg.workdir, *args)

    def server(self, kind: str) -> ServerProcess:
        """The running server of ``kind`` (cellvision, echo, http), once it listens; raises
        Skip if it cannot start."""
        self.start(kind)
        server = self._servers[kind]
        try:
            server.info  # noqa: B018 - waits for the announcement
        except BaseException:
            self._servers.pop(kind, None)
            raise
        return server

    def stop_server(self, kind: str) -> None:
        server = self._servers.pop(kind, None)
        if server is not None:
            server.stop()

    def close(self) -> None:
        for kind in list(self._servers):
            self.stop_server(kind)
