"""The vision system's two state machines of OPC 40100-1 §8, without OPC UA: what state it is
in, which method may move it where, and the transition each move takes.

- The **VisionStateMachine** (§8.2): Preoperational → Operational (automatically, once the
  configuration is served, or by ``SelectModeAutomatic``), Halted (``Halt``), Error (a job
  ended in an internal error), and back to Preoperational by ``Reset``.
- In Operational, the **automatic mode** (§8.3): Initialized → Ready (automatically: every
  inspection of the configuration is loaded, so every recipe is prepared) → SingleExecution
  (``StartSingleJob``) or ContinuousExecution (``StartContinuous``) → Ready when the job ends,
  or by ``Stop`` / ``Abort``.

The numbers are the specification's StateNumber and TransitionNumber (the nodeset's values):
clients see the state in ``CurrentState`` (its ``Id`` the state object's NodeId); the
transitions taken are logged with their numbers (the optional ``LastTransition`` is not in
the instance).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum


class VisionState(Enum):
    """The VisionStateMachineType's states, valued by their StateNumber."""

    PREOPERATIONAL = 1
    HALTED = 2
    ERROR = 3
    OPERATIONAL = 4

    @property
    def browse_name(self) -> str:
        return self.name.capitalize()


class AutomaticState(Enum):
    """The VisionAutomaticModeStateMachineType's states, valued by their StateNumber."""

    INITIALIZED = 5
    READY = 6
    SINGLE_EXECUTION = 7
    CONTINUOUS_EXECUTION = 8

    @property
    def browse_name(self) -> str:
        return "".join(part.capitalize() for part in self.name.split("_"))


TRANSITIONS: dict[tuple[str, str, bool], int] = {
    # (from, to, automatic): TransitionNumber of the nodeset's transition objects
    ("Preoperational", "Operational", True): 140,
    ("Preoperational", "Operational", False): 141,
    ("Preoperational", "Halted", False): 121,
    ("Preoperational", "Error", True): 130,
    ("Operational", "Halted", False): 421,
    ("Operational", "Error", True): 430,
    ("Operational", "Preoperational", True): 410,
    ("Halted", "Preoperational", False): 211,
    ("Error", "Preoperational", False): 311,
    ("Error", "Halted", False): 321,
    ("Initialized", "Ready", True): 560,
    ("Ready", "Initialized", True): 650,
    ("Ready", "SingleExecution", False): 671,
    ("Ready", "ContinuousExecution", False): 681,
    ("SingleExecution", "Ready", True): 760,
    ("SingleExecution", "Ready", False): 761,  # Stop
    ("ContinuousExecution", "Ready", True): 860,
    ("ContinuousExecution", "Ready", False): 861,  # Stop
}
ABORT_TRANSITIONS = {"SingleExecution": 762, "ContinuousExecution": 862}


class InvalidState(Exception):
    """A method called in a state that does not allow it (OPC UA: BadInvalidState); the
    message names the state and what would allow it."""


@dataclass(frozen=True)
class Transition:
    """One move: which machine, from and to which state (browse names), its number."""

    machine: str
    """``vision`` or ``automatic``."""
    source: str
    target: str
    number: int


