"""Errors that mean bad input: the CLI prints their message on one line and exits 2."""


class SoftacError(Exception):
    """A user-facing error: bad input, a missing or corrupt checkpoint, a bad env."""


class TrainingInterrupted(Exception):
    """Ctrl-C or SIGTERM stopped training after a checkpoint was written (exit 130)."""

    def __init__(self, step: int, checkpoint: str | None):
        self.step = step
        self.checkpoint = checkpoint
        where = f"; checkpoint at {checkpoint}" if checkpoint else ""
        super().__init__(f"interrupted at step {step}{where}")
