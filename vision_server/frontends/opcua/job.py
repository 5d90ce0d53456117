"""One job of the OPC UA front-end (OPC 40100-1's JobId): what it runs, for whom, and how it
is being ended."""

from __future__ import annotations

import asyncio

from ...service import InspectReply
from .model import now_utc


class Job:
    """One StartSingleJob or StartContinuous: what it runs and what the client called it."""

    def __init__(
        self, job_id: str, recipe: str, meas_id: str, part_id: str, product_id: str, user: str
    ) -> None:
        self.job_id = job_id
        self.recipe = recipe
        self.meas_id = meas_id
        self.part_id = part_id
        self.product_id = product_id
        self.user = user
        self.started = now_utc()
        self.task: asyncio.Task[None] | None = None
        self.run: asyncio.Task[InspectReply] | None = None
        """The inspection running now: what Abort, Halt and a stop cancel."""
        self.stop_requested = False
        self.aborted = False
        """Ended by Abort, Halt, an internal error or the server's stop: the mode was moved
        (or left) by whoever ended it."""
        self.done = asyncio.Event()


__all__ = ["Job"]
