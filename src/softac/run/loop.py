"""The training loop: a chunk of env steps and their updates from the run's source of transitions
(softac.run.transitions), then what is due (evaluate, log, checkpoint, callbacks, progress), until done.

With the host's source a chunk is one vector-env step: one policy call (jitted), one step of each env, one
buffer write (vectorised) and one jitted update that runs all `gradient_steps`. Metrics stay on the device
until a log row needs them.
"""

from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from softac.run import checkpoint as ckpt
from softac.run.callbacks import CallbackList, TrainingInfo
from softac.replay.collector import Collector
from softac.base.cpus import usable_cpus
from softac.errors import RunFailed, SoftacError, TrainingInterrupted
from softac.run.evaluation import EVAL_SEED_OFFSET, MAX_PARALLEL, run_episodes, summarize
from softac.config.names import parse_backends
from softac.config.sac_config import SACConfig
from softac.run.loggers import Loggers, check_backends_installed, run_loggers
from softac.run.csv_logs import Progress, TrainRows
from softac.learner.learner import Learner
from softac.run.run_dir import checkpoint_path, holds_run, versions, write_config, write_summary
from softac.run.run_state import RunState
from softac.run.stopping import check_success_rate, target_reached
from softac.run.device_transitions import DeviceTransitions
from softac.run.transitions import Chunk, HostTransitions
from softac.run.checkpoint_contents import checkpoint_parts
from softac.base.stop_signal import StopSignal


SHOW_EVERY = 100  # env steps between progress-bar refreshes


def crossed(before: int, after: int, interval: int) -> bool:
    """Did the step counter pass a multiple of `interval` going from `before` to `after`?"""
    return interval > 0 and before // interval != after // interval


def _check_finite(metrics: dict[str, float], step: int) -> None:
    bad = [k for k, v in metrics.items() if not np.isfinite(v)]
    if bad:
        raise RunFailed(f"training diverged at step {step}: {', '.join(bad)} became non-finite "
                        "(try lower learning rates); the last good checkpoint is kept")


class RunWriter:
    """What one training call writes into its run directory: the directory (made after the checks), its
    config, its logs (the CSV files and the chosen logger backends); checkpoints written atomically (a
    failed write keeps the previous one and fails the run, exit 3); the summary at a normal end."""

    def __init__(self, run: Path, config: dict[str, Any], extra: dict[str, Any], resume_step: int):
        try:
            run.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise SoftacError(f"cannot create run directory {run}: {exc.strerror or exc}") from None
        self.run = run
        write_config(run, config, {"versions": versions(), **extra}, start_step=resume_step,
                     continuing=holds_run(run))  # a resumed run keeps each segment's record
        self.loggers = run_loggers(run, parse_backends(config["loggers"]), config, resume_step)

    def has_checkpoint(self, name: str) -> bool:
        return checkpoint_path(self.run, name).exists()

    def save_checkpoint(self, name: str, meta: dict[str, Any], arrays: dict[str, Any]) -> str:
        path = checkpoint_path(self.run, name)
        try:
            return str(ckpt.save(path, meta, arrays))
        except OSError as exc:
            raise RunFailed(f"could not write checkpoint {path}: {exc.strerror or exc}; "
                            "the previous checkpoint is kept") from None

    def write_summary(self, summary: dict[str, Any]) -> None:
        write_summary(self.run, summary)

    def close(self) -> None:
        Loggers(self.loggers).close()


def transitions_source(learner: Learner, collector: Any, run_state: RunState) -> Any:
    """The device's source for a collector of device envs (softac.run.device_transitions), else the host's."""
    from softac.replay.device_collector import DeviceCollector

    if isinstance(collector, DeviceCollector):
        return DeviceTransitions(learner, collector, run_state)
    return HostTransitions(learner, collector, run_state)


def train(learner: Learner, collector: Collector, run: RunState, steps: int, run_dir: str | Path | None = None,
          target_return: float | None = None, progress: bool | None = None, callbacks: list | None = None,
          loggers: list | None = None, target_success: float | None = None) -> dict[str, Any]:
    """Train `learner` for `steps` more env steps on what `collector` gathers, advancing `run`; with
    `run_dir`, write the run directory as it goes. `callbacks` (softac.run.callbacks.Callback) run at the loop's
    hooks; `loggers` (softac.run.loggers.Logger) get every metrics record besides the run directory's own logs."""
    return TrainingLoop(learner, collector, run, steps, run_dir, target_return, progress, callbacks, loggers,
                        target_success=target_success).run()


