"""Where `offline_data` comes from (issue 68): a softac run's replay buffer (its last checkpoint) or a Minari dataset
(softac.replay.offline), loaded once as transitions and checked against the env; and a run's buffer as episodes, for
`softac dataset`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from softac.config.sac_config import SACConfig
from softac.envs.make import SpaceInfo
from softac.errors import SoftacError
from softac.replay.buffer import ObsOnceReplayBuffer
from softac.replay.collector import buffer_state
from softac.replay.offline import (OfflineData, OfflineDataError, check_dataset_spaces, check_offline_memory,
                                   minari_transitions)
from softac.run import checkpoint as ckpt
from softac.run.checkpoint_contents import saved_config


@dataclass
class RunBuffer:
    """A run's replay buffer as transitions, oldest first; `env` is the env each row came from."""
    obs: np.ndarray
    actions: np.ndarray  # in [-1, 1]
    rewards: np.ndarray
    next_obs: np.ndarray
    terminated: np.ndarray  # float32
    done: np.ndarray  # bool: terminated or truncated
    env: np.ndarray
    config: SACConfig
    saved: dict[str, Any]  # the checkpoint's meta: its spaces ("spaces"), counters
    checksum: str  # the checkpoint's arrays' sha256


def holds_softac_run(path: Path) -> bool:
    return ckpt.is_checkpoint(path) or ckpt.is_checkpoint(path / "checkpoints" / "last")


def run_buffer(path: str | Path) -> RunBuffer:
    """The replay buffer a run's last checkpoint (or a checkpoint directory saved with its buffer) holds."""
    path = Path(path)
    directory = path if ckpt.is_checkpoint(path) else ckpt.resolve(path, "last")
    meta, arrays = ckpt.load(directory)
    state = buffer_state(arrays)
    if not meta.get("has_buffer") or not state:
        raise OfflineDataError(f"{path} holds no replay buffer (a run's checkpoints/last has one; agent.save(path, "
                               "include_buffer=True) too)")
    return replay_rows(state, saved_config(meta, directory), meta, str(path))


def replay_rows(state: dict[str, np.ndarray], config: SACConfig, meta: dict[str, Any], where: str) -> RunBuffer:
    """A replay buffer's state_dict (a checkpoint's, or a live agent's) as transitions, oldest first."""
    fields = {"obs", "actions", "rewards", "terminated"} | ({"final_obs"} if config.buffer_obs_once else {"next_obs"})
    if config.pixels or not fields <= set(state) or state["obs"].ndim != 2:
        raise OfflineDataError(f"{where}: its replay buffer holds images or goal-relabelled episodes; softac reads "
                               "vector transitions as offline data")
    n = int(config.n_envs)
    if config.buffer_obs_once:
        pos, size = (int(v) for v in state["pos_size"][:2])
        buffer = ObsOnceReplayBuffer(config.buffer_size, state["obs"].shape[1], state["actions"].shape[1], n)
        buffer.load_state_dict(state)
        rows = _chronological(pos, size, buffer.capacity)
        env = _envs(rows, size, buffer.capacity, n)
        keep = buffer.valid[rows]
        rows, env = rows[keep], env[keep]
        done = buffer.final_slot[rows] >= 0
        arrays_out = dict(obs=buffer.obs[rows], actions=buffer.actions[rows], rewards=buffer.rewards[rows],
                          next_obs=buffer.next_obs_of(rows), terminated=buffer.terminated[rows], done=done)
    else:
        pos, size = (int(v) for v in state["pos_size"])
        rows = _chronological(pos, size, config.buffer_size)
        env = _envs(rows, size, config.buffer_size, n)
        arrays_out = {k: state[k][rows] for k in ("obs", "actions", "rewards", "next_obs", "terminated")}
        arrays_out["done"] = state["done"][rows] if "done" in state else state["terminated"][rows] > 0
    return RunBuffer(**arrays_out, env=env, config=config, saved=meta, checksum=str(meta.get("sha256", "")))


def _chronological(pos: int, size: int, capacity: int) -> np.ndarray:
    """The written rows, oldest first: 0..size-1 until the ring is full, then from `pos` round."""
    return np.arange(size) if size < capacity else (pos + np.arange(capacity)) % capacity


def _envs(rows: np.ndarray, size: int, capacity: int, n_envs: int) -> np.ndarray:
    """Each chronological row's env: rows are written a vector step at a time, env 0 first, so the k-th oldest row
    is env (k + first) mod N, the oldest of a full ring being env (-capacity) mod N."""
    first = 0 if size < capacity else (-capacity) % n_envs
    return (np.arange(len(rows)) + first) % n_envs


def buffer_episodes(buffer: RunBuffer, to_env: Any) -> list[dict[str, np.ndarray]]:
    """The buffer's rows as episodes, each env's rows in order, cut after each episode end (Minari's layout:
    observations [T+1], actions [T] in env units, rewards, terminations, truncations). An env's oldest episode may
    start inside its episode (the ring overwrote its beginning); its newest one is cut by the data's end and marked
    truncated there."""
    episodes = []
    for e in np.unique(buffer.env):
        rows = np.flatnonzero(buffer.env == e)
        ends = np.flatnonzero(buffer.done[rows]) + 1
        for part in np.split(rows, ends):
            if len(part) == 0:
                continue
            terminated = buffer.terminated[part] > 0
            truncated = buffer.done[part] & ~terminated
            truncated[-1] |= not terminated[-1]
            episodes.append({"observations": np.concatenate([buffer.obs[part[:1]], buffer.next_obs[part]]),
                             "actions": np.asarray(to_env(buffer.actions[part]), np.float32),
                             "rewards": buffer.rewards[part], "terminations": terminated, "truncations": truncated})
    return episodes


def load_offline_data(source: str, env_name: str, spaces: SpaceInfo, to_normalised: Any) -> OfflineData:
    """`offline_data`'s transitions for an env of `spaces`: a softac run's buffer, else a Minari dataset."""
    if spaces.layout is not None or spaces.image_shape is not None:
        raise OfflineDataError(f"offline data for {env_name}: goal envs (dict observations) and images are not read "
                               "as offline data yet")
    path = Path(source).expanduser()
    if path.is_dir() and holds_softac_run(path):
        return _from_run(source, path, env_name, spaces)
    return minari_transitions(source, env_name, spaces.obs_dim, spaces.low, spaces.high, to_normalised)


def _from_run(source: str, path: Path, env_name: str, spaces: SpaceInfo) -> OfflineData:
    try:
        buffer = run_buffer(path)
    except SoftacError as exc:
        raise OfflineDataError(f"offline data {source}: {exc}") from None
    saved_spaces = buffer.saved.get("spaces", {})
    low = np.asarray(saved_spaces.get("low", spaces.low), np.float64)
    high = np.asarray(saved_spaces.get("high", spaces.high), np.float64)
    check_dataset_spaces(source, buffer.obs.shape[1:], low, high, env_name, spaces.obs_dim, spaces.low, spaces.high)
    check_offline_memory(len(buffer.rewards), spaces.obs_dim, spaces.act_dim, source)
    # buffer_episodes' count: each episode end, and each env whose newest episode the data cuts
    episodes = int(buffer.done.sum()) + sum(not buffer.done[buffer.env == e][-1] for e in np.unique(buffer.env))
    return OfflineData(obs=buffer.obs, actions=buffer.actions, rewards=buffer.rewards, next_obs=buffer.next_obs,
                       terminated=buffer.terminated.astype(np.float32),
                       truncated=buffer.done & ~(buffer.terminated > 0), source=source, checksum=buffer.checksum,
                       episodes=episodes)
