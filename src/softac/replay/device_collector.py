"""`DeviceCollector`: the training envs and the replay buffer of a run that collects on the device (issue 67).

It holds what the device's chunks carry from one to the next (softac.run.device_transitions runs them): the N
envs' batch (`envs.device_envs.EnvBatch`: their state pytree, the observations to act on, episode counters, the
reset key), the replay buffer of device arrays (`replay.device_buffer`) and the key its chunks draw actions and
batches from. To the training loop it is a collector like the host's: a host copy of the env for evaluation and
videos (`make_env`), the bytes a transition takes, its parts of a checkpoint and their restore. Its memory is
stated and checked before anything is allocated. With offline_data (issue 68), the dataset is read once and put
on the device whole (`OfflineOnDevice`), for the chunks to draw each batch's offline rows from.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import gymnasium as gym
import numpy as np

from softac.base.memory import available_memory_bytes, memory_shortfall
from softac.config.sac_config import SACConfig
from softac.envs.device_envs import DeviceEnvs, EnvBatch
from softac.envs.make import EnvSource, SpaceInfo, copy_env
from softac.errors import CheckpointError, SoftacError
from softac.replay import device_buffer
from softac.replay.buffer import BufferMemoryError
from softac.replay.device_buffer import DeviceReplay
from softac.replay.offline import OfflineData, OfflineDataError, OfflineSource

BUFFER_PREFIX, ENVS_PREFIX = "buffer/", "envs/"  # checkpoint array names, as the host collector's
KEY_NAME = "collect_key"


def device_memory_bytes() -> int:
    """What the default device can still allocate: a GPU's limit less what is in use, else the host's memory."""
    import jax

    stats = getattr(jax.devices()[0], "memory_stats", lambda: None)() or {}
    if "bytes_limit" in stats:
        return int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0))
    return available_memory_bytes()


class OfflineOnDevice(NamedTuple):
    """An offline dataset's transitions as device arrays (observations raw, actions in [-1, 1])."""
    obs: Any
    actions: Any
    rewards: Any
    next_obs: Any
    terminated: Any


