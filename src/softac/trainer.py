"""The training loop: collect, learn, evaluate, log, checkpoint, show progress.

Per vector-env step there is one policy call (jitted), one step of each env,
one buffer write (vectorised) and one jitted update that runs all
`gradient_steps`. Metrics stay on the device until a log row needs them.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from softac import checkpoint as ckpt
from softac.cpus import usable_cpus
from softac.errors import RunFailed, SoftacError, TrainingInterrupted
from softac.evaluation import EVAL_SEED_OFFSET, MAX_PARALLEL, run_episodes
from softac.callbacks import CallbackList, TrainingInfo
from softac.loggers import Loggers, check_backends_installed, parse_backends, run_loggers
from softac.logs import Progress, TrainRows
from softac.rundir import check_run_dir_for, checkpoint_path, holds_run, versions, write_config, write_summary
from softac.sac import Batch

if TYPE_CHECKING:  # the agent imports this module when it trains
    from softac.agent import SAC

SHOW_EVERY = 100  # env steps between progress-bar refreshes


def crossed(before: int, after: int, interval: int) -> bool:
    """Did the step counter pass a multiple of `interval` going from `before` to `after`?"""
    return interval > 0 and before // interval != after // interval


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
        self.requested = True

    def __exit__(self, *exc: Any) -> None:
        for sig, handler in self.previous.items():
            signal.signal(sig, handler)


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


def train(agent: SAC, steps: int, run_dir: str | Path | None = None, target_return: float | None = None,
          progress: bool | None = None, callbacks: list | None = None, loggers: list | None = None) -> dict[str, Any]:
    """Train `agent` for `steps` more env steps; with `run_dir`, write the run directory as it goes.
    `callbacks` (softac.callbacks.Callback) run at the loop's hooks; `loggers` (softac.loggers.Logger) get
    every metrics record besides the run directory's own logs."""
    if steps < 0:
        raise SoftacError(f"steps must be >= 0, got {steps}")
    check_backends_installed(parse_backends(agent.config.loggers) if run_dir is not None else [])
    cfg, fns, run_state = agent.config, agent.fns, agent.run
    buffer, pool = agent.training_parts()
    start_step = run_state.num_steps
    end_step = start_step + steps
    n_envs, act_dim = cfg.n_envs, agent.spaces.act_dim
    run = Path(run_dir) if run_dir is not None else None
    last_metrics: dict[str, Any] | None = None

    def read_metrics() -> dict[str, float]:
        return {k: float(v) for k, v in last_metrics.items()} if last_metrics is not None else {}

    # every input is checked before the run directory is written (a refused callback leaves no half-made run)
    info = TrainingInfo(agent, start_step, end_step, run.resolve() if run is not None else None, read_metrics)
    try:
        hooks = CallbackList(list(callbacks or []), info)
    except TypeError as exc:
        raise SoftacError(str(exc)) from None
    writer: RunWriter | None = None
    if run is not None:
        check_run_dir_for(run_state, run)
        extra = {"resolved_target_entropy": fns.target_entropy, "resolved_matmul_dtype": fns.matmul_dtype,
                 "buffer_bytes_per_transition": round(agent.buffer_bytes_per_transition, 1),
                 "cpus": len(usable_cpus()) or os.cpu_count()}
        writer = RunWriter(run, cfg.to_dict(), extra, resume_step=start_step)
        run_state.run_dir = run.resolve()
    all_loggers = (writer.loggers if writer is not None else []) + list(loggers or [])
    logs = Loggers(all_loggers) if all_loggers else None

    eval_envs: list | None = None
    show = Progress(start_step, end_step, enabled=progress)
    wall0 = time.perf_counter()
    time0 = run_state.train_time_s
    rows = TrainRows(start_step, run_state.recent_returns)  # progress.csv's fps and return_mean
    logged_at: int | None = None
    next_show = start_step
    stop_reason = "steps"  # or target_return, or a callback's reason

    def elapsed() -> float:
        return time0 + time.perf_counter() - wall0

    def save_checkpoint(name: str, with_buffer: bool) -> str | None:
        if writer is None:
            return None
        if last_metrics is not None:  # never replace a good checkpoint with diverged weights
            _check_finite({k: float(v) for k, v in last_metrics.items()}, run_state.num_steps)
        run_state.train_time_s = elapsed()
        run_state.recent_returns = list(rows.recent)
        path = writer.save_checkpoint(name, *agent.checkpoint_parts(include_buffer=with_buffer))
        if hooks:
            hooks.call("on_checkpoint", name, path)
        return path

    # ---- the steps of the loop -------------------------------------------------------------

    def collect() -> tuple[int, int]:
        """One vector-env step: act (uniformly at random before learning_starts), step the envs, store the
        transitions, count finished episodes. Returns the step counter before and after."""
        before = run_state.num_steps
        obs = pool.obs
        if agent.obs_norm is not None:  # every observation the policy acts on, warm-up included
            agent.obs_norm.update(obs)
        if before < cfg.learning_starts:
            actions = run_state.rng.uniform(-1.0, 1.0, (n_envs, act_dim)).astype(np.float32)
            env_actions = agent.scaler.to_env(actions)
        else:  # NumPy goes straight into the jitted call: jnp.asarray would cost more than the env step
            actions, env_actions, run_state.act_key = fns.act(agent.state.actor, agent.state.actor_stats,
                                                              agent.normalize_obs(obs), run_state.act_key)
            actions, env_actions = np.asarray(actions), np.asarray(env_actions)
            if not np.all(np.isfinite(actions)):
                raise RunFailed(f"training diverged at step {before}: the policy produced non-finite "
                                "actions; the last good checkpoint is kept")
        result = pool.step(env_actions, before)
        buffer.add(obs, actions, result.rewards, result.next_obs, result.terminated,
                   result.terminated | result.truncated)
        run_state.num_steps = after = before + n_envs
        for _, episode_return, length in result.finished:
            run_state.num_episodes += 1
            rows.episode_finished(episode_return)
            if logs is not None:
                logs.log("rollout", {"return": round(episode_return, 6), "length": length}, after)
        return before, after

    def learn(after: int) -> None:
        """`gradient_steps` updates in one jitted call, on batches normalised with the current statistics."""
        nonlocal last_metrics
        if after >= cfg.learning_starts and cfg.gradient_steps > 0 and len(buffer) > 0:
            batch = buffer.sample(run_state.rng, cfg.batch_size, cfg.gradient_steps)
            batch["obs"] = agent.normalize_obs(batch["obs"])  # the buffer holds raw observations
            batch["next_obs"] = agent.normalize_obs(batch["next_obs"])
            agent.state, last_metrics = fns.update(agent.state, Batch(**batch))

    def evaluate_now(step: int, stop: StopSignal) -> dict[str, Any] | None:
        nonlocal eval_envs
        if eval_envs is None:
            eval_envs = [agent.make_env() for _ in range(min(cfg.eval_episodes, MAX_PARALLEL))]
        stats = run_episodes(lambda obs: agent.predict(obs, deterministic=True), agent.make_env, cfg.eval_episodes,
                             cfg.seed + EVAL_SEED_OFFSET, envs=eval_envs, should_stop=lambda: stop.requested)
        if stop.requested:  # cut short by Ctrl-C/SIGTERM: a partial evaluation is not a result
            return None
        run_state.last_eval, run_state.last_eval_step = stats["mean_return"], step
        if logs is not None:
            logs.log("eval", {"mean_return": stats["mean_return"], "std_return": stats["std_return"],
                              "episodes": stats["episodes"]}, step)
        if run_state.best_eval is None or stats["mean_return"] > run_state.best_eval:
            run_state.best_eval, run_state.best_step = stats["mean_return"], step
            save_checkpoint("best", with_buffer=False)
        if hooks:
            hooks.call("on_eval", stats)
        return stats

    def log_row(step: int) -> None:
        nonlocal logged_at
        logged_at = step
        row = rows.row(step, elapsed(), run_state.num_episodes)
        if last_metrics is not None:
            values = {k: float(v) for k, v in last_metrics.items()}
            _check_finite(values, step)
            row.update(values)
        if logs is not None:
            logs.log("train", {k: v for k, v in row.items() if k != "step"}, step)

    def on_intervals(before: int, after: int, stop: StopSignal) -> str | None:
        """The work due every log, eval and checkpoint interval, and the callbacks' on_step; why training
        should stop now (target_return or a callback's reason), else None."""
        reached = False
        if crossed(before, after, cfg.log_interval):
            log_row(after)
        if crossed(before, after, cfg.eval_interval):
            stats = evaluate_now(after, stop)
            reached = stats is not None and target_return is not None and stats["mean_return"] >= target_return
        if hooks:
            hooks.call("on_step")
        stopping = reached or info.stop_reason is not None
        if crossed(before, after, cfg.checkpoint_interval) and not stopping:  # (saved below when stopping)
            save_checkpoint("last", with_buffer=True)
        if reached:
            return "target_return"
        return f"callback: {info.stop_reason}" if info.stop_reason is not None else None

    try:
        with StopSignal() as stop:
            if hooks and hooks.call("on_training_start"):
                stop_reason = f"callback: {info.stop_reason}"
            if writer is not None and not writer.has_checkpoint("last"):
                save_checkpoint("last", with_buffer=True)  # from its first moment a run holds a loadable checkpoint
            while run_state.num_steps < end_step and stop_reason == "steps":
                if stop.requested:
                    where = save_checkpoint("last", with_buffer=True)
                    raise TrainingInterrupted(run_state.num_steps, where)
                before = run_state.num_steps
                # reset_interval: at the first step past each multiple, so the evaluation and checkpoint at
                # the multiple see the policy before the reset and a resumed run resets where a straight one
                # does; none at or past total_steps (a rule of the config, not of this call): a reset needs
                # the rest of the budget to recover
                if 0 < before < cfg.total_steps and crossed(before - n_envs, before, cfg.reset_interval):
                    agent.state = fns.reset(agent.state, cfg.seed, before // cfg.reset_interval)
                before, after = collect()
                learn(after)
                stop_reason = on_intervals(before, after, stop) or stop_reason
                if after >= next_show or stop_reason != "steps":  # the bar redraws at most every SHOW_EVERY steps
                    next_show = after + SHOW_EVERY
                    show.update(after, ret=rows.recent_mean(), eval=run_state.last_eval)

            # the run's last log row and evaluation, off the intervals' grid, only where the run ends (its
            # total_steps, a target or a callback): a segment that stops short of it and is resumed later
            # must leave the logs, the best checkpoint and eval.csv as one straight run leaves them
            final_step = run_state.num_steps
            run_ends = final_step > start_step and (final_step >= cfg.total_steps or stop_reason != "steps")
            if run_ends and logged_at != final_step:
                log_row(final_step)
            if run_ends and cfg.eval_interval > 0 and run_state.last_eval_step != final_step:
                evaluate_now(final_step, stop)
            save_checkpoint("last", with_buffer=True)
            if stop.requested:
                raise TrainingInterrupted(run_state.num_steps,
                                          str(checkpoint_path(writer.run, "last")) if writer is not None else None)
    finally:
        show.close(run_state.num_steps)
        run_state.train_time_s = elapsed()
        run_state.recent_returns = list(rows.recent)  # the next learn() (and save()) go on from them
        if writer is not None:
            writer.close()
        if eval_envs is not None:
            for env in eval_envs:
                with contextlib.suppress(Exception):
                    env.close()

    summary = {
        "steps": run_state.num_steps,
        "episodes": run_state.num_episodes,
        "train_time_s": run_state.train_time_s,
        "wall_s": time.perf_counter() - wall0,
        "last_eval": run_state.last_eval,
        "best_eval": run_state.best_eval,
        "stopped_early": stop_reason != "steps",
        "stop_reason": stop_reason,
        "recent_return_mean": rows.recent_mean(),
        "best_step": run_state.best_step,
        "total_steps": cfg.total_steps,
    }
    if writer is not None:
        writer.write_summary(summary)
    if hooks:
        hooks.call("on_training_end", summary)
    return summary
