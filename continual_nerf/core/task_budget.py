"""Which task is open and how long it trains: the continual state the pipeline owns and checkpoints."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Dict, Optional


@dataclass
class TaskBudget:
    """The open task's budget in training iterations or training seconds; "Next task now" spends it at once.

    Only training iterations count: the pipeline's clock runs from before an iteration to after it, so evaluation,
    checkpoints and task switches cost no budget.
    """

    iterations: int
    """Training iterations per task (ignored when `seconds` is set)."""
    seconds: Optional[float] = None
    """Training seconds per task (the paper's time-constrained setting), or None to count iterations."""
    iterations_done: int = 0
    """Training iterations of the open task so far."""
    seconds_done: float = 0.0
    """Training seconds of the open task so far."""
    total_seconds: float = 0.0
    """Training seconds of the whole run so far, every task included."""
    next_task_requested: bool = False
    """Set by the viewer's "Next task now": the open task ends after the current iteration."""

    def count(self, seconds: float) -> None:
        """Add one training iteration that took `seconds`."""
        self.iterations_done += 1
        self.seconds_done += seconds
        self.total_seconds += seconds

    def request_next_task(self) -> None:
        self.next_task_requested = True

    def spent(self) -> bool:
        if self.next_task_requested:
            return True
        if self.seconds is not None:
            return self.seconds_done >= self.seconds
        return self.iterations_done >= self.iterations

    def start_task(self) -> None:
        """A new task opens with its whole budget."""
        self.iterations_done = 0
        self.seconds_done = 0.0
        self.next_task_requested = False

    def progress(self) -> float:
        """How much of the open task's budget is spent, from 0 to 1."""
        done = self.seconds_done / self.seconds if self.seconds is not None else self.iterations_done / self.iterations
        return min(done, 1.0)

    def progress_text(self) -> str:
        """What is left of the open task's budget, as the viewer shows it."""
        if self.next_task_requested:
            return "ending the task (next task now)"
        if self.spent():
            return "budget spent"
        if self.seconds is not None:
            return f"{max(self.seconds - self.seconds_done, 0.0):.0f} s left of {self.seconds:g} s"
        return f"iteration {self.iterations_done} of {self.iterations}"

    def state(self) -> Dict[str, Any]:
        """What a checkpoint keeps: the progress, not the options (those come from the resumed run's config)."""
        return {
            "iterations_done": self.iterations_done,
            "seconds_done": self.seconds_done,
            "total_seconds": self.total_seconds,
        }

    def load_state(self, state: Dict[str, Any]) -> None:
        self.iterations_done = int(state["iterations_done"])
        self.seconds_done = float(state["seconds_done"])
        self.total_seconds = float(state["total_seconds"])


@dataclass
class TaskState:
    """The open task; tasks 1..current are released (their rays are usable, the open task's pixels too)."""

    current: int = 0
    """Index of the open task (0-based)."""

    @property
    def released_tasks(self) -> int:
        return self.current + 1

    def state(self) -> Dict[str, Any]:
        return asdict(self)

    def load_state(self, state: Dict[str, Any]) -> None:
        self.current = int(state["current"])
