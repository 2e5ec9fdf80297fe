"""Ctrl-C (SIGINT) and SIGTERM during a run.

While tasks train, a signal is answered at the start of the next training iteration: the trainer saves a checkpoint
of the last finished step, marks the run `interrupted` and prints one line with the command that resumes it, then the
process exits with 128 + the signal's number (130, 143). Before training starts, once it has finished, or at a second
signal there is nothing to save or the user insists: the process exits at once.
"""

from __future__ import annotations

import shlex
import signal
import sys
import threading
from pathlib import Path
from types import FrameType
from typing import Any, Callable, Dict, List, Optional, Sequence

from nerfstudio.utils import comms

EXIT_CODES: Dict[int, int] = {signal.SIGINT: 130, signal.SIGTERM: 143}
"""Exit status per signal, as a shell reports a process the signal ended."""

LOAD_OPTIONS = ("--load-dir", "--load-step", "--load-checkpoint")
"""ns-train's options that choose the checkpoint to start from; a resume command names its own."""


class Interrupts:
    """This process's SIGINT and SIGTERM handlers while a run lives."""

    def __init__(self) -> None:
        self.received: Optional[int] = None
        """The signal to answer at the next iteration, if one arrived while tasks were training."""
        self.deferring = False
        """Whether tasks are training: a signal waits for the end of the iteration instead of ending the process."""
        self.on_signal: Callable[[], None] = lambda: None
        """Called when a signal is deferred (the trainer leaves its pause, so that the next iteration comes)."""
        self.answered = False
        """Whether the run has saved and said how to resume: a later signal (the launcher stopping the processes once
        one has ended) ends the process without another line."""
        self._previous: Dict[int, Any] = {}
        self._installed = 0
        """Installs not restored yet: the handlers stay until the outermost restore (ns-train's lasts the process)."""

    def install(self) -> None:
        if in_main_thread():  # only the main thread may set handlers; a run driven from another keeps the defaults
            self._installed += 1
            for number in EXIT_CODES:
                self._previous.setdefault(number, signal.signal(number, self._handle))

    def restore(self) -> None:
        """Nothing pending; the handlers from before the outermost install once each install is restored (from the
        main thread: another leaves them for it)."""
        if in_main_thread() and self._installed:
            self._installed -= 1
            if not self._installed:
                for number, handler in self._previous.items():
                    signal.signal(number, handler)
                self._previous.clear()
        self.received, self.deferring, self.answered = None, False, False

    def _handle(self, number: int, frame: Optional[FrameType]) -> None:
        if self.deferring and self.received is None:
            self.received = number
            self.on_signal()
            return
        if comms.is_main_process() and not self.answered:  # every process of the run receives Ctrl-C; one says so
            name = signal.Signals(number).name
            print(f"Stopped by {name}; the checkpoints written so far are kept", file=sys.stderr, flush=True)
        raise SystemExit(EXIT_CODES[number])

    def pending(self) -> bool:
        return self.received is not None


def in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


INTERRUPTS = Interrupts()
"""The process's handlers: signals belong to the process, not to one trainer."""


def resume_command(checkpoint_dir: Path, argv: List[str], dropped: Sequence[str] = ()) -> str:
    """The command that resumes a run started with `argv` from `checkpoint_dir`: ns-train's own arguments with
    `--load-dir` right after the method (other load options and the `dropped` ones, with their values, left out), or a
    description when not started by ns-train."""
    program, *arguments = argv
    if Path(program).name != "ns-train" or not arguments:
        return f"its ns-train command with --load-dir {shlex.quote(str(checkpoint_dir))}"
    left_out = (*LOAD_OPTIONS, *dropped)
    kept: List[str] = []
    skip_value = False
    for argument in arguments[1:]:
        if skip_value:
            skip_value = False
        elif argument in left_out:
            skip_value = True
        elif not argument.startswith(tuple(f"{option}=" for option in left_out)):
            kept.append(argument)
    return shlex.join(["ns-train", arguments[0], "--load-dir", str(checkpoint_dir), *kept])