class TrainingLoop:
    """One training call: chunks of collecting and learning, and the work due at each interval (log rows, evaluations,
    checkpoints, callbacks), until `steps` more env steps, a target return or success rate, or a stop. Every input is
    checked when it is made, before the run directory is written (a refused callback leaves no half-made
    run); `run()` opens the run directory and everything else inside one `try`."""

    def __init__(self, learner: Learner, collector: Collector, run_state: RunState, steps: int,
                 run_dir: str | Path | None = None, target_return: float | None = None, progress: bool | None = None,
                 callbacks: list | None = None, loggers: list | None = None, agent: Any = None,
                 target_success: float | None = None):
        if steps < 0:
            raise SoftacError(f"steps must be >= 0, got {steps}")
        check_success_rate(target_success, "target_success")
        self.run_path = Path(run_dir) if run_dir is not None else None
        check_backends_installed(parse_backends(learner.config.loggers) if self.run_path is not None else [])
        self.learner, self.collector, self.run_state = learner, collector, run_state
        self.source = transitions_source(learner, collector, run_state)
        self.start_step = self.run_state.num_steps
        self.end_step = self.start_step + steps
        self.target_return, self.target_success = target_return, target_success
        self.info = TrainingInfo(learner, run_state, self.start_step, self.end_step,
                                 self.run_path.resolve() if self.run_path is not None else None, self.metric_values,
                                 collector.apply, agent=agent)
        try:
            self.hooks = CallbackList(list(callbacks or []), self.info)
        except TypeError as exc:
            raise SoftacError(str(exc)) from None
        if self.run_path is not None:
            self.run_state.check_may_write(self.run_path)
        self._raise_budget(self.end_step)
        self.extra_loggers = list(loggers or [])
        self.progress = progress
        self.writer: RunWriter | None = None
        self.logs: Loggers | None = None
        self.eval_envs: list | None = None
        self.stop_reason: str | None = None  # target_return, target_success or a callback's reason: stop now
        self.logged_at: int | None = None
        self.chunk_started_at: int | None = None  # the last chunk's first step (reset_if_due)
        self.logged_metrics: dict[str, float] = {}  # the last progress row's means

    @property
    def config(self) -> SACConfig:
        return self.learner.config

    def _raise_budget(self, end_step: int) -> None:
        """A raised budget is the run's own from now on (set once every input is accepted): its checkpoints and
        summary.json carry it, so a later resume continues to it, and the end-of-run evaluation, the resets and
        the learning-rate schedule follow it. The config itself never changes (it is frozen): the learner and the
        collector get one with the new total_steps."""
        if end_step > self.config.total_steps:
            self.learner.config = self.collector.config = self.config.replace(total_steps=end_step)

    def run(self) -> dict[str, Any]:
        self.source.start()
        self.wall0, self.time0 = time.perf_counter(), self.run_state.train_time_s
        # progress.csv's fps, return_mean and success_rate
        self.rows = TrainRows(self.start_step, self.run_state.recent_returns, self.run_state.recent_successes)
        self.show = Progress(self.start_step, self.end_step, enabled=self.progress)
        next_show = self.start_step
        try:
            self.open_run_dir()
            with StopSignal() as self.stop:
                if self.hooks and self.hooks.call("on_training_start"):
                    self.stop_reason = f"callback: {self.info.stop_reason}"
                if self.writer is not None and not self.writer.has_checkpoint("last"):
                    self.save_checkpoint("last")  # from its first moment a run holds a loadable checkpoint
                if self.stop_reason is None:
                    self.stop_reason = self.redo_interrupted_evaluation()
                while self.run_state.num_steps < self.end_step and self.stop_reason is None:
                    if self.stop.requested:
                        raise TrainingInterrupted(self.run_state.num_steps, self.save_checkpoint("last"))
                    self.reset_if_due()
                    chunk = self.source.chunk(self.end_step)
                    self.chunk_started_at = chunk.before
                    self.count_episodes(chunk)
                    self.stop_reason = self.on_intervals(chunk.before, chunk.after)
                    after = chunk.after
                    if after >= next_show or self.stop_reason is not None:  # redraw at most every SHOW_EVERY
                        next_show = after + SHOW_EVERY
                        self.show.update(after, ret=self.rows.recent_mean(), eval=self.run_state.last_eval,
                                         success=self.run_state.last_success)
                self.finish()
        finally:
            self.close()
        return self.summarise()

    # ---- set up and tear down ------------------------------------------------------------------------

    def open_run_dir(self) -> None:
        if self.run_path is not None:
            extra = {"resolved_target_entropy": self.learner.target_entropy,
                     "resolved_matmul_dtype": self.learner.matmul_dtype,
                     "buffer_bytes_per_transition": round(self.collector.bytes_per_transition, 1),
                     "cpus": len(usable_cpus()) or os.cpu_count()}
            self.writer = RunWriter(self.run_path, self.config.to_dict(), extra, resume_step=self.start_step)
            self.run_state.run_dir = self.run_path.resolve()
        all_loggers = (self.writer.loggers if self.writer is not None else []) + self.extra_loggers
        self.logs = Loggers(all_loggers) if all_loggers else None

    def close(self) -> None:
        self.show.close(self.run_state.num_steps)
        self.run_state.train_time_s = self.elapsed()
        self.keep_recent_episodes()
        if self.writer is not None:
            self.writer.close()
        for env in self.eval_envs or []:
            with contextlib.suppress(Exception):
                env.close()

    def finish(self) -> None:
        """The run's last log row and evaluation, off the intervals' grid, only where the run ends (its
        total_steps, a target or a callback): a segment that stops short of it and is resumed later must
        leave the logs, the best checkpoint and eval.csv as one straight run leaves them. Then the last
        checkpoint."""
        final_step = self.run_state.num_steps
        ends_here = final_step >= self.config.total_steps or self.stop_reason is not None
        run_ends = final_step > self.start_step and ends_here
        if run_ends and self.logged_at != final_step:
            self.log_row(final_step)
        # the final evaluation also in a segment that resumed at the last step: the segment before was stopped
        # (SIGTERM) during that evaluation, after its checkpoint (seen: a sweep's driver killed as a trial ended)
        if ends_here and self.config.eval_interval > 0 and self.run_state.last_eval_step != final_step:
            self.evaluate(final_step)
        where = self.save_checkpoint("last")
        if self.stop.requested:
            raise TrainingInterrupted(self.run_state.num_steps, where)

    def redo_interrupted_evaluation(self) -> str | None:
        """The evaluation due at the step this segment resumes from, when a stop (SIGTERM, Ctrl-C) cut it short
        in the segment before, after that step's update: done first, so that eval.csv, the best checkpoint and
        a target's stop are as in an undisturbed run (seen: a sweep's trial stopped as its driver was killed).
        Evaluation draws none of the run's random numbers, so doing it later changes nothing else."""
        cfg, step = self.config, self.start_step
        last_collect = step - cfg.n_envs
        if (step == 0 or cfg.eval_interval <= 0 or self.run_state.last_eval_step == step
                or not crossed(last_collect, step, cfg.eval_interval)):
            return None
        reached = self.target_reached(self.evaluate(step))
        if reached and not crossed(last_collect, step, cfg.log_interval):
            self.log_row(step)  # where an undisturbed run's finish() writes it (a logged step is logged already)
        return reached

    def summarise(self) -> dict[str, Any]:
        rs = self.run_state
        summary = {
            "steps": rs.num_steps, "episodes": rs.num_episodes, "train_time_s": rs.train_time_s,
            "wall_s": time.perf_counter() - self.wall0, "last_eval": rs.last_eval, "best_eval": rs.best_eval,
            "stopped_early": self.stop_reason is not None, "stop_reason": self.stop_reason or "steps",
            "recent_return_mean": self.rows.recent_mean(), "best_step": rs.best_step,
            "total_steps": self.config.total_steps,
        }
        if self.collector.spaces.goal_env or rs.last_success is not None or self.rows.successes:
            summary.update(last_success=rs.last_success, recent_success_rate=self.rows.success_rate())
        if self.writer is not None:
            self.writer.write_summary(summary)
        if self.hooks:
            self.hooks.call("on_training_end", summary)
        return summary

    # ---- the steps of the loop ---------------------------------------------------------------------

    def keep_recent_episodes(self) -> None:
        """The last episodes' returns and successes into the run state: a checkpoint, and the next learn(),
        go on from them."""
        self.run_state.recent_returns = list(self.rows.recent)
        self.run_state.recent_successes = list(self.rows.successes)

    def elapsed(self) -> float:
        return self.time0 + time.perf_counter() - self.wall0

    def metric_values(self) -> dict[str, float]:
        """Each metric's mean over the updates since the last progress row, or at a row's own step that row's
        (reading them waits for the device); {} before learning."""
        return self.learner.metrics() or self.logged_metrics

    def reset_if_due(self) -> None:
        """reset_interval: before the first chunk past each multiple (with the host's one-step chunks, at the
        first step past it), so the evaluation and checkpoint at the multiple see the policy before the reset
        and a resumed run resets where a straight one does; none at or past total_steps (a rule of the config,
        not of this call): a reset needs the rest of the budget to recover."""
        step, cfg = self.run_state.num_steps, self.config
        before = self.chunk_started_at if self.chunk_started_at is not None else step - cfg.n_envs
        if 0 < step < cfg.total_steps and crossed(before, step, cfg.reset_interval):
            self.learner.reset_networks(cfg.seed, step // cfg.reset_interval)

    def count_episodes(self, chunk: Chunk) -> None:
        """The episodes that ended in a chunk: counted, in the progress rows' recent returns, and logged."""
        for episode in chunk.finished:
            self.run_state.num_episodes += 1
            self.rows.episode_finished(episode.ret, episode.success)
            if self.logs is not None:
                values = {"return": round(episode.ret, 6), "length": episode.length}
                if episode.success is not None:
                    values["success"] = episode.success
                self.logs.log("rollout", values, chunk.after if episode.step is None else episode.step)

    def on_intervals(self, before: int, after: int) -> str | None:
        """The work due every log, eval and checkpoint interval, and the callbacks' on_step; why training
        should stop now (target_return, target_success or a callback's reason), else None."""
        cfg, reached = self.config, None
        if crossed(before, after, cfg.log_interval):
            self.log_row(after)
        if crossed(before, after, cfg.eval_interval):
            stats = self.evaluate(after)
            reached = self.target_reached(stats)
        if self.hooks:
            self.hooks.call("on_step")
        stopping = reached or self.info.stop_reason is not None
        if crossed(before, after, cfg.checkpoint_interval) and not stopping:  # (saved by finish() when stopping)
            self.save_checkpoint("last")
        if reached:
            return reached
        return f"callback: {self.info.stop_reason}" if self.info.stop_reason is not None else None

    def target_reached(self, stats: dict[str, Any] | None) -> str | None:
        """`target_return` or `target_success` when an evaluation reached it (either stops training)."""
        if stats is None:
            return None
        return target_reached(stats["mean_return"], stats.get("success_rate"), self.target_return, self.target_success)

    def log_row(self, step: int) -> None:
        self.logged_at = step
        row = self.rows.row(step, self.elapsed(), self.run_state.num_episodes)
        values = self.logged_metrics = self.learner.take_metrics()
        _check_finite(values, step)
        row.update(values)
        if self.logs is not None:
            self.logs.log("train", {k: v for k, v in row.items() if k != "step"}, step)

    def evaluate(self, step: int) -> dict[str, Any] | None:
        cfg, rs, make_env = self.config, self.run_state, self.collector.make_env
        if isinstance(self.source, DeviceTransitions):  # all episodes at once on the device's envs (issue 67)
            stats = summarize(*self.source.episodes(cfg.eval_episodes, cfg.seed + EVAL_SEED_OFFSET))
        else:
            if self.eval_envs is None:
                self.eval_envs = [make_env() for _ in range(min(cfg.eval_episodes, MAX_PARALLEL))]
            stats = run_episodes(self.learner.predict, make_env, cfg.eval_episodes, cfg.seed + EVAL_SEED_OFFSET,
                                 envs=self.eval_envs, should_stop=lambda: self.stop.requested)
        if self.stop.requested:  # cut short by Ctrl-C/SIGTERM: a partial evaluation is not a result
            return None
        rs.last_eval, rs.last_eval_step, rs.last_success = stats["mean_return"], step, stats["success_rate"]
        if self.logs is not None:
            values = {"mean_return": stats["mean_return"], "std_return": stats["std_return"],
                      "episodes": stats["episodes"]}
            if stats["success_rate"] is not None:
                values["success_rate"] = stats["success_rate"]
            self.logs.log("eval", values, step)
        if rs.best_eval is None or stats["mean_return"] > rs.best_eval:
            rs.best_eval, rs.best_step = stats["mean_return"], step
            self.save_checkpoint("best")
        if self.hooks:
            self.hooks.call("on_eval", stats)
        return stats

    def save_checkpoint(self, name: str) -> str | None:
        """`last` with the buffer and envs (to resume), `best` without; never diverged weights over good ones."""
        if self.writer is None:
            return None
        _check_finite(self.metric_values(), self.run_state.num_steps)
        self.run_state.train_time_s = self.elapsed()
        self.keep_recent_episodes()
        parts = checkpoint_parts(self.learner, self.run_state, self.collector, include_buffer=name == "last")
        path = self.writer.save_checkpoint(name, *parts)
        if self.hooks:
            self.hooks.call("on_checkpoint", name, path)
        return path
