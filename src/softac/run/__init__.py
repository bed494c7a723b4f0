"""A training run: the loop, callbacks, run state, checkpoints and run directory, evaluation, CSV logs, loggers."""