class DeviceCollector:
    """N envs on the device and their replay buffer, made on first use (`start`)."""

    def __init__(self, config: SACConfig, env_source: EnvSource, spaces: SpaceInfo, device_env: Any,
                 episode_length: int, env_action_repeat: int = 1,
                 offline_loader: Callable[[], OfflineData] | None = None):
        self.config, self.env_source, self.spaces = config, env_source, spaces
        self.offline_source = OfflineSource(offline_loader)
        self.offline_device: OfflineOnDevice | None = None
        repeat = config.action_repeat  # softac's own repeat on top of the env's: agent steps as on the host
        self.envs = DeviceEnvs(device_env, config.n_envs, -(-episode_length // repeat), env_action_repeat * repeat)
        self.capacity = device_buffer.capacity_for(config.buffer_size, config.n_envs)
        self.check_memory()
        self.replay: DeviceReplay | None = None
        self.batch: EnvBatch | None = None
        self.key: Any = None
        self.started = False

    @property
    def bytes_per_transition(self) -> float:
        return float(device_buffer.bytes_per_row(self.spaces.obs_dim, self.spaces.act_dim, self.config.buffer_obs_once,
                                                 self.capacity, self.config.n_envs))

    def empty_replay(self) -> DeviceReplay:
        return device_buffer.empty(self.capacity, self.spaces.obs_dim, self.spaces.act_dim,
                                   self.config.buffer_obs_once, self.config.n_envs)

    def check_memory(self, fraction: float = 0.8) -> None:
        short = memory_shortfall(self.capacity * self.bytes_per_transition, fraction, device_memory_bytes(),
                                 " on the device")
        if short is not None:
            raise BufferMemoryError(f"replay buffer of {self.capacity:,} transitions needs {short}; lower buffer_size "
                                    "(--set buffer_size=N)" + ("" if self.config.buffer_obs_once else
                                                               ", or store each observation once "
                                                               "(--set buffer_obs_once=true)"))

    def make_env(self, render_mode: str | None = None, **kwargs: Any) -> gym.Env:
        """A host copy of the training env (evaluation and videos run on it)."""
        return copy_env(self.env_source, render_mode, **kwargs)

    @property
    def offline(self) -> OfflineData | None:
        """The run's offline dataset once read (None before, or without offline_data)."""
        return self.offline_source.data

    def load_offline(self) -> OfflineData | None:
        """The run's offline dataset, read once and put on the device (its memory checked beside the replay's)."""
        data = self.offline_source.load()
        if data is not None and self.offline_device is None and self.config.mixes_offline_data:
            import jax.numpy as jnp

            short = memory_shortfall(self.capacity * self.bytes_per_transition + data.nbytes,
                                     available=device_memory_bytes(), where=" on the device")
            if short is not None:
                raise OfflineDataError(f"offline data {data.source}: its {len(data):,} transitions and the replay "
                                       f"need {short}")
            self.offline_device = OfflineOnDevice(*(jnp.asarray(a, jnp.float32) for a in (
                data.obs, data.actions, data.rewards, data.next_obs, data.terminated)))
        return data

    def prefilled(self, replay: DeviceReplay, data: OfflineData) -> DeviceReplay:
        """offline_mode prefill: the dataset's transitions as the replay's first rows, in whole vector steps (the
        replay is written n_envs rows at a time, so the last len(data) % n_envs rows are left out, and said so)."""
        import warnings

        import jax.numpy as jnp

        n = self.config.n_envs
        data.check_prefill_fits(self.capacity)
        rows = len(data) - len(data) % n
        if rows < len(data):
            warnings.warn(f"offline_mode prefill: {data.source}'s last {len(data) - rows} transitions are left out "
                          f"(the device's replay is written {n} rows, one vector step, at a time)", stacklevel=3)
        ends = (data.terminated > 0) | data.truncated
        columns = dict(obs=data.obs, actions=data.actions, rewards=data.rewards, next_obs=data.next_obs,
                       terminated=data.terminated, done=ends)
        filled = {name: getattr(replay, name).at[:rows].set(jnp.asarray(value[:rows], getattr(replay, name).dtype))
                  for name, value in columns.items()}
        return replay._replace(**filled, position=jnp.asarray(rows % self.capacity, jnp.int32),
                               size=jnp.asarray(rows, jnp.int32))

    def start(self, num_steps: int) -> None:
        """The buffer and the envs, when not there: fresh envs reset from a key of the seed and `num_steps`."""
        import jax

        if self.replay is None:
            self.replay = self.empty_replay()
            if self.config.offline_mode == "prefill" and self.load_offline() is not None:
                self.replay = self.prefilled(self.replay, self.offline)
        self.load_offline()
        if not self.started:
            key = jax.random.PRNGKey(self.config.seed)
            env_key, self.key = jax.random.split(jax.random.fold_in(key, num_steps))
            self.batch = jax.jit(self.envs.reset)(env_key)
            self.started = True

    def close_workers(self) -> None:
        """No worker processes: the envs live on the device."""

    def can_sample(self) -> bool:
        return self.replay is not None and int(self.replay.size) > 0

    def apply(self, fn: Callable[[Any], Any]) -> list[Any]:
        raise SoftacError("the training envs of a run that collects on the device are arrays inside its jitted "
                          "steps, not env objects: call the function on make_env()'s copy instead")

    # ---- checkpoints -------------------------------------------------------------------------------

    def replay_state(self) -> dict[str, np.ndarray] | None:
        """The replay's rows and position as a checkpoint keeps them (replay_rows), or None before it exists."""
        return None if self.replay is None else self.replay_rows()

    def checkpoint_parts(self, include_buffer: bool) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """The replay's rows held and its position, the envs' batch and the key (a `last` checkpoint, to resume)."""
        meta: dict[str, Any] = {"has_buffer": bool(include_buffer and self.replay is not None),
                                "has_envs": bool(include_buffer and self.started),
                                **self.offline_source.checkpoint_meta()}
        arrays: dict[str, np.ndarray] = {}
        if meta["has_buffer"]:
            arrays.update({BUFFER_PREFIX + name: value for name, value in self.replay_rows().items()})
        if meta["has_envs"]:
            import jax

            leaves = jax.tree_util.tree_leaves((self.batch, self.key))
            meta["envs"] = {"kind": "device", "leaves": len(leaves), "n_envs": self.config.n_envs}
            arrays.update({f"{ENVS_PREFIX}{i}": np.asarray(leaf) for i, leaf in enumerate(leaves)})
        return meta, arrays

    def replay_rows(self) -> dict[str, np.ndarray]:
        """The replay's rows held and its positions, as the checkpoint keeps them (obs once: the observations written
        ahead of `size` too, the side ring whole; the host's ObsOnceReplayBuffer.state_dict's form)."""
        replay, size = self.replay, int(self.replay.size)
        rows = {"position": np.asarray(replay.position)}
        if not device_buffer.obs_once(replay):
            return {**rows, **{name: np.asarray(getattr(replay, name))[:size] for name in device_buffer.ROWS}}
        written = min(size + self.config.n_envs, self.capacity)
        rows.update({name: np.asarray(getattr(replay, name))[:size] for name in device_buffer.OBS_ONCE_ROWS})
        rows.update({name: np.asarray(getattr(replay, name)) for name in device_buffer.OBS_ONCE_RING})
        return {**rows, "obs": np.asarray(replay.obs)[:written], "final_pos": np.asarray(replay.final_pos)}

    def replay_from_rows(self, rows: dict[str, np.ndarray]) -> DeviceReplay:
        import jax.numpy as jnp

        replay = self.empty_replay()
        once = device_buffer.obs_once(replay)
        if once != ("final_slot" in rows):
            raise CheckpointError("its replay buffer was written with buffer_obs_once="
                                  f"{str(not once).lower()}; resume with the same setting")
        size = len(rows["rewards"])
        if not once and "done" not in rows:  # checkpoints from before n-step returns on the device (always n_step 1)
            rows = {**rows, "done": rows["terminated"] > 0}
        if size > self.capacity or (once and len(rows["final_obs"]) != replay.final_obs.shape[0]):
            raise CheckpointError(f"its replay buffer holds {size:,} transitions, more than buffer_size allows "
                                  f"({self.capacity:,}), or another n_envs' layout")
        per_row = device_buffer.OBS_ONCE_ROWS + ("obs",) if once else device_buffer.ROWS
        filled = {name: getattr(replay, name).at[:len(rows[name])].set(jnp.asarray(rows[name])) for name in per_row}
        if once:
            filled.update({name: jnp.asarray(rows[name]) for name in device_buffer.OBS_ONCE_RING},
                          final_pos=jnp.asarray(rows["final_pos"], jnp.int32))
        return replay._replace(**filled, size=jnp.asarray(size, jnp.int32),
                               position=jnp.asarray(rows["position"], jnp.int32))

    def restore(self, meta: dict[str, Any], arrays: dict[str, np.ndarray], num_steps: int) -> None:
        import jax
        import jax.numpy as jnp

        self.offline_source.restore(meta)
        if meta.get("has_buffer"):
            self.replay = self.replay_from_rows({name[len(BUFFER_PREFIX):]: value for name, value in arrays.items()
                                                 if name.startswith(BUFFER_PREFIX)})
        if meta.get("has_envs"):
            envs = meta.get("envs", {})
            if envs.get("kind") != "device" or envs.get("n_envs") != self.config.n_envs:
                raise CheckpointError("its envs were not collected on the device with these n_envs")
            template = jax.eval_shape(lambda k: (self.envs.reset(k), k), jax.random.PRNGKey(0))
            leaves, tree = jax.tree_util.tree_flatten(template)
            saved = [arrays.get(f"{ENVS_PREFIX}{i}") for i in range(len(leaves))]
            if envs.get("leaves") != len(leaves) or any(
                    s is None or s.shape != t.shape or s.dtype != t.dtype for s, t in zip(saved, leaves)):
                raise CheckpointError("its device envs' state does not match this env")
            self.batch, self.key = jax.tree_util.tree_unflatten(tree, [jnp.array(s, copy=True) for s in saved])
            self.started = True
