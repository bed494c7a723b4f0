"""`Collector`: the training envs and the replay buffer they fill.

It steps the envs (in this process, or in env worker processes with env_workers > 0) with the actions the
loop chose, stores each transition, and samples batches for the learner (with `offline_data`, part of each batch
from the dataset: softac.replay.offline). The parts are made on first use: an agent that only predicts never starts
an env pool, allocates a buffer or reads its dataset. Worker processes end with
each learn(); their envs' state is kept ("parked") so the next learn() carries on exactly.
"""

from __future__ import annotations

import warnings
from functools import partial
from typing import TYPE_CHECKING, Any, Callable

import gymnasium as gym
import numpy as np

from softac.replay.buffer import ObsOnceReplayBuffer, ReplayBuffer
from softac.config.sac_config import SACConfig
from softac.envs.make import EnvFailed, EnvPool, EnvSource, SpaceInfo, StepResult, copy_env, env_name
from softac.replay.her_buffer import HerReplayBuffer, HerSetup
from softac.replay.image_buffer import FrameReplayBuffer
from softac.replay.offline import OfflineData, OfflineDataError, OfflineSource, mixed_batches, offline_rows

if TYPE_CHECKING:
    from softac.envs.workers import WorkerEnvPool

BUFFER_PREFIX, ENVS_PREFIX = "buffer/", "envs/"  # checkpoint array names


def _with_prefix(arrays: dict[str, np.ndarray], prefix: str) -> dict[str, np.ndarray]:
    return {k[len(prefix):]: v for k, v in arrays.items() if k.startswith(prefix)}


