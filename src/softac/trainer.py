"""The training loop: collect, learn, evaluate, log, checkpoint, show progress.

Per vector-env step there is one policy call (jitted), one step of each env,
one buffer write (vectorised) and one jitted update that runs all
`gradient_steps`. Metrics stay on the device until a log row needs them.
"""

from __future__ import annotations

import collections
import contextlib
import os
import signal
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from softac import checkpoint as ckpt
from softac.cpus import usable_cpus
from softac.errors import RunFailed, SoftacError, TrainingInterrupted
from softac.evaluation import EVAL_SEED_OFFSET, MAX_PARALLEL, run_episodes
from softac.logs import Progress, RunLogger, write_config, write_summary
from softac.sac import Batch

RECENT_EPISODES = 20  # episodes behind return_mean in progress.csv and the progress bar
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


def _holds_run(run: Path) -> bool:
    return (run / "checkpoints").is_dir() and any((run / "checkpoints").iterdir())


def check_new_run_dir(run: Path) -> None:
    """A new run never writes over another run's checkpoints."""
    if run.exists() and not run.is_dir():
        raise SoftacError(f"run directory {run} exists and is not a directory")
    if _holds_run(run):
        raise SoftacError(f"{run} already holds a run; continue it with --resume {run} or pick another --out")


def check_run_dir_for(agent: Any, run: Path) -> None:
    """An agent writes only into a new directory or the run it is the latest state of: a loaded agent never
    writes over another run, nor rewinds its own from an older (best) checkpoint. Its own run includes one
    killed (kill -9, power loss) before its first periodic checkpoint, continued from the step-0 checkpoint."""
    if agent.run_dir == run.resolve():
        return
    if agent.num_steps > 0 and _holds_run(run):
        raise SoftacError(f"{run} already holds a run that this agent is not the latest state of (it was loaded "
                          f"from {agent.restored_from or 'elsewhere'}); train into a new directory, or load "
                          f"{run / 'checkpoints' / 'last'} to continue that run")
    check_new_run_dir(run)