class Machines:
    """Both state machines' current states and the rules between them. Every method that
    moves them returns the transitions taken, in order (the front-end mirrors them into the
    address space and its events); a refused move raises :class:`InvalidState`."""

    def __init__(self) -> None:
        self.vision = VisionState.PREOPERATIONAL
        self.automatic: AutomaticState | None = None
        """The automatic mode's state while Operational; None otherwise."""

    # ------------------------------------------------------------------ what is allowed

    @property
    def ready(self) -> bool:
        return self.vision is VisionState.OPERATIONAL and self.automatic is AutomaticState.READY

    @property
    def executing(self) -> bool:
        return self.automatic in (
            AutomaticState.SINGLE_EXECUTION,
            AutomaticState.CONTINUOUS_EXECUTION,
        )

    def describe(self) -> str:
        if self.automatic is None:
            return self.vision.browse_name
        return f"{self.vision.browse_name}/{self.automatic.browse_name}"

    def _require_ready(self, method: str) -> None:
        if not self.ready:
            raise InvalidState(
                f"{method} needs Operational/Ready; the vision system is {self.describe()}"
                + ("" if self.vision is not VisionState.HALTED else " (Reset it first)")
                + ("" if self.vision is not VisionState.ERROR else " (Reset it first)")
                + ("" if not self.executing else " (a job runs: wait, Stop or Abort it)")
            )

    # ------------------------------------------------------------------ moves

    def become_operational(self, *, automatic: bool) -> list[Transition]:
        """Preoperational → Operational, whose automatic mode starts in Initialized and goes
        on to Ready (every recipe is prepared)."""
        if self.vision is not VisionState.PREOPERATIONAL:
            if self.vision is VisionState.OPERATIONAL and not automatic:
                return []  # SelectModeAutomatic while already in it: nothing to do
            raise InvalidState(
                f"SelectModeAutomatic needs Preoperational; the vision system is {self.describe()}"
            )
        taken = [self._vision_to(VisionState.OPERATIONAL, automatic=automatic)]
        self.automatic = AutomaticState.INITIALIZED
        taken.append(self._automatic_to(AutomaticState.READY, automatic=True))
        return taken

    def start_single(self) -> list[Transition]:
        self._require_ready("StartSingleJob")
        return [self._automatic_to(AutomaticState.SINGLE_EXECUTION, automatic=False)]

    def start_continuous(self) -> list[Transition]:
        self._require_ready("StartContinuous")
        return [self._automatic_to(AutomaticState.CONTINUOUS_EXECUTION, automatic=False)]

    def job_done(self) -> list[Transition]:
        """A job ended by itself: a single job with its result, a continuous one with a run
        that did not complete. Nothing when no job runs (an Abort or Halt came first)."""
        if self.executing:
            return [self._automatic_to(AutomaticState.READY, automatic=True)]
        return []

    def stop(self) -> list[Transition]:
        if not self.executing:
            raise InvalidState(f"Stop needs a job running; the vision system is {self.describe()}")
        return [self._automatic_to(AutomaticState.READY, automatic=False)]

    def abort(self) -> list[Transition]:
        if not self.executing or self.automatic is None:
            raise InvalidState(f"Abort needs a job running; the vision system is {self.describe()}")
        source = self.automatic.browse_name
        self.automatic = AutomaticState.READY
        return [Transition("automatic", source, "Ready", ABORT_TRANSITIONS[source])]

    def halt(self) -> list[Transition]:
        """Halt from any state but Halted (a running job is the caller's to end first)."""
        if self.vision is VisionState.HALTED:
            raise InvalidState("Halt: the vision system is Halted already")
        self.automatic = None
        return [self._vision_to(VisionState.HALTED, automatic=False)]

    def fail(self) -> list[Transition]:
        """An internal error: Operational (or Preoperational) → Error."""
        if self.vision in (VisionState.ERROR, VisionState.HALTED):
            return []
        self.automatic = None
        return [self._vision_to(VisionState.ERROR, automatic=True)]

    def reset(self) -> list[Transition]:
        """Halted or Error → Preoperational (the caller then makes it Operational again)."""
        if self.vision not in (VisionState.HALTED, VisionState.ERROR):
            raise InvalidState(
                f"Reset needs Halted or Error; the vision system is {self.describe()}"
            )
        return [self._vision_to(VisionState.PREOPERATIONAL, automatic=False)]

    # ------------------------------------------------------------------ bookkeeping

    def _vision_to(self, target: VisionState, *, automatic: bool) -> Transition:
        source = self.vision.browse_name
        number = TRANSITIONS[(source, target.browse_name, automatic)]
        self.vision = target
        return Transition("vision", source, target.browse_name, number)

    def _automatic_to(self, target: AutomaticState, *, automatic: bool) -> Transition:
        assert self.automatic is not None
        source = self.automatic.browse_name
        number = TRANSITIONS[(source, target.browse_name, automatic)]
        self.automatic = target
        return Transition("automatic", source, target.browse_name, number)


__all__ = [
    "AutomaticState",
    "InvalidState",
    "Machines",
    "Transition",
    "VisionState",
]
