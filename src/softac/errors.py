"""User-facing errors: the CLI prints their message on one line and exits 2 (bad input) or 3 (a run that
started and then failed)."""


class SoftacError(Exception):
    """A user-facing error: bad input, a missing or corrupt checkpoint, a bad env."""


class RunFailed(SoftacError):
    """A run that started and then failed: the loss diverged, the env returned NaN or raised mid-run, a
    checkpoint could not be written (a full disk). The last good checkpoint is kept; the CLI exits 3."""


class EnvError(SoftacError):
    """An env that cannot be used: an unknown id, a space SAC cannot act in (bad input, exit 2)."""


class EnvFailed(EnvError, RunFailed):
    """An env that raised or returned non-finite values once the run had started (exit 3)."""


class ConfigError(SoftacError, ValueError):
    """A bad config key or value; the message names the key."""


class CheckpointError(SoftacError):
    """A checkpoint that cannot be read, or does not fit the config and env it is loaded for (exit 2)."""


class TrainingInterrupted(Exception):
    """Ctrl-C or SIGTERM stopped training after a checkpoint was written (exit 130)."""

    def __init__(self, step: int, checkpoint: str | None):
        self.step = step
        self.checkpoint = checkpoint
        where = f"; checkpoint at {checkpoint}" if checkpoint else ""
        super().__init__(f"interrupted at step {step}{where}")
