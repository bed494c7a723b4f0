"""`SAC`: the Python API. It holds the learner state and composes the parts.

    agent = SAC(SACConfig.preset("InvertedPendulum-v5"))
    agent.learn(20_000)
    agent.save("pendulum"); agent = SAC.load("pendulum")
    action = agent.predict(obs, deterministic=True)
"""

from __future__ import annotations

import contextlib
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from softac import checkpoint as ckpt
from softac.buffer import ObsOnceReplayBuffer, ReplayBuffer, buffer_bytes_per_transition, make_buffer
from softac.config import SACConfig
from softac.device import select_device
from softac.envs import EnvFailed, EnvPool, EnvSource, check_spaces, copy_env, env_name, make_env
from softac.errors import SoftacError
from softac.normalization import RunningObsNorm
from softac.rundir import versions
from softac.runstate import RunState

if TYPE_CHECKING:  # sac imports JAX, which the agent loads only when it is made
    import gymnasium as gym

    from softac.env_workers import WorkerEnvPool
    from softac.sac import SACState


def check_model_memory(config: SACConfig, obs_dim: int, act_dim: int, fraction: float = 0.5) -> None:
    """Refuse networks and batches the machine cannot hold, before allocating anything."""
    from softac.buffer import _human, available_memory_bytes

    def mlp_params(sizes: list[int]) -> int:
        return sum((a + 1) * b for a, b in zip(sizes[:-1], sizes[1:]))

    actor = mlp_params([obs_dim, *config.hidden_sizes, 2 * act_dim])
    critics = config.n_critics * mlp_params([obs_dim + act_dim, *config.hidden_sizes, 1])
    parameters = 4 * (3 * actor + 4 * critics)  # weights + Adam moments; critics also have targets
    # activations kept for the backward passes, per gradient step (critics, targets and actor, both phases)
    activations = 4 * config.batch_size * sum(config.hidden_sizes) * (4 * config.n_critics + 4)
    batch = config.batch_size * config.gradient_steps * ReplayBuffer.bytes_per_transition(obs_dim, act_dim)
    need, have = parameters + activations + batch, available_memory_bytes()
    if need > fraction * have:
        raise SoftacError(f"networks and batches need about {_human(need)} ({(actor + critics):,} parameters, "
                          f"batch_size={config.batch_size}) but only {_human(have)} is available; "
                          "lower hidden_sizes or batch_size")


def _bounds_text(low: np.ndarray, high: np.ndarray) -> str:
    def one_line(a: np.ndarray) -> str:
        return np.array2string(np.asarray(a), precision=4, separator=", ", threshold=8, max_line_width=10**9)

    return f"low {one_line(low)}, high {one_line(high)}"


