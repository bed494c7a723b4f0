"""A stand-in for stable_baselines3's HerReplayBuffer (see tests/fake_peers/README.md): SB3's DictReplayBuffer
layout (a dict of [size, n_envs, ...] observation arrays) and its episode arrays (ep_start, ep_length,
_current_ep_start), filled as SB3 fills them, so that a HER peer's checkpoint and resume are tested."""

import numpy as np


class HerReplayBuffer:
    def __init__(self, size, env, n_sampled_goal=4, goal_selection_strategy="future"):
        self.buffer_size, self.pos, self.full = size, 0, False
        self.n_sampled_goal, self.goal_selection_strategy = n_sampled_goal, goal_selection_strategy
        spaces = env.observation_space.spaces
        self.observations = {k: np.zeros((size, 1, *s.shape), np.float32) for k, s in spaces.items()}
        self.next_observations = {k: np.zeros((size, 1, *s.shape), np.float32) for k, s in spaces.items()}
        self.actions = np.zeros((size, 1, *env.action_space.shape), np.float32)
        self.rewards, self.dones, self.timeouts = (np.zeros((size, 1), np.float32) for _ in range(3))
        self.ep_start = np.zeros((size, 1), np.int64)
        self.ep_length = np.zeros((size, 1), np.int64)
        self._current_ep_start = np.zeros(1, np.int64)

    def add(self, obs, next_obs, action, reward, done, episode_end=False):
        for key in self.observations:
            self.observations[key][self.pos, 0], self.next_observations[key][self.pos, 0] = obs[key], next_obs[key]
        self.actions[self.pos, 0], self.rewards[self.pos, 0], self.dones[self.pos, 0] = action, reward, done
        self.ep_start[self.pos, 0] = self._current_ep_start[0]
        self.pos = (self.pos + 1) % self.buffer_size
        self.full = self.full or self.pos == 0
        if episode_end:
            start, end = int(self._current_ep_start[0]), self.pos if self.pos > self._current_ep_start[0] else self.pos + self.buffer_size
            rows = np.arange(start, end) % self.buffer_size
            self.ep_length[rows, 0] = end - start
            self._current_ep_start[0] = self.pos

    def sample_check(self):
        """SB3's HER buffer samples only rows of finished episodes: there must be some."""
        if not self.ep_length.any():
            raise RuntimeError("Unable to sample before the end of the first episode")
