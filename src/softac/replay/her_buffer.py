"""Hindsight experience replay (HER, Andrychowicz et al. 2017): the replay buffer of goal envs.

A goal env (Gymnasium-Robotics' Fetch arm and mazes, or any env built the same way) observes a dict with
`observation`, `achieved_goal` and `desired_goal`, and has `compute_reward(achieved_goal, desired_goal, info)`
that works on batches. The networks see the dict flattened into one vector, its keys in the observation
space's order (Gymnasium's Dict sorts them: achieved_goal, desired_goal, observation), which is what
`DictLayout` records. The replay buffer keeps the three parts apart and, at sample time, gives a share of the
batch (her_k / (her_k + 1), as the paper's `future_p`) a goal that the same episode achieved later (`future`),
at its end (`final`) or anywhere (`episode`), with the reward the env's own compute_reward gives for it.

Only transitions of finished episodes are relabelled, so a relabelled goal always comes from the same
episode of the same env: an env's transitions are `n_envs` rows apart, and each row knows its episode's id,
its index in the episode and, once the episode has ended, the episode's length.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from softac.envs.goals import GOAL_KEYS, DictLayout, RewardFn, batched_reward_fn
from softac.errors import SoftacError
from softac.replay.buffer import RingBuffer, check_buffer_memory

HER_STRATEGIES = ("future", "final", "episode")


def goal_steps(rng: np.random.Generator, t: np.ndarray, length: np.ndarray, strategy: str) -> np.ndarray:
    """For transitions at steps `t` of finished episodes of `length` steps, the step whose achieved goal becomes
    each one's new goal: at or after it (`future`: its next_obs's achieved goal), the last (`final`), any
    (`episode`)."""
    if strategy == "final":
        return length - 1
    if strategy == "future":
        return t + np.floor(rng.random(t.shape) * (length - t)).astype(np.int64)
    return np.floor(rng.random(t.shape) * length).astype(np.int64)


def relabel_goals(obs: np.ndarray, next_obs: np.ndarray, rewards: np.ndarray, which: np.ndarray, goals: np.ndarray,
                  layout: DictLayout, reward_fn: RewardFn) -> None:
    """Rows `which` of a batch (flat observations, in place) given the desired goal `goals`, and the reward the
    env's compute_reward gives for it."""
    desired, achieved = layout.slices["desired_goal"], layout.slices["achieved_goal"]
    obs[which, desired] = goals
    next_obs[which, desired] = goals
    rewards[which] = reward_fn(next_obs[which, achieved], goals)


