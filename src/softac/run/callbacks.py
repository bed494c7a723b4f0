"""Callbacks: user code that runs inside `agent.learn(steps, callbacks=[...])`.

Subclass `Callback` and override the hooks you need. Each hook gets a `TrainingInfo` (the learner, the step,
the latest metrics and evaluations, the run directory, and the agent being trained). A hook that returns False, or calls
`info.stop("why")`, ends training cleanly: the loop stops after the current step, the final evaluation and
the `last` checkpoint are written as at a normal end, and the summary's `stop_reason` says why.

    class StopAt(Callback):
        def on_eval(self, info, stats):
            return stats["mean_return"] < 900  # False stops

Callbacks are not saved in checkpoints: one with state of its own rebuilds it in `on_training_start` (from
`info.step`, or the run's eval.csv) when a run resumes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

if TYPE_CHECKING:
    from softac.learner.learner import Learner
    from softac.run.run_state import RunState


@dataclass
class TrainingInfo:
    """What a callback sees; `stop(reason)` asks the loop to end after the current step."""

    learner: Learner  # the learner being trained: predict(obs) (its deterministic policy), state, obs statistics
    run_state: RunState  # the counters, random streams and evaluations the loop advances
    start_step: int  # where this learn() call started (a resumed run starts past 0)
    end_step: int  # where it will stop unless stopped earlier
    run_dir: Path | None
    read_metrics: Callable[[], dict[str, float]] = field(repr=False, default=dict)
    apply_envs: Callable[[Callable[[Any], Any]], list[Any]] = field(repr=False, default=lambda fn: [])
    stop_reason: str | None = None
    # the softac.SAC whose learn() runs the loop, for callbacks that save or evaluate the whole agent
    # (SB3's `self.model`); the loop itself never reads it
    agent: Any = field(repr=False, default=None)

    @property
    def step(self) -> int:
        """Env steps so far (summed over the vector envs)."""
        return self.run_state.num_steps

    @property
    def episodes(self) -> int:
        return self.run_state.num_episodes

    @property
    def last_eval(self) -> float | None:
        return self.run_state.last_eval

    @property
    def best_eval(self) -> float | None:
        return self.run_state.best_eval

    @property
    def metrics(self) -> dict[str, float]:
        """The losses, alpha and Q means, each the mean over the gradient steps since the last progress row that
        computed it (the actor's over actor steps; at a row's own step, that row's values; empty before learning
        starts). Reading them waits
        for the device, so read them when needed rather than on every step."""
        return self.read_metrics()

    def stop(self, reason: str) -> None:
        self.stop_reason = self.stop_reason or reason

    def apply_to_envs(self, fn: Callable[[Any], Any]) -> list[Any]:
        """Call `fn(env)` on each training env (e.g. to change a physics parameter for a curriculum) and
        return the results. Evaluation envs are fresh copies of the env and are not changed."""
        return self.apply_envs(fn)


class Callback:
    """Override any of these; returning False (not None) stops training cleanly."""

    def on_training_start(self, info: TrainingInfo) -> bool | None:
        """Before the first step of this learn() call (also when a run resumes)."""

    def on_step(self, info: TrainingInfo) -> bool | None:
        """After each vector-env step: n_envs transitions stored and their gradient steps done."""

    def on_eval(self, info: TrainingInfo, stats: dict[str, Any]) -> bool | None:
        """After each deterministic evaluation; `stats` has mean_return, std_return, episodes, returns."""

    def on_checkpoint(self, info: TrainingInfo, name: str, path: str) -> bool | None:
        """After a checkpoint is written: `name` is last or best."""

    def on_training_end(self, info: TrainingInfo, summary: dict[str, Any]) -> None:
        """When learn() returns normally (budget reached, target return, or a stop); not after Ctrl-C or a
        failed run."""


class CallbackList:
    """The callbacks of one learn() call, run in order; a stop from any of them is kept with its name."""

    def __init__(self, callbacks: list[Callback], info: TrainingInfo):
        for callback in callbacks:
            if not any(callable(getattr(callback, hook, None)) for hook in HOOKS):
                raise TypeError(f"{callback!r} is not a callback: it has none of {', '.join(HOOKS)}")
        self.callbacks = list(callbacks)
        self.info = info

    def __bool__(self) -> bool:
        return bool(self.callbacks)

    def call(self, hook: str, *args: Any) -> bool:
        """Run `hook` on every callback; True when training should stop."""
        for callback in self.callbacks:
            method = getattr(callback, hook, None)
            if method is not None and method(self.info, *args) is False:
                self.info.stop(f"{type(callback).__name__}.{hook} returned False")
        return self.info.stop_reason is not None


HOOKS = ("on_training_start", "on_step", "on_eval", "on_checkpoint", "on_training_end")


class StopOnPlateau(Callback):
    """Stop when the evaluation mean has not improved by more than `min_delta` for `patience` evaluations
    in a row (early stopping, as SB3's StopTrainingOnNoModelImprovement), after at least `min_evals`."""

    def __init__(self, patience: int = 5, min_delta: float = 0.0, min_evals: int = 0):
        if patience < 1:
            raise ValueError("patience must be >= 1")
        self.patience, self.min_delta, self.min_evals = patience, min_delta, min_evals
        self.best: float | None = None
        self.evals = self.since_best = 0

    def on_training_start(self, info: TrainingInfo) -> None:
        self.best = info.best_eval  # a resumed run starts from the best it had
        self.since_best = 0

    def on_eval(self, info: TrainingInfo, stats: dict[str, Any]) -> bool | None:
        self.evals += 1
        mean = stats["mean_return"]
        if self.best is None or mean > self.best + self.min_delta:
            self.best, self.since_best = mean, 0
            return None
        self.since_best += 1
        if self.since_best >= self.patience and self.evals >= self.min_evals:
            info.stop(f"eval mean return has not improved on {self.best:.1f} for {self.patience} evaluations")
        return None