def train(agent: Any, steps: int, run_dir: str | Path | None = None, target_return: float | None = None,
          progress: bool | None = None) -> dict[str, Any]:
    cfg = agent.config
    if steps < 0:
        raise SoftacError(f"steps must be >= 0, got {steps}")
    buffer, pool = agent.training_parts()
    fns, scaler = agent.fns, agent.scaler
    start_step = agent.num_steps
    end_step = start_step + steps
    n_envs, act_dim = cfg.n_envs, agent.spaces.act_dim
    run = Path(run_dir) if run_dir is not None else None
    if run is not None:
        check_run_dir_for(agent, run)
        try:
            run.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise SoftacError(f"cannot create run directory {run}: {exc.strerror or exc}") from None
        agent.run_dir = run.resolve()
    logger = RunLogger(run, resume_step=start_step) if run is not None else None
    if run is not None:
        from softac.agent import _versions

        write_config(run, cfg.to_dict(), {"versions": _versions(),
                                          "resolved_target_entropy": fns.target_entropy,
                                          "buffer_bytes_per_transition": round(agent.buffer_bytes_per_transition, 1),
                                          "cpus": len(usable_cpus()) or os.cpu_count()})

    ts = agent.trainer_state
    ts.setdefault("best_eval", None)
    ts.setdefault("last_eval", None)
    recent = collections.deque(ts.get("recent_returns", []), maxlen=RECENT_EPISODES)
    last_metrics: dict[str, Any] | None = None
    eval_envs: list | None = None
    show = Progress(start_step, end_step, enabled=progress)
    wall0 = time.perf_counter()
    time0 = agent.train_time_s
    steps_at_last_log, time_at_last_log = start_step, wall0
    logged_at: int | None = None
    next_show = start_step
    stopped_early = False

    def elapsed() -> float:
        return time0 + time.perf_counter() - wall0

    def save_checkpoint(name: str, with_buffer: bool) -> str | None:
        if run is None:
            return None
        if last_metrics is not None:  # never replace a good checkpoint with diverged weights
            _check_finite({k: float(v) for k, v in last_metrics.items()}, agent.num_steps)
        agent.train_time_s = elapsed()
        ts["recent_returns"] = list(recent)
        meta, arrays = agent.checkpoint_parts(include_buffer=with_buffer)
        try:
            return str(ckpt.save(run / "checkpoints" / name, meta, arrays))
        except OSError as exc:
            raise RunFailed(f"could not write checkpoint {run / 'checkpoints' / name}: {exc.strerror or exc}; "
                            "the previous checkpoint is kept") from None

    def evaluate_now(step: int, stop: StopSignal) -> dict[str, Any] | None:
        nonlocal eval_envs
        if eval_envs is None:
            eval_envs = [agent.make_env() for _ in range(min(cfg.eval_episodes, MAX_PARALLEL))]
        stats = run_episodes(lambda obs: agent.predict(obs, deterministic=True), agent.make_env, cfg.eval_episodes,
                             cfg.seed + EVAL_SEED_OFFSET, envs=eval_envs, should_stop=lambda: stop.requested)
        if stop.requested:  # cut short by Ctrl-C/SIGTERM: a partial evaluation is not a result
            return None
        ts["last_eval"] = stats["mean_return"]
        ts["last_eval_step"] = step
        if logger is not None:
            logger.evals.write({"step": step, "mean_return": stats["mean_return"],
                                "std_return": stats["std_return"], "episodes": stats["episodes"]})
            logger.scalars("eval", {"mean_return": stats["mean_return"], "std_return": stats["std_return"]}, step)
        if ts["best_eval"] is None or stats["mean_return"] > ts["best_eval"]:
            ts["best_eval"] = stats["mean_return"]
            ts["best_step"] = step
            save_checkpoint("best", with_buffer=False)
        return stats

    def log_row(step: int) -> None:
        nonlocal steps_at_last_log, time_at_last_log, logged_at
        logged_at = step
        now = time.perf_counter()
        fps = (step - steps_at_last_log) / max(now - time_at_last_log, 1e-9)
        steps_at_last_log, time_at_last_log = step, now
        row: dict[str, Any] = {"step": step, "time_s": round(elapsed(), 3), "fps": round(fps, 1),
                               "episodes": agent.num_episodes,
                               "return_mean": float(np.mean(recent)) if recent else float("nan")}
        if last_metrics is not None:
            values = {k: float(v) for k, v in last_metrics.items()}
            _check_finite(values, step)
            row.update(values)
        if logger is not None:
            logger.progress.write(row)
            logger.scalars("train", row, step)

    try:
        with StopSignal() as stop:
            if run is not None and not (run / "checkpoints" / "last").exists():
                save_checkpoint("last", with_buffer=True)  # from its first moment a run holds a loadable checkpoint
            while agent.num_steps < end_step:
                if stop.requested:
                    where = save_checkpoint("last", with_buffer=True)
                    raise TrainingInterrupted(agent.num_steps, where)
                before = agent.num_steps
                # reset_interval: at the first step past each multiple, so the evaluation and checkpoint at
                # the multiple see the policy before the reset and a resumed run resets where a straight one
                # does; none at or past total_steps (a rule of the config, not of this call): a reset needs
                # the rest of the budget to recover
                if 0 < before < cfg.total_steps and crossed(before - n_envs, before, cfg.reset_interval):
                    agent.state = fns.reset(agent.state, cfg.seed, before // cfg.reset_interval)
                obs = pool.obs
                if agent.obs_norm is not None:  # every observation the policy acts on, warm-up included
                    agent.obs_norm.update(obs)
                if before < cfg.learning_starts:
                    actions = agent.rng.uniform(-1.0, 1.0, (n_envs, act_dim)).astype(np.float32)
                    env_actions = scaler.to_env(actions)
                else:  # NumPy goes straight into the jitted call: jnp.asarray would cost more than the env step
                    actions, env_actions, agent.act_key = fns.act(agent.state.actor, agent.normalize_obs(obs),
                                                                  agent.act_key)
                    actions, env_actions = np.asarray(actions), np.asarray(env_actions)
                    if not np.all(np.isfinite(actions)):
                        raise RunFailed(f"training diverged at step {before}: the policy produced non-finite "
                                        "actions; the last good checkpoint is kept")
                result = pool.step(env_actions, before)
                buffer.add(obs, actions, result.rewards, result.next_obs, result.terminated,
                           result.terminated | result.truncated)
                agent.num_steps = after = before + n_envs
                for _, episode_return, length in result.finished:
                    agent.num_episodes += 1
                    recent.append(episode_return)
                    if logger is not None:
                        logger.episodes.write({"step": after, "return": round(episode_return, 6), "length": length})
                        logger.scalars("rollout", {"episode_return": episode_return, "episode_length": length}, after)

                if after >= cfg.learning_starts and cfg.gradient_steps > 0 and len(buffer) > 0:
                    batch = buffer.sample(agent.rng, cfg.batch_size, cfg.gradient_steps)
                    # raw observations in the buffer, normalised (obs_norm) with the current statistics
                    batch["obs"] = agent.normalize_obs(batch["obs"])
                    batch["next_obs"] = agent.normalize_obs(batch["next_obs"])
                    agent.state, last_metrics = fns.update(agent.state, Batch(**batch))

                if crossed(before, after, cfg.log_interval):
                    log_row(after)
                if crossed(before, after, cfg.eval_interval):
                    stats = evaluate_now(after, stop)
                    if stats is not None and target_return is not None and stats["mean_return"] >= target_return:
                        stopped_early = True
                if crossed(before, after, cfg.checkpoint_interval) and not stopped_early:  # (saved below when stopping)
                    save_checkpoint("last", with_buffer=True)
                if after >= next_show or stopped_early:  # the bar redraws at most every SHOW_EVERY steps
                    next_show = after + SHOW_EVERY
                    show.update(after, ret=float(np.mean(recent)) if recent else None, eval=ts["last_eval"])
                if stopped_early:
                    break

            final_step = agent.num_steps
            if final_step > start_step and logged_at != final_step:
                log_row(final_step)
            if final_step > start_step and cfg.eval_interval > 0 and ts.get("last_eval_step") != final_step:
                evaluate_now(final_step, stop)
            save_checkpoint("last", with_buffer=True)
            if stop.requested:
                raise TrainingInterrupted(agent.num_steps, str(run / "checkpoints" / "last") if run else None)
    finally:
        show.close(agent.num_steps)
        agent.train_time_s = elapsed()
        if logger is not None:
            logger.close()
        if eval_envs is not None:
            for env in eval_envs:
                with contextlib.suppress(Exception):
                    env.close()

    summary = {
        "steps": agent.num_steps,
        "episodes": agent.num_episodes,
        "train_time_s": agent.train_time_s,
        "wall_s": time.perf_counter() - wall0,
        "last_eval": ts["last_eval"],
        "best_eval": ts["best_eval"],
        "stopped_early": stopped_early,
        "recent_return_mean": float(np.mean(recent)) if recent else None,
        "best_step": ts.get("best_step"),
        "total_steps": cfg.total_steps,
    }
    if run is not None:
        write_summary(run, summary)
    return summary
