"""`SAC`: the Python API, the user-facing face over the parts it builds.

    agent = SAC(SACConfig.preset("InvertedPendulum-v5"))
    agent.learn(20_000)
    agent.save("pendulum"); agent = SAC.load("pendulum")
    action = agent.predict(obs, deterministic=True)

An agent is a learner (networks, optimisers, obs statistics: what it knows; softac.learner.learner), a collector
(training envs and replay buffer; softac.replay.collector) and a run state (counters, random streams,
evaluations; softac.run.run_state). `learn()` hands the three to a training loop (softac.run.loop); `save()`
and `load()` go through softac.run.checkpoint_contents. No module below this one imports it.
"""

from __future__ import annotations

import contextlib
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from softac.run import checkpoint as ckpt
from softac.run import checkpoint_contents as snapshot
from softac.replay.collector import Collector
from softac.replay.device_collector import DeviceCollector
from softac.config.sac_config import SACConfig
from softac.base.device import select_device
from softac.envs.make import EnvSource, check_spaces, copy_env, env_name, training_env_source
from softac.replay.exploration import exploration_noise
from softac.replay.her_buffer import her_setup
from softac.learner.learner import Learner
from softac.run.run_state import RunState

if TYPE_CHECKING:
    import gymnasium as gym


def device_collector(config: SACConfig, env_source: EnvSource, spaces: Any,
                     offline_loader: Any = None) -> DeviceCollector:
    from softac.envs.playground import device_env

    env = device_env(config.env_id)
    return DeviceCollector(config, env_source, spaces, env.env, env.episode_length, env.action_repeat, offline_loader)