class HerReplayBuffer(RingBuffer):
    """Transitions of a goal env, each observation kept as its three parts, relabelled at sample time.

    Rows are written one vector step at a time, env 0 first (as ReplayBuffer's), so an env's next transition
    is n_envs rows on. Per row: `episode` (an id per episode, unique in the run), `t` (its index in that
    episode) and `length` (the episode's length once it has ended, 0 before). The running episodes' ids and
    lengths so far are part of the buffer's state, so a resumed run relabels as a straight one does.
    """

    PARTS = GOAL_KEYS
    ARRAYS = ("actions", "rewards", "terminated", "done", "episode", "t", "length")

    def __init__(self, capacity: int, layout: DictLayout, act_dim: int, n_envs: int, reward_fn: RewardFn,
                 strategy: str = "future", k: int = 4, memory_fraction: float = 0.8, gamma: float = 0.99):
        if strategy not in HER_STRATEGIES:
            raise SoftacError(f"her_strategy must be one of {', '.join(HER_STRATEGIES)}, got '{strategy}'")
        self.capacity, self.layout, self.act_dim, self.n_envs = int(capacity), layout, act_dim, n_envs
        self.n_step, self.gamma = 1, gamma
        self.reward_fn, self.strategy, self.k = reward_fn, strategy, int(k)
        self.relabel_fraction = self.k / (self.k + 1.0)
        check_buffer_memory(self.capacity, self.bytes_per_transition(layout.dim, act_dim), memory_fraction)
        # each part addressable by its key, as views into one array in the networks' flat layout, so that a
        # batch is one gather per field and the relabelling writes the desired_goal columns of that batch
        self.flat_obs = np.zeros((self.capacity, layout.dim), np.float32)
        self.flat_next_obs = np.zeros((self.capacity, layout.dim), np.float32)
        self.obs = {key: self.flat_obs[:, layout.slices[key]] for key in self.PARTS}
        self.next_obs = {key: self.flat_next_obs[:, layout.slices[key]] for key in self.PARTS}
        self.actions = np.zeros((self.capacity, act_dim), np.float32)
        self.rewards = np.zeros((self.capacity,), np.float32)
        self.terminated = np.zeros((self.capacity,), np.float32)
        self.done = np.zeros((self.capacity,), bool)
        self.episode = np.full((self.capacity,), -1, np.int64)
        self.t = np.zeros((self.capacity,), np.int64)
        self.length = np.zeros((self.capacity,), np.int64)
        self.pos = self.size = 0
        self.running_episode = np.arange(n_envs, dtype=np.int64)  # the id of each env's current episode
        self.running_length = np.zeros(n_envs, np.int64)
        self.next_episode = n_envs

    @staticmethod
    def bytes_per_transition(obs_dim: int, act_dim: int) -> int:
        return 4 * (2 * obs_dim + act_dim + 2) + 1 + 3 * 8

    def _ends_episode(self, rows: np.ndarray) -> np.ndarray:
        return self.done[rows]

    def start_new_episodes(self) -> None:
        """The envs were reset outside the buffer's view (a fresh start, or a resume that could not restore
        them): their unfinished episodes end here unrelabelled, and new ones begin."""
        n = self.n_envs
        self.running_episode = np.arange(self.next_episode, self.next_episode + n, dtype=np.int64)
        self.running_length[:] = 0
        self.next_episode += n

    def add(self, obs: np.ndarray, actions: np.ndarray, rewards: np.ndarray, next_obs: np.ndarray,
            terminated: np.ndarray, done: np.ndarray) -> None:
        n = len(rewards)
        if n != self.n_envs:
            raise SoftacError(f"HER buffer got {n} transitions for {self.n_envs} envs")
        rows = self._rows(n)
        self.flat_obs[rows] = obs
        self.flat_next_obs[rows] = next_obs
        self.actions[rows] = actions
        self.rewards[rows] = rewards
        self.terminated[rows] = terminated
        self.done[rows] = ended = np.asarray(done, bool)
        self.episode[rows] = self.running_episode
        self.t[rows] = self.running_length
        self.length[rows] = 0
        self.running_length += 1
        for env in np.flatnonzero(ended):
            length, episode = int(self.running_length[env]), int(self.running_episode[env])
            own = (rows[env] - n * np.arange(length)) % self.capacity
            own = own[self.episode[own] == episode]  # the episode's rows still in the buffer
            self.length[own] = length
            self.running_episode[env] = self.next_episode
            self.running_length[env] = 0
            self.next_episode += 1
        self._advance(n)

    def _goal_rows(self, rng: np.random.Generator, idx: np.ndarray) -> np.ndarray:
        """For each row (of a finished episode), the row whose achieved goal becomes its new goal."""
        t = self.t[idx]
        chosen = goal_steps(rng, t, self.length[idx], self.strategy)
        rows = (idx + (chosen - t) * self.n_envs) % self.capacity
        if self.strategy == "episode":  # earlier rows of a long episode may have been overwritten
            rows = np.where(self.episode[rows] == self.episode[idx], rows, idx)
        return rows

    def sample(self, rng: np.random.Generator, batch_size: int, n_batches: int = 1) -> dict[str, np.ndarray]:
        """`n_batches` batches of flat observations, each row relabelled with probability her_k/(her_k+1)
        where its episode has ended."""
        idx = rng.integers(0, self.size, size=(n_batches, batch_size)).reshape(-1)
        relabel = (rng.random(idx.shape) < self.relabel_fraction) & (self.length[idx] > 0)
        obs, next_obs, rewards = self.flat_obs[idx], self.flat_next_obs[idx], self.rewards[idx]
        which = np.flatnonzero(relabel)
        if which.size:
            goals = self.flat_next_obs[self._goal_rows(rng, idx[which]), self.layout.slices["achieved_goal"]]
            relabel_goals(obs, next_obs, rewards, which, goals, self.layout, self.reward_fn)
        shape = (n_batches, batch_size)
        return {"obs": obs.reshape(*shape, -1), "actions": self.actions[idx].reshape(*shape, -1),
                "rewards": rewards.reshape(shape), "next_obs": next_obs.reshape(*shape, -1),
                "terminated": self.terminated[idx].reshape(shape), "steps": np.ones(shape, np.float32)}

    def state_dict(self) -> dict[str, np.ndarray]:
        out = {name: getattr(self, name)[: self.size] for name in self.ARRAYS}
        for key in self.PARTS:  # by key, so a checkpoint does not depend on the flat layout's order
            out[f"obs.{key}"] = self.obs[key][: self.size]
            out[f"next_obs.{key}"] = self.next_obs[key][: self.size]
        out["pos_size"] = np.array([self.pos, self.size, self.next_episode], np.int64)
        out["running_episode"], out["running_length"] = self.running_episode.copy(), self.running_length.copy()
        return out

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        if "running_episode" not in state or len(state["running_episode"]) != self.n_envs:
            raise SoftacError("checkpoint buffer is not a HER buffer of this config's n_envs")
        pos, size, next_episode = (int(v) for v in state["pos_size"])
        if size > self.capacity:
            raise SoftacError(f"checkpoint buffer holds {size} transitions, more than buffer_size={self.capacity}")
        for name in self.ARRAYS:
            getattr(self, name)[:size] = state[name]
        for key in self.PARTS:
            self.obs[key][:size] = state[f"obs.{key}"]
            self.next_obs[key][:size] = state[f"next_obs.{key}"]
        self.pos, self.size, self.next_episode = pos, size, next_episode
        self.running_episode = np.asarray(state["running_episode"], np.int64).copy()
        self.running_length = np.asarray(state["running_length"], np.int64).copy()