def buffer_state(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The replay buffer's state_dict in a checkpoint's arrays (empty when the checkpoint holds no buffer)."""
    return _with_prefix(arrays, BUFFER_PREFIX)


Buffer = ReplayBuffer | ObsOnceReplayBuffer | HerReplayBuffer | FrameReplayBuffer


def replay_buffer_for(config: SACConfig, spaces: SpaceInfo, her: HerSetup | None) -> tuple[Callable[[], Buffer], float]:
    """The one switch over buffer kinds: the replay buffer a config, its spaces and HER ask for (a function that
    makes it, called on first use) and its bytes per transition (stated before a run starts)."""
    size, n, obs_dim, act_dim = config.buffer_size, config.n_envs, spaces.obs_dim, spaces.act_dim
    returns = {"n_step": config.n_step, "gamma": config.gamma}
    if her is not None:
        return (partial(HerReplayBuffer, size, her.layout, act_dim, n, her.reward_fn, her.strategy, her.k,
                        gamma=config.gamma), HerReplayBuffer.bytes_per_transition(obs_dim, act_dim))
    if spaces.image_shape is not None:  # each frame of the stacks (pixels.FrameStack) once
        return (partial(FrameReplayBuffer, size, spaces.image_shape, act_dim, n, **returns),
                FrameReplayBuffer.bytes_per_transition(spaces.image_shape, act_dim, size, n))
    if config.buffer_obs_once:
        return (partial(ObsOnceReplayBuffer, size, obs_dim, act_dim, n, **returns),
                ObsOnceReplayBuffer.bytes_per_transition(obs_dim, act_dim, size, n))
    return (partial(ReplayBuffer, size, obs_dim, act_dim, n_envs=n, **returns),
            ReplayBuffer.bytes_per_transition(obs_dim, act_dim))


class Collector:
    """The env pool and the replay buffer of one training run."""

    def __init__(self, config: SACConfig, env_source: EnvSource, spaces: SpaceInfo, her: HerSetup | None = None,
                 offline_loader: Callable[[], OfflineData] | None = None):
        self.config, self.env_source, self.spaces, self.her = config, env_source, spaces, her
        # offline_data (issue 68): read on first use; a resumed run's checkpoint names the checksum it must still have
        self.offline_source = OfflineSource(offline_loader)
        self.buffer: Buffer | None = None
        self.pool: EnvPool | WorkerEnvPool | None = None
        self.started = False  # the envs were reset (or restored) once; they go on from where they are
        # the envs' state (the pool's get_state()) while no pool holds it: loaded from a checkpoint, or kept
        # from env worker processes that a finished learn() closed; the next pool starts from it
        self.parked_envs: tuple[dict, dict[str, np.ndarray]] | None = None

    @property
    def bytes_per_transition(self) -> float:
        return replay_buffer_for(self.config, self.spaces, self.her)[1]

    @property
    def offline(self) -> OfflineData | None:
        """The run's offline dataset once read (None before, or without offline_data)."""
        return self.offline_source.data

    def _make_buffer(self) -> Buffer:
        return replay_buffer_for(self.config, self.spaces, self.her)[0]()

    def _envs_reset(self) -> None:
        """The envs start fresh episodes that the buffer did not see end (HER's episode bookkeeping)."""
        if isinstance(self.buffer, HerReplayBuffer):
            self.buffer.start_new_episodes()

    def make_env(self, render_mode: str | None = None, **kwargs: Any) -> gym.Env:
        """A fresh copy of the training env (evaluation and videos run on copies)."""
        return copy_env(self.env_source, render_mode, **kwargs)

    # ---- the parts, made on first use ----------------------------------------------------------------

    def start(self, num_steps: int) -> None:
        """Make the buffer and the env pool if they are not there; envs restored or parked go on from their
        state, new ones are reset with seeds that depend on `num_steps`."""
        if self.buffer is None:
            self.buffer = self._make_buffer()
            if self.config.offline_mode == "prefill" and self.load_offline() is not None and len(self.buffer) == 0:
                self._prefill(self.offline)
        self.load_offline()
        if self.pool is None:
            self.pool = self._make_pool()
            if self.parked_envs is not None:
                self._unpark(*self.parked_envs, num_steps)
        if not self.started:
            self.pool.reset(num_steps)
            self._envs_reset()
            self.started = True

    def _make_pool(self) -> EnvPool | WorkerEnvPool:
        source, cfg = self.env_source, self.config
        if cfg.env_workers > 0:
            from softac.envs.workers import WorkerEnvPool

            return WorkerEnvPool(source, cfg.n_envs, cfg.seed, env_name(source), cfg.env_workers)

        def make(i: int):
            return source if (i == 0 and isinstance(source, gym.Env)) else copy_env(source)

        return EnvPool(make, cfg.n_envs, cfg.seed, env_name(source))

    def _unpark(self, meta: dict, arrays: dict[str, np.ndarray], num_steps: int) -> None:
        self.parked_envs = None
        if not self.pool.set_state(meta, arrays, num_steps):
            self._envs_reset()
            warnings.warn(f"env {self.pool.name} cannot save its state, so resumed training starts fresh episodes "
                          "(give its class save_state()/load_state() for an exact resume)", stacklevel=4)

    def close_workers(self) -> None:
        """Stop the env worker processes, if any, keeping their envs' state for the next start(), which
        carries on exactly; envs lost with a failed worker start fresh episodes there."""
        if self.pool is None or isinstance(self.pool, EnvPool):
            return
        pool, self.pool = self.pool, None
        try:
            self.parked_envs = pool.get_state() if pool.usable else None
        except EnvFailed:
            self.parked_envs = None
        finally:
            pool.close()
        if self.parked_envs is None:
            self.started = False

    # ---- collecting and sampling ---------------------------------------------------------------------

    @property
    def obs(self) -> np.ndarray:
        """The envs' current observations (one row per env)."""
        return self.pool.obs

    def step(self, obs: np.ndarray, actions: np.ndarray, env_actions: np.ndarray, step: int) -> StepResult:
        """Step every env with `env_actions` and store the transitions from `obs` (actions in [-1, 1])."""
        result = self.pool.step(env_actions, step)
        self.buffer.add(obs, actions, result.rewards, result.next_obs, result.terminated,
                        result.terminated | result.truncated)
        return result

    def can_sample(self) -> bool:
        return self.buffer is not None and len(self.buffer) > 0

    def sample(self, rng: np.random.Generator, batch_size: int, batches: int) -> dict[str, np.ndarray]:
        """`batches` batches of `batch_size` transitions, stacked (raw observations); with offline_data mixed in,
        offline_fraction of each batch's rows from the dataset (RLPD's symmetric sampling), drawn from `rng` too."""
        if self.offline is None or not self.config.mixes_offline_data:
            return self.buffer.sample(rng, batch_size, batches)
        k = offline_rows(batch_size, self.config.offline_fraction)
        online = self.buffer.sample(rng, batch_size - k, batches)
        her = self.her if isinstance(self.buffer, HerReplayBuffer) else None  # the dataset's goals relabelled too
        return mixed_batches(online, self.offline.sample(rng, k, batches, her))

    # ---- offline data (issue 68) ---------------------------------------------------------------------

    def load_offline(self) -> OfflineData | None:
        """The run's offline dataset, read once (None without offline_data); a resumed run's must be the one it
        started with."""
        return self.offline_source.load()

    def _prefill(self, data: OfflineData) -> None:
        """offline_mode prefill: the dataset's transitions become the replay's first rows."""
        if isinstance(self.buffer, HerReplayBuffer):
            raise OfflineDataError(f"offline_mode prefill: {data.source} cannot be copied into a goal env's HER "
                                   "buffer (it keeps each env's episodes n_envs rows apart); use offline_mode mix, "
                                   "where HER relabels the dataset's episodes too")
        if isinstance(self.buffer, FrameReplayBuffer):
            raise OfflineDataError(f"offline_mode prefill: {data.source} cannot be copied into an image run's frame "
                                   "buffer (it stores each env's frames as they come); use offline_mode mix")
        data.check_prefill_fits(self.buffer.capacity)
        self.buffer.add(data.obs, data.actions, data.rewards, data.next_obs, data.terminated,
                        (data.terminated > 0) | data.truncated)

    def apply(self, fn: Callable[[Any], Any]) -> list[Any]:
        """Call `fn(env)` on each training env and return the results."""
        return self.pool.apply(fn)

    # ---- checkpoints -------------------------------------------------------------------------------

    def env_state(self) -> tuple[dict, dict[str, np.ndarray]] | None:
        """The training envs' state, or None before they started."""
        if not self.started:
            return None
        return self.pool.get_state() if self.pool is not None else self.parked_envs

    def replay_state(self) -> dict[str, np.ndarray] | None:
        """The replay buffer's state_dict (what a checkpoint keeps of it), or None before it exists."""
        return None if self.buffer is None else self.buffer.state_dict()

    def checkpoint_parts(self, include_buffer: bool) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """The buffer and the envs' state, when asked for and there (a `last` checkpoint, to resume)."""
        meta: dict[str, Any] = {"has_buffer": bool(include_buffer and self.buffer is not None),
                                **self.offline_source.checkpoint_meta()}
        env_state = self.env_state() if include_buffer else None
        meta["has_envs"] = env_state is not None
        arrays: dict[str, np.ndarray] = {}
        if meta["has_buffer"]:
            arrays.update({BUFFER_PREFIX + k: v for k, v in self.buffer.state_dict().items()})
        if env_state is not None:
            env_meta, env_arrays = env_state
            meta["envs"] = env_meta
            arrays.update({ENVS_PREFIX + k: v for k, v in env_arrays.items()})
        return meta, arrays

    def restore(self, meta: dict[str, Any], arrays: dict[str, np.ndarray], num_steps: int) -> None:
        """Take the buffer and envs a checkpoint holds (`num_steps`: where its run stands)."""
        self.offline_source.restore(meta)
        if meta.get("has_buffer"):
            self.buffer = self._make_buffer()
            self.buffer.load_state_dict(buffer_state(arrays))
        if meta.get("has_envs"):
            self.close_workers()
            self.pool = None
            self.started = True  # restored from the checkpoint, not reset
            self.parked_envs = (meta["envs"], _with_prefix(arrays, ENVS_PREFIX))
            if self.config.env_workers == 0:  # in-process envs are restored now; worker processes start with learn()
                self.start(num_steps)
