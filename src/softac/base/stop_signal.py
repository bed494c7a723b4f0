"""Ctrl-C and SIGTERM during training: a flag the training loop (softac's, or a peer's run in softac.peers)
checks between steps, so that it stops after writing a checkpoint (exit 130) instead of dying mid-write."""

from __future__ import annotations

import math
import signal
import threading
from typing import Any

_finish_after_stop = False
_end_within_s: float | None = None


def finish_after_stop() -> None:
    """For a process that runs one command (`softac`, `python -m softac`, `python -m softac.peers`): once a
    signal has stopped training, a repeated SIGTERM is ignored until the process exits, so that it ends through
    its own path (its line, exit 130), not killed between the checkpoint and that line. A sweep's trial gets two:
    the sweep's, and its Ray worker's death (PR_SET_PDEATHSIG); measured, the second one 0.2-0.8 s after the
    first killed the process (-15) before it had said where it stopped. SIGKILL still ends it. Not for library
    callers (their handlers are restored as found), nor for main() called in-process."""
    global _finish_after_stop
    _finish_after_stop = True


def end_within_after_stop(seconds: float) -> None:
    """For a sweep trial's process: once a signal has stopped training, the process ends (SIGALRM, its default
    action) if it is still alive `seconds` later, wherever it is stuck, C code included. Its checkpoints are
    written atomically, so one cut short leaves the one before."""
    global _end_within_s
    _end_within_s = seconds
    signal.signal(signal.SIGALRM, signal.SIG_DFL)


class StopSignal:
    """SIGINT/SIGTERM set a flag the loop checks; a second Ctrl-C stops at once."""

    def __init__(self) -> None:
        self.requested = False
        self.previous: dict[int, Any] = {}

    def __enter__(self) -> "StopSignal":
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self.previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        if self.requested and signum == signal.SIGINT:
            raise KeyboardInterrupt
        if not self.requested and _end_within_s is not None:
            signal.alarm(max(1, math.ceil(_end_within_s)))
        self.requested = True

    def __exit__(self, *exc: Any) -> None:
        for sig, handler in self.previous.items():
            stopping = self.requested and _finish_after_stop and sig == signal.SIGTERM
            # SIG_IGN, not a Python handler, which the interpreter resets to the default as it exits (measured:
            # killed, -15, in its teardown); processes started after it would inherit SIG_IGN, so only a process
            # that runs one command and then exits takes this (finish_after_stop)
            signal.signal(sig, signal.SIG_IGN if stopping else handler)
