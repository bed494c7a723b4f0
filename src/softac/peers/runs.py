"""Three ways to run a peer (a throughput probe, a run to a target return, a whole run that writes a softac-style
run directory) and the entry point of a peer's process (`python -m softac.peers`)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

from softac.peers.checkpoints import load_peer_checkpoint, save_peer_checkpoint
from softac.peers.models import (HER_SETTINGS, PEERS, THROUGHPUT_LEARNING_STARTS, peer_model, peer_version,
                                 sweep_config)


def peer_throughput(framework: str, env_id: str, warmup: int, steps: int, seed: int) -> dict[str, Any]:
    from stable_baselines3.common.callbacks import BaseCallback

    class Clock(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.t_start = None

        def _on_step(self) -> bool:
            if self.num_timesteps == warmup:
                self.t_start = time.perf_counter()
            return True

    clock = Clock()
    # every framework learns from step 100 in a throughput probe, so the timed steps all learn
    model = peer_model(framework, env_id, seed, learning_starts=THROUGHPUT_LEARNING_STARTS)
    model.learn(warmup + steps, callback=clock)
    elapsed = time.perf_counter() - clock.t_start
    return {"steps_per_s": steps / elapsed}


def peer_solve(framework: str, env_id: str, seed: int, target: float, max_steps: int) -> dict[str, Any]:
    import gymnasium as gym
    from stable_baselines3.common.callbacks import EvalCallback, StopTrainingOnRewardThreshold

    class TimedEval(EvalCallback):
        eval_s = 0.0

        def _on_step(self) -> bool:
            t0 = time.perf_counter()
            result = super()._on_step()
            self.eval_s += time.perf_counter() - t0
            return result

    stop = StopTrainingOnRewardThreshold(reward_threshold=target, verbose=0)
    evaluator = TimedEval(gym.make(env_id), eval_freq=1000, n_eval_episodes=10, deterministic=True,
                          callback_on_new_best=stop, verbose=0)
    model = peer_model(framework, env_id, seed)
    t0 = time.perf_counter()
    model.learn(max_steps, callback=evaluator)
    total = time.perf_counter() - t0
    return {"steps": int(model.num_timesteps), "solved": bool(evaluator.best_mean_reward >= target),
            "train_s": total - evaluator.eval_s, "best_eval": float(evaluator.best_mean_reward)}


def peer_run(framework: str, env_id: str, seed: int, steps: int, out: Path, eval_interval: int,
             eval_episodes: int, log_interval: int, checkpoint_interval: int = 0, preset: str | None = None,
             overrides: list[str] | None = None, action_repeat: int = 1,
             target_return: float | None = None, target_success: float | None = None) -> dict[str, Any]:
    """Train a peer and write a softac-style run directory (config.yaml, progress.csv, episodes.csv,
    eval.csv, summary.json), evaluated exactly like softac evaluates: deterministic actions, episode i of
    every evaluation seeded `seed + EVAL_SEED_OFFSET + i`; progress.csv's columns mean what softac's mean
    (softac.run.csv_logs.TrainRows). The run directory is locked as softac's are (one writer). Every
    `checkpoint_interval` steps, and when Ctrl-C or SIGTERM stops it (TrainingInterrupted, exit 130), the run
    saves checkpoints/last; the same call on the same directory continues from there, so a peer's run that
    takes longer than one sitting (SBX's CrossQ at its defaults: hours on one CPU) still finishes. A peer
    whose settings are a sweep's runs at the config `preset` and `overrides` make (sweep_config). With
    `action_repeat` (or a sweep peer's action_repeat setting) its training and evaluation envs repeat each
    action, as softac's do; steps count the agent's actions, as softac's. With `target_return` the run stops
    after the first evaluation whose mean reaches it (softac train's --target-return); with `target_success`,
    a goal env's, after the first whose success rate reaches it (--target-success)."""
    from softac.errors import SoftacError, TrainingInterrupted
    from softac.run.run_dir import run_lock

    sweep = {"preset": preset, "overrides": list(overrides or [])}
    if PEERS[framework].package == "brax":  # Brax's trainer runs its own loop (softac.peers.brax_sac)
        from softac.peers.brax_sac import BraxSACRun

        config = sweep_config(env_id, **sweep)
        if target_success is not None:
            raise SoftacError("brax-sac trains Playground's envs, which report no success: no --target-success")
        settled_action_repeat(action_repeat, config)  # Brax repeats the setting's (BraxSACRun)
        with run_lock(out):
            return BraxSACRun(env_id, seed, steps, out, eval_interval, eval_episodes, config, sweep,
                              target_return).run()
    with run_lock(out):
        try:
            return PeerRun(framework, env_id, seed, steps, out, eval_interval, eval_episodes, log_interval,
                           checkpoint_interval, sweep, action_repeat, target_return, target_success).run()
        except TrainingInterrupted as exc:
            # said before the lock goes: a stopped sweep waits for the lock, then its user reads the trial's log
            print(f"python -m softac.peers: {exc}; run the same command again to continue", file=sys.stderr,
                  flush=True)
            raise


def settled_action_repeat(action_repeat: int, config: Any = None) -> int:
    """The action repeat a peer's run takes: --action-repeat, or a sweep peer's setting (`config`'s), which
    must agree when both are given (SoftacError otherwise, as for a value below 1)."""
    from softac.errors import SoftacError

    if action_repeat < 1:
        raise SoftacError(f"--action-repeat must be >= 1, not {action_repeat}")
    if config is None or config.action_repeat == 1:
        return action_repeat
    if action_repeat not in (1, config.action_repeat):
        raise SoftacError(f"--action-repeat {action_repeat} and the setting action_repeat={config.action_repeat} "
                          "differ: give one")
    return config.action_repeat


def _hyperparameters(model: Any) -> dict[str, Any]:
    """What config.yaml records of a peer's model: its settings as it holds them."""
    hyper = {k: getattr(model, k) for k in ("learning_rate", "qf_learning_rate", "buffer_size", "batch_size",
                                            "learning_starts", "tau", "gamma", "train_freq", "gradient_steps",
                                            "policy_delay", "ent_coef", "target_entropy", "use_sde",
                                            "sde_sample_freq") if hasattr(model, k)}
    if "train_freq" in hyper:
        hyper["train_freq"] = f"{hyper['train_freq'].frequency} {hyper['train_freq'].unit.value}"
    return {**{k: (v if isinstance(v, (int, float, str)) else str(v)) for k, v in hyper.items()},
            "policy_kwargs": str(model.policy_kwargs)}


class PeerRun:
    """One peer run into a run directory: a fresh model, or the one its last checkpoint holds with the
    run's bookkeeping (step, episodes, evaluations so far, seconds so far, recent returns). A resumed run
    starts a new training episode where the checkpoint was written (the env's state mid-episode is not
    saved) and draws other random numbers than an unbroken run would: it is the same experiment, not the
    same numbers, unlike softac's exact resume."""

    def __init__(self, framework: str, env_id: str, seed: int, steps: int, out: Path, eval_interval: int,
                 eval_episodes: int, log_interval: int, checkpoint_interval: int,
                 sweep: dict[str, Any] | None = None, action_repeat: int = 1, target_return: float | None = None,
                 target_success: float | None = None):
        from softac.run import checkpoint as ckpt
        from softac.run.run_dir import checkpoint_path

        self.framework, self.env_id, self.seed, self.steps, self.out = framework, env_id, seed, steps, out
        self.eval_interval, self.eval_episodes, self.log_interval = eval_interval, eval_episodes, log_interval
        self.checkpoint_interval, self.target_return = checkpoint_interval, target_return
        self.target_success = target_success
        self.reached: str | None = None  # target_return or target_success once an evaluation reached it
        self.sweep = sweep if PEERS[framework].settings == "sweep" else None  # the softac settings it runs at
        self.checkpoint = checkpoint_path(out, "last")
        config = sweep_config(env_id, **self.sweep) if self.sweep is not None else None
        self.action_repeat = action_repeat = settled_action_repeat(action_repeat, config)
        self.identity = {"framework": framework, "env_id": env_id, "seed": seed, "total_steps": steps}
        if action_repeat != 1:  # only then: the checkpoints of runs without it keep their identity
            self.identity["action_repeat"] = action_repeat
        self.resumed = ckpt.is_checkpoint(self.checkpoint)
        if self.resumed:
            self.model, meta = load_peer_checkpoint(framework, env_id, self.checkpoint, self.identity)
            self.record = meta["record"]
        else:
            self.model = peer_model(framework, env_id, seed, config, action_repeat)
            self.record = {"step": 0, "episodes": 0, "best": None, "best_step": None, "last": None,
                           "elapsed_s": 0.0, "recent_returns": []}

    def run(self) -> dict[str, Any]:
        from stable_baselines3.common.callbacks import BaseCallback

        from softac.errors import TrainingInterrupted
        from softac.run.evaluation import MAX_PARALLEL
        from softac.envs.goals import dict_layout, dict_observation_space
        from softac.run.loggers import CsvLogger
        from softac.run.csv_logs import TrainRows
        from softac.run.run_dir import write_config, write_summary
        from softac.base.stop_signal import StopSignal

        peer, start = PEERS[self.framework], self.record["step"]
        config = {**self.identity, "algorithm": peer.algorithm, "settings": peer.settings, "about": peer.about,
                  "eval_interval": self.eval_interval, "eval_episodes": self.eval_episodes,
                  **_hyperparameters(self.model)}
        if peer.her:
            config["her"] = {"replay_buffer_class": "HerReplayBuffer", **HER_SETTINGS}
        if self.sweep is not None:
            config["softac_settings"] = self.sweep
        write_config(self.out, config, {"versions": {self.framework: peer_version(self.framework)}},
                     start_step=start, continuing=self.resumed)
        # the same files as a softac run (plots, reports and sweep tables read both); on resume, rows past the
        # checkpoint's step are dropped
        self.logs = CsvLogger(self.out, start if self.resumed else None)
        # evaluated on softac's envs (a dict observation flattened, as run_episodes takes it), the flat
        # observations given back to the peer's policy as the dict it was trained on
        self.eval_envs = [self.make_env() for _ in range(min(self.eval_episodes, MAX_PARALLEL))]
        space = dict_observation_space(self.eval_envs[0])
        self.layout = dict_layout(space) if space is not None else None
        self.t0 = time.perf_counter() - self.record["elapsed_s"]  # time_s counts every segment's seconds
        self.rows = TrainRows(start, self.record["recent_returns"], self.record.get("recent_successes", []))
        run = self

        class Hooks(BaseCallback):
            def _on_step(self) -> bool:
                return run.on_step(self.num_timesteps, self.locals.get("infos", []))

        try:
            with StopSignal() as self.stop:
                self.model.learn(self.steps - start, callback=Hooks(), reset_num_timesteps=not self.resumed)
            if self.stop.requested:
                raise TrainingInterrupted(int(self.model.num_timesteps), str(self.checkpoint))
            if self.eval_interval > 0 and self.steps % self.eval_interval != 0 and not self.reached:
                self.evaluate(self.steps)
        finally:
            self.logs.close()
            for env in self.eval_envs:
                env.close()
        elapsed = time.perf_counter() - self.t0
        summary = {"steps": int(self.model.num_timesteps), "episodes": self.record["episodes"],
                   "train_time_s": elapsed, "wall_s": elapsed, "last_eval": self.record["last"],
                   "best_eval": self.record["best"], "stopped_early": self.reached is not None,
                   "stop_reason": self.reached or "steps", "best_step": self.record["best_step"],
                   "total_steps": self.steps, "framework": self.framework}
        if self.layout is not None and "last_success" in self.record:
            summary.update(last_success=self.record["last_success"], recent_success_rate=self.rows.success_rate())
        write_summary(self.out, summary)
        return summary

    def on_step(self, step: int, infos: list[dict[str, Any]]) -> bool:
        """Episodes, log rows, evaluations and checkpoints due at this step; False stops training (a signal,
        after the checkpoint is written)."""
        from softac.envs.make import success_of

        for info in infos:
            if "episode" in info:
                self.record["episodes"] += 1
                success = success_of(info)  # the env's info at the episode's last step (SB3's Monitor keeps it)
                self.rows.episode_finished(float(info["episode"]["r"]), success)
                values = {"return": float(info["episode"]["r"]), "length": int(info["episode"]["l"])}
                if success is not None:
                    values["success"] = success
                self.logs.log("rollout", values, step)
        if step % self.log_interval == 0:
            row = self.rows.row(step, time.perf_counter() - self.t0, self.record["episodes"])
            self.logs.log("train", {k: v for k, v in row.items() if k != "step"}, step)
        if self.eval_interval > 0 and step % self.eval_interval == 0:
            from softac.run.stopping import target_reached

            self.evaluate(step)
            self.reached = target_reached(self.record["last"], self.record.get("last_success"), self.target_return,
                                          self.target_success)
        if self.stop.requested or (self.checkpoint_interval > 0 and step % self.checkpoint_interval == 0):
            self.save(step)
        return not (self.stop.requested or self.reached)

    def make_env(self) -> Any:
        """An evaluation env: softac's, each action repeated as in training."""
        from softac.envs.make import make_env, with_action_repeat

        return make_env(with_action_repeat(self.env_id, self.action_repeat))

    def policy(self, obs: Any) -> Any:
        """The peer's deterministic actions for a batch of flat observations (as a dict, for a dict env), normalised
        by the training statistics where it has them (VecNormalize), as softac's predict() normalises."""
        normalizer = self.model.get_vec_normalize_env()
        if normalizer is not None:
            obs = normalizer.normalize_obs(obs)
        if self.layout is not None:
            obs = {key: obs[:, self.layout.slices[key]] for key in self.layout.keys}
        return self.model.predict(obs, deterministic=True)[0]

    def evaluate(self, step: int) -> None:
        from softac.run.evaluation import EVAL_SEED_OFFSET, run_episodes

        stats = run_episodes(self.policy, self.make_env, self.eval_episodes,
                             self.seed + EVAL_SEED_OFFSET, envs=self.eval_envs)
        values = {"mean_return": stats["mean_return"], "std_return": stats["std_return"], "episodes": stats["episodes"]}
        if stats["success_rate"] is not None:
            values["success_rate"] = self.record["last_success"] = stats["success_rate"]
        self.logs.log("eval", values, step)
        self.record["last"] = stats["mean_return"]
        if self.record["best"] is None or stats["mean_return"] > self.record["best"]:
            self.record["best"], self.record["best_step"] = stats["mean_return"], step

    def save(self, step: int) -> None:
        from softac.errors import RunFailed

        self.record.update(step=step, elapsed_s=time.perf_counter() - self.t0, recent_returns=list(self.rows.recent),
                           recent_successes=list(self.rows.successes))
        try:
            save_peer_checkpoint(self.model, self.checkpoint, {"peer": self.identity, "record": self.record,
                                                               "sweep": self.sweep})
        except OSError as exc:
            raise RunFailed(f"could not write checkpoint {self.checkpoint}: {exc.strerror or exc}; "
                            "the previous checkpoint is kept") from None


# ---- the entry point of a peer's process ------------------------------------------------------------

def arguments() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m softac.peers", description="run a peer; prints one JSON line")
    p.add_argument("kind", choices=["throughput", "solve", "run"])
    p.add_argument("framework", choices=list(PEERS))
    p.add_argument("--env", default="InvertedPendulum-v5")
    p.add_argument("--warmup", type=int, default=500, help="throughput: untimed steps first")
    p.add_argument("--steps", type=int, default=2000, help="throughput: timed steps; run: steps to train")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--target", type=float, default=1000.0, help="solve: the evaluation return to reach")
    p.add_argument("--max-steps", type=int, default=50_000, help="solve: the step budget")
    p.add_argument("--out", help="run: the run directory to write")
    p.add_argument("--eval-interval", type=int, default=1000)
    p.add_argument("--eval-episodes", type=int, default=10)
    p.add_argument("--log-interval", type=int, default=1000)
    p.add_argument("--checkpoint-interval", type=int, default=0,
                   help="run: steps between checkpoints (0: only when stopped by a signal); run again to continue")
    p.add_argument("--action-repeat", type=int, default=1,
                   help="run: each action applied this many times, the rewards summed (softac's action_repeat)")
    p.add_argument("--preset", help="a peer that runs at a sweep's settings: softac's preset (default: the env's)")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="... and its overrides")
    p.add_argument("--target-return", type=float, help="run: stop once an evaluation's mean return reaches this")
    p.add_argument("--target-success", type=float, help="run: stop once an evaluation's success rate reaches this")
    return p


def main(argv: list[str]) -> None:
    from softac.base.cpus import adopt_trial_settings
    from softac.errors import RunFailed, SoftacError, TrainingInterrupted

    adopt_trial_settings()  # a sweep trial's process: its CPUs and parent, before the peer's library starts

    parser = arguments()
    a = parser.parse_args(argv)
    try:
        if a.kind == "run":
            if not a.out:
                parser.error("run needs --out")
            out = peer_run(a.framework, a.env, a.seed, a.steps, Path(a.out), a.eval_interval, a.eval_episodes,
                           a.log_interval, a.checkpoint_interval, a.preset, a.set, a.action_repeat, a.target_return,
                           a.target_success)
        elif a.kind == "throughput":
            out = peer_throughput(a.framework, a.env, a.warmup, a.steps, a.seed)
        else:
            out = peer_solve(a.framework, a.env, a.seed, a.target, a.max_steps)
    except TrainingInterrupted:  # peer_run said where it stopped
        sys.exit(130)
    except SoftacError as exc:
        print(f"python -m softac.peers: {exc}", file=sys.stderr)
        sys.exit(3 if isinstance(exc, RunFailed) else 2)
    print(json.dumps(out), flush=True)