class SAC:
    """A Soft Actor-Critic agent for one env (an id or a gym.Env instance)."""

    def __init__(self, config: SACConfig | None = None, env: EnvSource | None = None):
        if config is None:
            config = SACConfig.for_env(env if isinstance(env, str) else None)
        if env is None:
            env = config.env_id
        elif isinstance(env, str):
            config = config.replace(env_id=env)
        else:
            config = config.replace(env_id=env_name(env))
        self.config = config
        self.env_source: EnvSource = env
        self.device = select_device(config.device)

        probe = make_env(env)
        self.spaces = check_spaces(probe)
        if isinstance(env, str):
            probe.close()
        else:
            self.env_source = probe  # the (possibly flattened) user instance

        check_model_memory(config, self.spaces.obs_dim, self.spaces.act_dim)
        from softac import sac

        self.fns = sac.build(config, self.spaces.obs_dim, self.spaces.act_dim, self.spaces.low, self.spaces.high)
        self.scaler = self.fns.scaler
        self.state: SACState = self.fns.init(config.seed)  # what the agent knows
        self.run = RunState.new(config.seed)  # where its training stands (counters, RNGs, evaluations, its run)
        # running observation statistics (obs_norm): updated while training, applied wherever the actor acts
        self.obs_norm = RunningObsNorm(self.spaces.obs_dim, config.obs_norm_clip) if config.obs_norm else None
        self.buffer: ReplayBuffer | ObsOnceReplayBuffer | None = None
        self.pool: EnvPool | WorkerEnvPool | None = None
        self.pool_started = False
        # the envs' state (EnvPool.get_state's) while no pool holds it: loaded from a checkpoint, or kept from
        # env worker processes that a finished learn() closed; the next pool starts from it
        self.parked_envs: tuple[dict, dict[str, np.ndarray]] | None = None

    # ---- where training stands (the rest of the run state: agent.run) ------------

    @property
    def num_steps(self) -> int:
        """Environment steps trained so far (SB3's num_timesteps)."""
        return self.run.num_steps

    @property
    def num_episodes(self) -> int:
        """Training episodes finished so far."""
        return self.run.num_episodes

    # ---- parts made on first use ----------------------------------------------

    @property
    def buffer_bytes_per_transition(self) -> float:
        return buffer_bytes_per_transition(self.config, self.spaces.obs_dim, self.spaces.act_dim)

    def make_env(self, render_mode: str | None = None, **kwargs: Any) -> gym.Env:
        return copy_env(self.env_source, render_mode, **kwargs)

    def training_parts(self) -> tuple[ReplayBuffer | ObsOnceReplayBuffer, EnvPool | WorkerEnvPool]:
        if self.buffer is None:
            self.buffer = make_buffer(self.config, self.spaces.obs_dim, self.spaces.act_dim)
        if self.pool is None:
            self.pool = self._make_pool()
            if self.parked_envs is not None:
                self._restore_envs(*self.parked_envs)
        if not self.pool_started:
            self.pool.reset(self.num_steps)
            self.pool_started = True
        return self.buffer, self.pool

    def _make_pool(self) -> EnvPool | WorkerEnvPool:
        source, cfg = self.env_source, self.config
        if cfg.env_workers > 0:
            from softac.env_workers import WorkerEnvPool

            return WorkerEnvPool(source, cfg.n_envs, cfg.seed, env_name(source), cfg.env_workers)

        def make(i: int):
            return source if (i == 0 and not isinstance(source, str)) else copy_env(source)

        return EnvPool(make, cfg.n_envs, cfg.seed, env_name(source))

    def _restore_envs(self, meta: dict, arrays: dict[str, np.ndarray]) -> None:
        self.parked_envs = None
        if not self.pool.set_state(meta, arrays, self.num_steps):
            import warnings

            warnings.warn(f"env {self.pool.name} cannot save its state, so resumed training starts fresh episodes "
                          "(give its class save_state()/load_state() for an exact resume)", stacklevel=3)

    def close_env_workers(self) -> None:
        """Stop the env worker processes, if any (learn() does as it ends, however it ends), keeping their
        envs' state for the next learn(), which carries on exactly; envs lost with a failed worker start
        fresh episodes there."""
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
            self.pool_started = False

    def env_state(self) -> tuple[dict, dict[str, np.ndarray]] | None:
        """The training envs' state (for a checkpoint), or None before they started."""
        if not self.pool_started:
            return None
        return self.pool.get_state() if self.pool is not None else self.parked_envs

    # ---- acting ---------------------------------------------------------------

    def normalize_obs(self, obs: np.ndarray) -> np.ndarray:
        """What the networks see: raw observations, or with obs_norm the normalised ones."""
        return obs if self.obs_norm is None else self.obs_norm.normalize(obs)

    def predict(self, obs: Any, deterministic: bool = True) -> np.ndarray:
        """Env-scaled action(s) for one observation or a batch of them."""
        obs = np.asarray(obs, np.float32)
        single = obs.ndim <= 1
        batch = obs.reshape(1, -1) if single else obs.reshape(obs.shape[0], -1)
        if batch.shape[1] != self.spaces.obs_dim:
            raise SoftacError(f"observation has {batch.shape[1]} values; this agent expects {self.spaces.obs_dim}")
        batch = self.normalize_obs(batch)
        if deterministic:
            actions = np.asarray(self.fns.act_deterministic(self.state.actor, self.state.actor_stats, batch))
            actions = self.scaler.to_env(actions)
        else:
            _, actions, self.run.predict_key = self.fns.act(self.state.actor, self.state.actor_stats, batch,
                                                           self.run.predict_key)
            actions = np.asarray(actions)
        return actions[0] if single else actions

    # ---- training ---------------------------------------------------------------

    def learn(self, steps: int, run_dir: str | Path | None = None, target_return: float | None = None,
              progress: bool | None = None, callbacks: list | None = None,
              loggers: list | None = None) -> dict[str, Any]:
        """Train for `steps` more environment steps; returns a summary dict (its stop_reason: steps,
        target_return, or "callback: ..."). `callbacks`: softac.callbacks.Callback objects; `loggers`: extra
        softac.loggers.Logger objects that get every metrics record (softac does not close them)."""
        from softac.rundir import run_lock
        from softac.trainer import train

        # one writer per run: a second process training into run_dir is refused (RunLocked, exit 2)
        with run_lock(run_dir) if run_dir is not None else contextlib.nullcontext():
            try:
                return train(self, steps, run_dir=run_dir, target_return=target_return, progress=progress,
                             callbacks=callbacks, loggers=loggers)
            finally:
                self.close_env_workers()  # no worker process outlives the call, whatever ended it

    # ---- save / load --------------------------------------------------------------

    def checkpoint_parts(self, include_buffer: bool) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        import jax

        arrays: dict[str, np.ndarray] = {}
        leaves = jax.tree_util.tree_flatten_with_path(self.state)[0]
        for path, leaf in leaves:
            arrays["state" + jax.tree_util.keystr(path)] = np.asarray(leaf)
        run_meta, run_arrays = self.run.checkpoint_parts()
        arrays.update(run_arrays)
        if self.obs_norm is not None:  # in every checkpoint, best too: predict() needs them
            for k, v in self.obs_norm.state_dict().items():
                arrays[f"obs_norm/{k}"] = v
        meta: dict[str, Any] = {
            "config": self.config.to_dict(),
            "versions": versions(),
            "saved_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "spaces": {"obs_dim": self.spaces.obs_dim, "act_dim": self.spaces.act_dim,
                       "low": self.spaces.low.tolist(), "high": self.spaces.high.tolist()},
            **run_meta,
            "has_buffer": bool(include_buffer and self.buffer is not None),
        }
        env_state = self.env_state() if include_buffer else None
        meta["has_envs"] = env_state is not None
        if meta["has_buffer"]:
            for k, v in self.buffer.state_dict().items():
                arrays[f"buffer/{k}"] = v
        if env_state is not None:
            env_meta, env_arrays = env_state
            meta["envs"] = env_meta
            for k, v in env_arrays.items():
                arrays[f"envs/{k}"] = v
        return meta, arrays

    def _check_spaces(self, saved: dict[str, Any], where: Path | str, allow_new_bounds: bool) -> None:
        """The checkpoint's spaces against this agent's env: sizes must match; bounds too, unless allowed."""
        if saved.get("obs_dim") != self.spaces.obs_dim or saved.get("act_dim") != self.spaces.act_dim:
            raise ckpt.CheckpointError(
                f"checkpoint {where} is for observations of {saved.get('obs_dim')} and actions of "
                f"{saved.get('act_dim')} values, but the env has {self.spaces.obs_dim} and {self.spaces.act_dim}")
        if allow_new_bounds or "low" not in saved:
            return
        low, high = (np.asarray(saved[k], np.float32) for k in ("low", "high"))
        if not (np.array_equal(low, self.spaces.low) and np.array_equal(high, self.spaces.high)):
            raise ckpt.CheckpointError(
                f"checkpoint {where} was trained with action bounds {_bounds_text(low, high)}, but the env has "
                f"{_bounds_text(self.spaces.low, self.spaces.high)}; to scale its actions to the new bounds, "
                "pass allow_new_bounds=True (--allow-new-bounds)")

    def save(self, path: str | Path, include_buffer: bool = False) -> Path:
        """Save the agent (networks, optimisers, alpha, RNGs; the buffer and envs too if asked)."""
        meta, arrays = self.checkpoint_parts(include_buffer)
        return ckpt.save(path, meta, arrays)

    @classmethod
    def load(cls, path: str | Path, env: EnvSource | None = None, which: str | None = None,
             device: str | None = None, env_workers: int | None = None, allow_new_bounds: bool = False) -> "SAC":
        """Load a checkpoint directory or a run (its best checkpoint, else last). `device` and `env_workers`
        replace the saved config's: neither changes what the agent computes. An env whose action bounds
        differ from the saved ones is refused unless `allow_new_bounds` (the policy's actions, in [-1, 1]
        inside the networks, are then scaled to the new bounds)."""
        directory = ckpt.resolve(path, which)
        meta, arrays = ckpt.load(directory)
        try:
            config = SACConfig().replace(**meta["config"])
        except SoftacError as exc:
            raise ckpt.CheckpointError(f"checkpoint {directory} has an invalid config: {exc}") from None
        overrides = {key: value for key, value in (("device", device), ("env_workers", env_workers))
                     if value is not None}
        config = config.replace(**overrides)
        agent = cls(config, env)
        agent.restore(meta, arrays, directory, allow_new_bounds)
        return agent

    def restore(self, meta: dict[str, Any], arrays: dict[str, np.ndarray], where: Path | str = "",
                allow_new_bounds: bool = False) -> None:
        import jax
        import jax.numpy as jnp

        self._check_spaces(meta.get("spaces", {}), where, allow_new_bounds)
        paths, treedef = jax.tree_util.tree_flatten_with_path(self.state)
        leaves = []
        for path, template in paths:
            name = "state" + jax.tree_util.keystr(path)
            value = arrays.get(name)
            if value is None or value.shape != np.shape(template) or value.dtype != np.asarray(template).dtype:
                raise ckpt.CheckpointError(f"checkpoint {where} does not match this config/env at {name}")
            # a copy the device owns: jnp.asarray may alias the NumPy array on CPU, and the update donates
            # the state's buffers (older jaxlibs then corrupt the heap; seen with jax 0.4.30 and 0.5.3)
            leaves.append(jnp.array(value, copy=True))
        self.state = jax.tree_util.tree_unflatten(treedef, leaves)
        self.run.restore(meta, arrays, where)
        if self.obs_norm is not None:
            stats = {k[len("obs_norm/"):]: v for k, v in arrays.items() if k.startswith("obs_norm/")}
            if set(stats) != {"count", "mean", "m2"}:
                raise ckpt.CheckpointError(f"checkpoint {where} has obs_norm on but no observation statistics")
            try:
                self.obs_norm.load_state_dict(stats)
            except SoftacError as exc:
                raise ckpt.CheckpointError(f"checkpoint {where}: {exc}") from None
        if meta.get("has_buffer"):
            self.buffer = make_buffer(self.config, self.spaces.obs_dim, self.spaces.act_dim)
            self.buffer.load_state_dict({k[len("buffer/"):]: v for k, v in arrays.items() if k.startswith("buffer/")})
        if meta.get("has_envs"):
            self.close_env_workers()
            self.pool = None
            self.pool_started = True  # restored from the checkpoint, not reset
            self.parked_envs = (meta["envs"], {k[len("envs/"):]: v for k, v in arrays.items() if k.startswith("envs/")})
            if self.config.env_workers == 0:  # in-process envs are restored now; worker processes start with learn()
                self.training_parts()
