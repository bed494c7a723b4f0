"""Where `offline_data` comes from (issue 68): a softac run's replay buffer (its last checkpoint) or a Minari dataset
(softac.replay.offline), loaded once as transitions and checked against the env; and a run's buffer as episodes, for
`softac dataset`."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from softac.base.memory import memory_shortfall
from softac.config.sac_config import SACConfig
from softac.envs.goals import DictLayout
from softac.envs.make import SpaceInfo
from softac.errors import SoftacError
from softac.replay.buffer import ObsOnceReplayBuffer
from softac.replay.collector import buffer_state
from softac.replay.her_buffer import HerReplayBuffer
from softac.replay.image_buffer import FrameReplayBuffer
from softac.replay.offline import (OfflineData, OfflineDataError, check_dataset_spaces, check_offline_memory,
                                   episode_steps, minari_transitions)
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


def run_buffer(path: str | Path, layout: DictLayout | None = None) -> RunBuffer:
    """The replay buffer a run's last checkpoint (or a checkpoint directory saved with its buffer) holds (`layout`:
    a dict-observing env's, whose HER buffer keeps the observations' parts apart)."""
    path = Path(path)
    directory = path if ckpt.is_checkpoint(path) else ckpt.resolve(path, "last")
    short = memory_shortfall(ckpt.arrays_bytes(directory))  # before reading it: the buffer is most of it
    if short is not None:
        raise OfflineDataError(f"{path}: its checkpoint's arrays need {short}")
    meta, arrays = ckpt.load(directory)
    state = buffer_state(arrays)
    if not meta.get("has_buffer") or not state:
        raise OfflineDataError(f"{path} holds no replay buffer (a run's checkpoints/last has one; agent.save(path, "
                               "include_buffer=True) too)")
    return replay_rows(state, saved_config(meta, directory), meta, str(path), layout)


def replay_rows(state: dict[str, np.ndarray], config: SACConfig, meta: dict[str, Any], where: str,
                layout: DictLayout | None = None) -> RunBuffer:
    """A replay buffer's state_dict (a checkpoint's, or a live agent's) as transitions, oldest first; a HER
    buffer's observations put back together in the env's flat `layout`."""
    if "running_episode" in state and layout is not None and all(f"obs.{k}" in state for k in HerReplayBuffer.PARTS):
        state = {**state, "obs": layout.flatten({k: state[f"obs.{k}"] for k in layout.keys}),
                 "next_obs": layout.flatten({k: state[f"next_obs.{k}"] for k in layout.keys}),
                 "pos_size": state["pos_size"][:2]}
    n = int(config.n_envs)
    if "frames" in state:
        return _frame_rows(state, config, meta)
    capacity = int(config.buffer_size)
    if "position" in state and "pos_size" not in state:  # a device run's replay (issue 67): its rows as the host's
        capacity = max(n, (capacity // n) * n)  # device_buffer.capacity_for: written N at a time
        pos_size = [int(state["position"]), len(state["rewards"])] + (
            [int(state["final_pos"])] if "final_pos" in state else [])
        state = {**state, "pos_size": np.array(pos_size, np.int64)}
    fields = {"obs", "actions", "rewards", "terminated"} | ({"final_obs"} if config.buffer_obs_once else {"next_obs"})
    if not fields <= set(state) or state["obs"].ndim != 2:
        raise OfflineDataError(f"{where}: its replay buffer is not one softac reads as offline data (vector, dict "
                               "or frame-stack observations)")
    if config.buffer_obs_once:
        buffer = ObsOnceReplayBuffer(capacity, state["obs"].shape[1], state["actions"].shape[1], n)
        buffer.load_state_dict(state)
        rows, env = _written_rows(state, buffer.capacity, n, lambda rows: buffer.valid[rows])
        done = buffer.final_slot[rows] >= 0
        arrays_out = dict(obs=buffer.obs[rows], actions=buffer.actions[rows], rewards=buffer.rewards[rows],
                          next_obs=buffer.next_obs_of(rows), terminated=buffer.terminated[rows], done=done)
    else:
        rows, env = _written_rows(state, capacity, n)
        arrays_out = {k: state[k][rows] for k in ("obs", "actions", "rewards", "next_obs", "terminated")}
        arrays_out["done"] = state["done"][rows] if "done" in state else state["terminated"][rows] > 0
    return RunBuffer(**arrays_out, env=env, config=config, saved=meta, checksum=str(meta.get("sha256", "")))


def _frame_rows(state: dict[str, np.ndarray], config: SACConfig, meta: dict[str, Any]) -> RunBuffer:
    """An image run's frame buffer (each frame stored once) as transitions of frame stacks, oldest first: the rows
    whose frames the ring still holds."""
    obs_shape = (state["obs_frames"].shape[1], *state["frames"].shape[1:])
    n = int(config.n_envs)
    buffer = FrameReplayBuffer(config.buffer_size, obs_shape, state["actions"].shape[1], n)
    buffer.load_state_dict(state)
    rows, env = _written_rows(state, buffer.capacity, n, buffer._valid)
    return RunBuffer(obs=buffer._stacks(buffer.obs_frames[rows]), actions=buffer.actions[rows],
                     rewards=buffer.rewards[rows], next_obs=buffer._stacks(buffer.next_obs_frames[rows]),
                     terminated=buffer.terminated[rows], done=buffer.done[rows], env=env, config=config, saved=meta,
                     checksum=str(meta.get("sha256", "")))


def _written_rows(state: dict[str, np.ndarray], capacity: int, n_envs: int,
                  valid: Callable[[np.ndarray], np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The ring's written rows oldest first and each one's env, less those `valid` says the ring no longer holds
    whole (an obs-once or frame buffer's rows whose observations were overwritten)."""
    pos, size = (int(v) for v in state["pos_size"][:2])
    rows = _chronological(pos, size, capacity)
    env = _envs(rows, size, capacity, n_envs)
    if valid is None:
        return rows, env
    keep = valid(rows)
    return rows[keep], env[keep]


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
    """`offline_data`'s transitions for an env of `spaces`: a softac run's buffer, else a Minari dataset. A goal
    env's keep their episodes whole, for HER."""
    if spaces.image_state is not None:
        raise OfflineDataError(f"offline data for {env_name}: an image with state values (packed into softac's "
                               "frames) is not read as offline data; softac reads vectors, dicts of them and images")
    path = Path(source).expanduser()
    if path.is_dir() and holds_softac_run(path):
        return _from_run(source, path, env_name, spaces)
    return minari_transitions(source, env_name, spaces, to_normalised)


