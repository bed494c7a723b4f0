"""Goal-conditioned envs (the env side of HER, Andrychowicz et al. 2017; the buffer is softac.replay.her_buffer).

A goal env (Gymnasium-Robotics' Fetch arm and mazes, or any env built the same way) observes a dict with
`observation`, `achieved_goal` and `desired_goal`, and has `compute_reward(achieved_goal, desired_goal, info)`
that works on batches. The networks see the dict flattened into one vector, its keys in the observation
space's order (Gymnasium's Dict sorts them: achieved_goal, desired_goal, observation), which is what
`DictLayout` records; `batched_reward_fn` is the env's reward for relabelled goals.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import gymnasium as gym
import numpy as np

from softac.errors import SoftacError

GOAL_KEYS = ("observation", "achieved_goal", "desired_goal")


@dataclass(frozen=True)
class DictLayout:
    """Where each key of a dict observation (a goal env's, or any other) sits in the flat vector the networks
    see: the keys in their space's order, each flattened."""
    keys: tuple[str, ...]
    slices: dict[str, slice]
    dim: int

    def flatten(self, obs: dict[str, Any]) -> np.ndarray:
        """One dict observation, or a dict of batches (leading axis), as flat float32 vectors."""
        missing = [k for k in self.keys if k not in obs]
        if missing:
            raise SoftacError(f"observation dict lacks {', '.join(missing)}; this agent expects keys "
                              f"{', '.join(self.keys)}")
        parts = [np.asarray(obs[k], np.float32) for k in self.keys]
        sizes = [self.slices[k].stop - self.slices[k].start for k in self.keys]
        single = all(p.size == n for p, n in zip(parts, sizes))
        if single:
            return np.concatenate([p.reshape(-1) for p in parts])
        batch = len(parts[0])
        try:
            return np.concatenate([p.reshape(batch, n) for p, n in zip(parts, sizes)], axis=1)
        except ValueError:
            raise SoftacError(f"observation dict's parts do not match this agent's sizes "
                              f"({', '.join(f'{k}: {n}' for k, n in zip(self.keys, sizes))})") from None


def dict_observation_space(env: gym.Env) -> gym.spaces.Dict | None:
    """The Dict observation space under softac's flattening wrapper, or the env's own if it is a Dict."""
    while isinstance(env, gym.Wrapper):
        if isinstance(env, gym.wrappers.FlattenObservation):
            space = env.env.observation_space
            return space if isinstance(space, gym.spaces.Dict) else None
        env = env.env
    space = env.observation_space
    return space if isinstance(space, gym.spaces.Dict) else None


def dict_layout(space: gym.spaces.Dict) -> DictLayout:
    """The flat layout of a Dict space: its keys in order, each flattened (as gym.spaces.flatten does)."""
    slices, start = {}, 0
    for key, sub in space.spaces.items():
        n = int(gym.spaces.flatdim(sub))
        slices[key] = slice(start, start + n)
        start += n
    return DictLayout(tuple(space.spaces), slices, start)


def is_goal_env(env: gym.Env) -> bool:
    """The three goal keys in a Dict observation space, and a callable compute_reward."""
    space = dict_observation_space(env)
    return (space is not None and all(k in space.spaces for k in GOAL_KEYS)
            and callable(getattr(env.unwrapped, "compute_reward", None)))


RewardFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


def batched_reward_fn(env: gym.Env, name: str) -> RewardFn:
    """`reward(achieved_goals, desired_goals)` for batches, from the env's compute_reward; checked here on a
    batch of three so that an env whose compute_reward takes one goal at a time fails at the start, in one
    line. Infos are not kept in the buffer: each relabelled transition's info is an empty dict."""
    compute = env.unwrapped.compute_reward
    space = dict_observation_space(env)
    goals = np.stack([np.asarray(space.spaces["desired_goal"].sample(), np.float32).reshape(-1) for _ in range(3)])
    try:
        out = np.asarray(compute(goals, goals[::-1], [{} for _ in range(3)]), np.float64)
    except Exception as exc:
        raise SoftacError(f"env {name}: compute_reward does not accept a batch of goals ({type(exc).__name__}: "
                          f"{exc}); HER needs one that does, as Gymnasium-Robotics' envs have".splitlines()[0]) from None
    if out.shape != (3,) or not np.all(np.isfinite(out)):
        raise SoftacError(f"env {name}: compute_reward does not accept a batch of goals (given 3, it returned "
                          f"shape {out.shape}, not (3,) finite rewards); HER needs one that does, as "
                          "Gymnasium-Robotics' envs have")

    def reward(achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        n = len(achieved)
        return np.asarray(compute(achieved, desired, [{} for _ in range(n)]), np.float32).reshape(n)

    return reward