@dataclass(frozen=True)
class HerSetup:
    """What the replay buffer needs to relabel: the goal layout, the env's batched reward, the strategy and k."""
    layout: DictLayout
    reward_fn: RewardFn
    strategy: str
    k: int


def her_setup(config: Any, env: gym.Env, spaces: Any) -> HerSetup | None:
    """HER for this config and env (`spaces`: softac.envs.make.SpaceInfo; errors name the env by config.env_id), or
    None: `her=auto` turns it on for goal envs; `her=on` on another env, or HER with n-step returns or
    buffer_obs_once, is refused in one line."""
    if config.her == "off" or (config.her == "auto" and not spaces.goal_env):
        return None
    if not spaces.goal_env:
        observed = spaces.layout.keys if spaces.layout is not None else f"a {spaces.obs_dim}-value vector"
        raise SoftacError(f"her=on needs a goal env (a dict observation with {', '.join(GOAL_KEYS)} and "
                          f"compute_reward); env {config.env_id} observes {observed}")
    if config.n_step > 1:
        raise SoftacError(f"n_step={config.n_step} cannot be combined with HER (a relabelled goal changes every "
                          "reward of the n steps); set n_step=1, or her=off")
    if config.buffer_obs_once:
        raise SoftacError("buffer_obs_once cannot be combined with HER (its buffer keeps the goal parts of each "
                          "observation apart); set buffer_obs_once=false, or her=off")
    layout = spaces.layout
    achieved, desired = (layout.slices[k] for k in ("achieved_goal", "desired_goal"))
    if achieved.stop - achieved.start != desired.stop - desired.start:
        raise SoftacError(f"env {config.env_id}: achieved_goal has {achieved.stop - achieved.start} values but "
                          f"desired_goal {desired.stop - desired.start}; HER needs goals of one shape")
    return HerSetup(layout, batched_reward_fn(env, config.env_id), config.her_strategy, config.her_k)