def _from_run(source: str, path: Path, env_name: str, spaces: SpaceInfo) -> OfflineData:
    try:
        buffer = run_buffer(path, spaces.layout)
    except SoftacError as exc:
        raise OfflineDataError(f"offline data {source}: {exc}") from None
    saved_spaces = buffer.saved.get("spaces", {})
    low = np.asarray(saved_spaces.get("low", spaces.low), np.float64)
    high = np.asarray(saved_spaces.get("high", spaces.high), np.float64)
    # each env's newest episode is cut by the data's end: buffer_episodes counts it, and ends it truncated
    cut = np.zeros(len(buffer.done), bool)
    for e in np.unique(buffer.env):
        cut[np.flatnonzero(buffer.env == e)[-1]] = not buffer.done[buffer.env == e][-1]
    episodes = int(buffer.done.sum() + cut.sum())
    check_dataset_spaces(source, buffer.obs.shape[1:], low, high, env_name, spaces)
    check_offline_memory(len(buffer.rewards), episodes, spaces, source)
    terminated = buffer.terminated.astype(np.float32)
    truncated = buffer.done & ~(terminated > 0)
    arrays = dict(obs=buffer.obs, actions=buffer.actions, rewards=buffer.rewards, next_obs=buffer.next_obs,
                  terminated=terminated, truncated=truncated)
    if not (spaces.goal_env or spaces.image_shape is not None):
        return OfflineData(**arrays, source=source, checksum=buffer.checksum, episodes=episodes)
    # a goal env's or an image env's rows episode after episode (each env's in turn): HER finds each row's episode,
    # and an image episode's frame stacks are held once
    order = np.concatenate([np.flatnonzero(buffer.env == e) for e in np.unique(buffer.env)])
    arrays = {k: v[order] for k, v in arrays.items()}
    arrays["truncated"] = arrays["truncated"] | cut[order]
    ends = (arrays["terminated"] > 0) | arrays["truncated"]
    t, length = episode_steps(ends) if spaces.goal_env else (None, None)
    if spaces.image_shape is not None:
        arrays["obs"], arrays["obs_row"] = _stacks_once(arrays.pop("obs"), arrays["next_obs"], ends)
        arrays["next_obs"] = None
    return OfflineData(**arrays, source=source, checksum=buffer.checksum, episodes=episodes, t=t, length=length)


def _stacks_once(obs: np.ndarray, next_obs: np.ndarray, ends: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows laid out episode after episode (`ends` marking each one's last) as each episode's observations [T+1]
    in turn, and each row's observation in them (OfflineData.obs_row)."""
    starts = np.concatenate([[True], ends[:-1]])
    before = np.cumsum(starts)  # episodes begun up to each row: the extra first observations before its next one
    next_at = np.arange(len(obs)) + before
    held = np.empty((len(obs) + int(starts.sum()), *obs.shape[1:]), obs.dtype)
    held[next_at] = next_obs
    held[next_at[starts] - 1] = obs[starts]
    return held, next_at - 1