class SAC:
    """A Soft Actor-Critic agent for one env (an id or a gym.Env instance)."""

    def __init__(self, config: SACConfig | None = None, env: EnvSource | None = None,
                 offline_data: str | Path | None = None):
        """`offline_data`: a dataset to learn from beside the env (config key offline_data, which it replaces): a
        Minari dataset id or directory, a softac run directory, or a `softac dataset` output (issue 68)."""
        if config is None:
            config = SACConfig.for_env(env if isinstance(env, str) else None)
        if offline_data is not None:
            config = config.replace(offline_data=str(offline_data))
        if env is None:
            env = config.env_id
        elif isinstance(env, str):
            config = config.replace(env_id=env)
        else:
            config = config.replace(env_id=env_name(env))
        self.env_source: EnvSource = env
        self.device = select_device(config.device)

        self.env_source, probe = training_env_source(env, config)
        self.spaces = check_spaces(probe)
        # checked now: a goal env's compute_reward must take batches (an env observed through images has no HER)
        her = her_setup(config, probe, self.spaces) if self.spaces.image_shape is None else None
        if isinstance(env, str) and her is None:
            probe.close()

        self.learner = Learner(config, self.spaces)  # what the agent knows
        # its training envs and replay buffer: on the host, or N envs on the device (MuJoCo Playground's; issue 67)
        offline = self._offline_loader(config)
        self.collector = (device_collector(config, self.env_source, self.spaces, offline) if config.collects_on_device
                          else Collector(config, self.env_source, self.spaces, her, offline))
        # where its training stands (counters, RNGs, exploration noise, evaluations, its run)
        self.run_state = RunState.new(config.seed, exploration_noise(config, self.spaces.act_dim))

    def _offline_loader(self, config: SACConfig) -> Any:
        """offline_data's reader (issue 68), called when training first needs the dataset."""
        if not config.offline_data:
            return None
        from softac.run.offline_sources import load_offline_data

        return partial(load_offline_data, config.offline_data, config.env_id, self.spaces,
                       self.learner.scaler.to_normalised)

    @property
    def config(self) -> SACConfig:
        """The agent's settings: the learner's config (a frozen SACConfig; training past total_steps gives the
        learner one with the raised budget)."""
        return self.learner.config

    @property
    def num_steps(self) -> int:
        """Environment steps trained so far (SB3's num_timesteps)."""
        return self.run_state.num_steps

    @property
    def num_episodes(self) -> int:
        """Training episodes finished so far."""
        return self.run_state.num_episodes

    @property
    def buffer_bytes_per_transition(self) -> float:
        return self.collector.bytes_per_transition

    def __repr__(self) -> str:
        run, last = self.run_state.run_dir, self.run_state.last_eval
        return (f"SAC(env={self.config.env_id!r}, steps={self.num_steps}, episodes={self.num_episodes}, "
                f"last_eval={None if last is None else round(last, 2)}, run_dir={str(run) if run else None!r})")

    def show(self, plots: bool = True, evaluations: bool = True, video: bool | None = None) -> list[Path]:
        """In Jupyter, show the run this agent trained into: learning curve, metric grid, evaluations and a
        video (softac.outputs.notebook.show); elsewhere, write them and print where."""
        from softac.outputs.notebook import show

        return show(self, plots=plots, evaluations=evaluations, video=video)

    def make_env(self, render_mode: str | None = None, **kwargs: Any) -> gym.Env:
        """A fresh copy of the agent's env (what evaluate() and videos run on)."""
        return copy_env(self.env_source, render_mode, **kwargs)

    def predict(self, obs: Any, deterministic: bool = True, policy: str = "deployed") -> np.ndarray:
        """Env-scaled action(s) for one observation or a batch of them. `policy`: "deployed" (the weight
        average with policy_average_tau, else the actor), "actor" (the actor that explores) or "average"."""
        if deterministic:
            return self.learner.predict(obs, policy)
        actions, self.run_state.predict_key = self.learner.sample(obs, self.run_state.predict_key, policy)
        return actions

    def learn(self, steps: int, run_dir: str | Path | None = None, target_return: float | None = None,
              progress: bool | None = None, callbacks: list | None = None,
              loggers: list | None = None, target_success: float | None = None) -> dict[str, Any]:
        """Train for `steps` more environment steps; returns a summary dict (its stop_reason: steps,
        target_return, target_success, or "callback: ..."). `callbacks`: softac.run.callbacks.Callback objects; `loggers`: extra
        softac.run.loggers.Logger objects that get every metrics record (softac does not close them). Training past
        config.total_steps raises it to where this call ends, as `softac train --resume --steps` does."""
        from softac.run.run_dir import run_lock
        from softac.run.loop import TrainingLoop

        # one writer per run: a second process training into run_dir is refused (RunLocked, exit 2)
        with run_lock(run_dir) if run_dir is not None else contextlib.nullcontext():
            try:
                loop = TrainingLoop(self.learner, self.collector, self.run_state, steps, run_dir=run_dir,
                                    target_return=target_return, progress=progress, callbacks=callbacks,
                                    loggers=loggers, agent=self, target_success=target_success)
                return loop.run()
            finally:
                self.collector.close_workers()  # no worker process outlives the call, whatever ended it

    def write_dataset(self, out: str | Path, episodes: int | None = None, policy: str = "deployed", noise: float = 0.0,
                      seed: int = 0, dataset_id: str | None = None, steps: int | None = None) -> Path:
        """A Minari dataset at `out` (as `softac dataset`, issue 68): the agent's replay buffer as each env's
        episodes, or `episodes` fresh episodes of its deterministic `policy` with Gaussian noise of std `noise` in
        [-1, 1] units (or episodes until `steps` transitions, the last cut there); `dataset_id` (NAMESPACE/NAME-vN)
        by default from `out`. Returns `out`; train from it with
        SAC(config, offline_data=out)."""
        from softac.outputs.dataset import write_agent_dataset

        return write_agent_dataset(self, f"a softac agent on {self.config.env_id}", out, dataset_id, episodes, policy,
                                   noise, seed, steps).path

    def save(self, path: str | Path, include_buffer: bool = False) -> Path:
        """Save the agent (networks, optimisers, alpha, RNGs; the buffer and envs too if asked)."""
        return ckpt.save(path, *snapshot.checkpoint_parts(self.learner, self.run_state, self.collector, include_buffer))

    @classmethod
    def load(cls, path: str | Path, env: EnvSource | None = None, which: str | None = None,
             device: str | None = None, env_workers: int | None = None, allow_new_bounds: bool = False,
             loggers: str | None = None) -> "SAC":
        """Load a checkpoint directory or a run (its best checkpoint, else last). `device`, `env_workers`
        and `loggers` replace the saved config's: none changes what the agent computes. An env whose action
        bounds differ from the saved ones is refused unless `allow_new_bounds` (the policy's actions, in
        [-1, 1] inside the networks, are then scaled to the new bounds)."""
        directory = ckpt.resolve(path, which)
        meta, arrays = ckpt.load(directory)
        config = snapshot.saved_config(meta, directory, device=device, env_workers=env_workers, loggers=loggers)
        agent = cls(config, env)
        snapshot.restore(meta, arrays, agent.learner, agent.run_state, agent.collector, directory, allow_new_bounds)
        return agent
