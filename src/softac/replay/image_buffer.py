"""A replay buffer for image observations that stores each camera frame once (issue 44).

An image observation is a stack of the last `k` frames ([k, h, w, c], oldest first). Stored as it comes,
a transition would hold 2k frames; here each transition holds the indices of its observation's k frames
in one ring of frames, and the next observation is the same indices shifted by one with the newest frame
appended. A step stores one frame (the next observation's newest); an episode's first observation stores
its k frames (k - 1 of them at most once more than needed). 100k transitions of 84x84 RGB frames take
~2.4 GB instead of ~12.7 GB (k = 3, two observations per transition).

Frames carry absolute numbers (how many frames were written before them), so a transition whose frames the
ring has overwritten is recognised and never sampled. The frame ring holds an eighth more frames than the
transitions' ring has rows, plus k per env, room for episodes of 8k steps and longer on average before a
transition loses a frame.
"""

from __future__ import annotations

import numpy as np

from softac.replay.buffer import RingBuffer, check_buffer_memory
from softac.base.memory import human_bytes
from softac.errors import SoftacError


class FrameReplayBuffer(RingBuffer):
    """Transitions (obs, action, reward, next_obs, terminated, done) of frame stacks [k, h, w, c] (uint8), each
    frame stored once; the same sampling, n-step returns and checkpoint interface as `ReplayBuffer`."""

    def __init__(self, capacity: int, obs_shape: tuple[int, int, int, int], act_dim: int, n_envs: int = 1,
                 memory_fraction: float = 0.8, n_step: int = 1, gamma: float = 0.99):
        if len(obs_shape) != 4:
            raise SoftacError(f"image replay holds frame stacks [k, h, w, c], not observations of shape {obs_shape}")
        frame_stack = int(obs_shape[0])
        self.capacity, self.act_dim, self.n_envs = int(capacity), act_dim, n_envs
        self.n_step, self.gamma = n_step, gamma
        self.k = frame_stack
        self.obs_shape = tuple(int(n) for n in obs_shape)
        self.frame_shape = self.obs_shape[1:]
        self.frame_capacity = self.frame_ring_size(self.capacity, frame_stack, n_envs)
        check_buffer_memory(self.capacity, self.bytes_per_transition(self.obs_shape, act_dim, self.capacity, n_envs),
                            memory_fraction)
        self.frames = np.zeros((self.frame_capacity, *self.frame_shape), np.uint8)
        self.frames_written = 0
        # each observation as the absolute numbers of its frames, oldest first
        self.obs_frames = np.zeros((self.capacity, frame_stack), np.int64)
        self.next_obs_frames = np.zeros((self.capacity, frame_stack), np.int64)
        self.actions = np.zeros((self.capacity, act_dim), np.float32)
        self.rewards = np.zeros(self.capacity, np.float32)
        self.terminated = np.zeros(self.capacity, np.float32)
        self.done = np.zeros(self.capacity, bool)
        # each env's last next observation, as frame numbers (-1: none yet): the next step's obs is usually it
        self.last_next = np.full((n_envs, frame_stack), -1, np.int64)
        self.pos = 0
        self.size = 0

    @staticmethod
    def frame_ring_size(capacity: int, frame_stack: int, n_envs: int) -> int:
        return capacity + capacity // 8 + frame_stack * n_envs

    @classmethod
    def bytes_per_transition(cls, obs_shape: tuple[int, int, int, int], act_dim: int, capacity: int,
                             n_envs: int) -> float:
        frame_stack, height, width, channels = obs_shape
        row = 8 * 2 * frame_stack + 4 * (act_dim + 2) + 1
        return row + height * width * channels * cls.frame_ring_size(capacity, frame_stack, n_envs) / capacity

    def describe_memory(self) -> str:
        per = self.bytes_per_transition(self.obs_shape, self.act_dim, self.capacity, self.n_envs)
        return f"{self.capacity:,} transitions x {human_bytes(per)} = {human_bytes(per * self.capacity)}"

    # ---- writing ---------------------------------------------------------------------------------------

    def _store(self, frames: np.ndarray) -> np.ndarray:
        """Write frames [m, h, w, c] and return their numbers."""
        numbers = self.frames_written + np.arange(len(frames))
        self.frames[numbers % self.frame_capacity] = frames
        self.frames_written += len(frames)
        return numbers

    def _alive(self, numbers: np.ndarray) -> np.ndarray:
        return (numbers >= 0) & (numbers >= self.frames_written - self.frame_capacity)

    def _obs_numbers(self, env: int, obs: np.ndarray) -> np.ndarray:
        """The frame numbers of `obs`: the env's last next observation when it is that (the episode goes on),
        else its k frames written now."""
        last = self.last_next[env]
        if np.all(self._alive(last)) and np.array_equal(self._stacks(last), obs):
            return last.copy()
        return self._store(obs)

    def add(self, obs: np.ndarray, actions: np.ndarray, rewards: np.ndarray, next_obs: np.ndarray,
            terminated: np.ndarray, done: np.ndarray | None = None) -> None:
        """Add one vector step's transitions (one row per env, env 0 first); `done` defaults to `terminated`."""
        n = len(rewards)
        if n != self.n_envs:
            raise SoftacError(f"image replay buffer made for {self.n_envs} envs got {n} transitions")
        obs, next_obs = np.asarray(obs, np.uint8), np.asarray(next_obs, np.uint8)
        idx = self._rows(n)
        for j in range(n):
            numbers = self._obs_numbers(j, obs[j])
            next_frames = next_obs[j]
            if np.array_equal(next_frames[:-1], obs[j][1:]):  # the stack moved on by one frame
                next_numbers = np.append(numbers[1:], self._store(next_frames[-1:]))
            else:  # an env that stacks its own way: the next observation's frames written whole
                next_numbers = self._store(next_frames)
            self.obs_frames[idx[j]] = numbers
            self.next_obs_frames[idx[j]] = next_numbers
            self.last_next[j] = next_numbers
        self.actions[idx] = actions
        self.rewards[idx] = rewards
        self.terminated[idx] = terminated
        self.done[idx] = np.asarray(terminated if done is None else done, bool)
        self._advance(n)

    # ---- sampling ----------------------------------------------------------------------------------------

    def _ends_episode(self, rows: np.ndarray) -> np.ndarray:
        return self.done[rows]

    def _valid(self, idx: np.ndarray) -> np.ndarray:
        """Rows whose frames are all still in the ring (a row's next rows were written later: theirs are too)."""
        return self._alive(self.obs_frames[idx, 0]) & self._alive(np.min(self.next_obs_frames[idx], axis=-1))

    def _stacks(self, numbers: np.ndarray) -> np.ndarray:
        """Observations [..., k, h, w, c] of frame numbers [..., k]: whole frames gathered, nothing transposed."""
        return self.frames[numbers % self.frame_capacity]

    def sample(self, rng: np.random.Generator, batch_size: int, n_batches: int = 1) -> dict[str, np.ndarray]:
        """`n_batches` independent batches stacked as [n_batches, batch_size, ...]; observations uint8."""
        # the newest row's frames are the newest: when it has lost them, so has every row (a frame ring too small)
        if self.size == 0 or not self._valid(np.array([(self.pos - 1) % self.capacity]))[0]:
            raise SoftacError("replay buffer holds no complete transition to sample yet")
        idx = rng.integers(0, self.size, size=(n_batches, batch_size))
        bad = ~self._valid(idx)
        while bad.any():  # rows that lost a frame to the ring are few (episodes shorter than 8k steps)
            idx[bad] = rng.integers(0, self.size, size=int(bad.sum()))
            bad = ~self._valid(idx)
        last, rewards, steps = self._returns_of(idx)
        return {"obs": self._stacks(self.obs_frames[idx]), "actions": self.actions[idx], "rewards": rewards,
                "next_obs": self._stacks(self.next_obs_frames[last]), "terminated": self.terminated[last],
                "steps": steps}

    # ---- checkpoints ---------------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, np.ndarray]:
        written = min(self.frames_written, self.frame_capacity)
        return {"frames": self.frames[:written], "obs_frames": self.obs_frames[: self.size],
                "next_obs_frames": self.next_obs_frames[: self.size], "actions": self.actions[: self.size],
                "rewards": self.rewards[: self.size], "terminated": self.terminated[: self.size],
                "done": self.done[: self.size], "last_next": self.last_next,
                "pos_size": np.array([self.pos, self.size, self.frames_written], np.int64)}

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        pos, size, frames_written = (int(v) for v in state["pos_size"])
        frames = state["frames"]
        if size > self.capacity or frames.shape[1:] != self.frame_shape or len(frames) > self.frame_capacity \
                or state["last_next"].shape != self.last_next.shape:
            raise SoftacError("checkpoint buffer does not match buffer_size, n_envs or the image shape of this config")
        self.frames[: len(frames)] = frames
        for name in ("obs_frames", "next_obs_frames", "actions", "rewards", "terminated", "done"):
            getattr(self, name)[:size] = state[name]
        self.last_next[:] = state["last_next"]
        self.pos, self.size, self.frames_written = pos, size, frames_written
