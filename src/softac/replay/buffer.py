"""A preallocated replay buffer: one NumPy array per field, no per-transition objects."""

from __future__ import annotations

import numpy as np

from softac.errors import SoftacError
from softac.base.memory import memory_shortfall, transition_bytes


class BufferMemoryError(SoftacError):
    pass


def check_buffer_memory(capacity: int, bytes_each: float, memory_fraction: float = 0.8) -> None:
    """Refuse, before allocating anything, a buffer the machine cannot hold."""
    short = memory_shortfall(capacity * bytes_each, memory_fraction)
    if short is not None:
        raise BufferMemoryError(f"replay buffer of {capacity:,} transitions needs {short}; lower buffer_size "
                                "(--set buffer_size=N)")


class RingBuffer:
    """Row bookkeeping every replay buffer shares (the plain, obs-once, HER and frame buffers): the oldest rows are
    overwritten first."""

    capacity: int
    pos: int
    size: int
    n_envs: int
    n_step: int
    gamma: float

    def _rows(self, n: int) -> np.ndarray:
        return (self.pos + np.arange(n)) % self.capacity

    def _advance(self, n: int) -> None:
        self.pos = int((self.pos + n) % self.capacity)
        self.size = int(min(self.size + n, self.capacity))

    def __len__(self) -> int:
        return self.size

    def _ends_episode(self, rows: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _can_enter(self, rows: np.ndarray) -> np.ndarray:
        return np.ones(rows.shape, bool)

    def _n_step_rows(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(last row, discounted reward sum, rewards summed) of the n-step returns from rows `idx`.

        From each sampled row the walk follows its env's next rows (n_envs apart, also across the ring's wrap),
        summing gamma^k r_(t+k) for up to n_step rewards. It stops after a row that ended its episode
        (terminated or truncated: that row's `terminated` and true final observation then decide the
        bootstrap) and before a row not written yet, so the last row is always a whole transition.
        """
        k = np.arange(self.n_step)
        rows = (idx[..., None] + k * self.n_envs) % self.capacity  # [..., n_step]: this env's next rows
        ahead = (self.pos - 1 - idx) % self.capacity  # rows written after each sampled row
        enters = k * self.n_envs <= ahead[..., None]
        enters[..., 1:] &= ~self._ends_episode(rows[..., :-1]) & self._can_enter(rows[..., 1:])
        taken = np.logical_and.accumulate(enters, axis=-1)
        steps = taken.sum(axis=-1)
        last = np.take_along_axis(rows, steps[..., None] - 1, axis=-1)[..., 0]
        discounts = (self.gamma ** k).astype(np.float32)
        rewards = np.sum(self.rewards[rows] * np.where(taken, discounts, np.float32(0.0)), axis=-1)
        return last, rewards, steps.astype(np.float32)

    def _returns_of(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self.n_step == 1:
            return idx, self.rewards[idx], np.ones(idx.shape, np.float32)
        return self._n_step_rows(idx)


class ReplayBuffer(RingBuffer):
    """Transitions (obs, action, reward, next_obs, terminated, done), oldest overwritten first.

    `terminated` and truncation are kept apart by construction: only `terminated` stops the bootstrap,
    because truncation must still bootstrap, and the stored next_obs is the true final observation, never
    the one after reset. `done` (terminated or truncated) marks episode ends for n-step returns.
    Rows are written one vector step at a time, env 0 first, so an env's next transition is n_envs rows on.
    """

    FIELDS = ("obs", "actions", "rewards", "next_obs", "terminated", "done")

    def __init__(self, capacity: int, obs_dim: int, act_dim: int, memory_fraction: float = 0.8,
                 n_envs: int = 1, n_step: int = 1, gamma: float = 0.99):
        self.capacity = int(capacity)
        self.obs_dim, self.act_dim = obs_dim, act_dim
        self.n_envs, self.n_step, self.gamma = n_envs, n_step, gamma
        check_buffer_memory(self.capacity, self.bytes_per_transition(obs_dim, act_dim), memory_fraction)
        self.obs = np.zeros((self.capacity, obs_dim), np.float32)
        self.next_obs = np.zeros((self.capacity, obs_dim), np.float32)
        self.actions = np.zeros((self.capacity, act_dim), np.float32)
        self.rewards = np.zeros((self.capacity,), np.float32)
        self.terminated = np.zeros((self.capacity,), np.float32)
        self.done = np.zeros((self.capacity,), bool)
        self.pos = 0
        self.size = 0

    @staticmethod
    def bytes_per_transition(obs_dim: int, act_dim: int) -> int:
        return transition_bytes(obs_dim, act_dim)

    def add(self, obs: np.ndarray, actions: np.ndarray, rewards: np.ndarray,
            next_obs: np.ndarray, terminated: np.ndarray, done: np.ndarray | None = None) -> None:
        """Add a batch of transitions (one row per vector env); `done` defaults to `terminated`."""
        idx = self._rows(len(rewards))
        self.obs[idx] = obs
        self.actions[idx] = actions
        self.rewards[idx] = rewards
        self.next_obs[idx] = next_obs
        self.terminated[idx] = terminated
        self.done[idx] = np.asarray(terminated if done is None else done, bool)
        self._advance(len(rewards))

    def _ends_episode(self, rows: np.ndarray) -> np.ndarray:
        return self.done[rows]

    def sample(self, rng: np.random.Generator, batch_size: int, n_batches: int = 1) -> dict[str, np.ndarray]:
        """`n_batches` independent batches stacked as [n_batches, batch_size, ...]."""
        idx = rng.integers(0, self.size, size=(n_batches, batch_size))
        last, rewards, steps = self._returns_of(idx)
        return {"obs": self.obs[idx], "actions": self.actions[idx], "rewards": rewards,
                "next_obs": self.next_obs[last], "terminated": self.terminated[last], "steps": steps}

    def state_dict(self) -> dict[str, np.ndarray]:
        out = {name: getattr(self, name)[: self.size] for name in self.FIELDS}
        out["pos_size"] = np.array([self.pos, self.size], np.int64)
        return out

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        pos, size = (int(v) for v in state["pos_size"])
        if size > self.capacity:
            raise SoftacError(f"checkpoint buffer holds {size} transitions, more than buffer_size={self.capacity}")
        for name in self.FIELDS:
            if name == "done" and name not in state:  # checkpoints from before n-step returns (always n_step 1)
                self.done[:size] = state["terminated"] > 0
                continue
            getattr(self, name)[:size] = state[name]
        self.pos, self.size = pos, size


class ObsOnceReplayBuffer(RingBuffer):
    """The same transitions as ReplayBuffer, storing each observation once (`buffer_obs_once`).

    Row i holds obs_t of one env; that env's next observation is the row written one vector step
    later, i + n_envs, which `add` fills at once (so every valid row can be rebuilt). Where an
    episode ended, the true final observation goes to a side ring of final observations instead.
    Rows whose data was overwritten early (the oldest n_envs rows of a full buffer, or rows whose
    final observation left the side ring) are marked invalid and never sampled.
    """

    FIELDS = ReplayBuffer.FIELDS

    def __init__(self, capacity: int, obs_dim: int, act_dim: int, n_envs: int, memory_fraction: float = 0.8,
                 n_step: int = 1, gamma: float = 0.99):
        self.capacity, self.obs_dim, self.act_dim, self.n_envs = int(capacity), obs_dim, act_dim, n_envs
        self.n_step, self.gamma = n_step, gamma
        self.final_capacity = self.final_ring_size(self.capacity, n_envs)
        check_buffer_memory(self.capacity, self.bytes_per_transition(obs_dim, act_dim, self.capacity, n_envs),
                            memory_fraction)
        self.obs = np.zeros((self.capacity, obs_dim), np.float32)
        self.actions = np.zeros((self.capacity, act_dim), np.float32)
        self.rewards = np.zeros((self.capacity,), np.float32)
        self.terminated = np.zeros((self.capacity,), np.float32)
        self.final_slot = np.full(self.capacity, -1, np.int32)  # -1: the next obs is row i + n_envs
        self.valid = np.zeros(self.capacity, bool)
        self.final_obs = np.zeros((self.final_capacity, obs_dim), np.float32)
        self.final_owner = np.full(self.final_capacity, -1, np.int64)
        self.final_pos = 0
        self.pos = 0
        self.size = 0

    @staticmethod
    def final_ring_size(capacity: int, n_envs: int) -> int:
        return min(capacity, max(capacity // 8, 4 * n_envs))  # room for episodes averaging >= 8 steps

    @classmethod
    def bytes_per_transition(cls, obs_dim: int, act_dim: int, capacity: int, n_envs: int) -> float:
        row = 4 * (obs_dim + act_dim + 2) + 4 + 1  # + final-slot index and valid flag
        return row + cls.final_ring_size(capacity, n_envs) * 4 * obs_dim / capacity  # + a share of the side ring

    def add(self, obs: np.ndarray, actions: np.ndarray, rewards: np.ndarray, next_obs: np.ndarray,
            terminated: np.ndarray, done: np.ndarray) -> None:
        n = len(rewards)
        idx = self._rows(n)
        self.obs[idx] = obs
        self.actions[idx] = actions
        self.rewards[idx] = rewards
        self.terminated[idx] = terminated
        self.final_slot[idx] = -1
        self.valid[idx] = True
        ended = np.asarray(done, bool)
        for j in np.flatnonzero(ended):
            slot = self.final_pos
            self.final_pos = (slot + 1) % self.final_capacity
            owner = self.final_owner[slot]
            if owner >= 0 and self.final_slot[owner] == slot:  # its final obs is about to be overwritten
                self.valid[owner] = False
                self.final_slot[owner] = -1
            self.final_obs[slot] = next_obs[j]
            self.final_owner[slot] = idx[j]
            self.final_slot[idx[j]] = slot
        successors = (idx[~ended] + n) % self.capacity
        self.obs[successors] = next_obs[~ended]
        self.valid[successors] = False  # those rows (if filled: the oldest) now hold a newer obs
        self._advance(n)

    def next_obs_of(self, idx: np.ndarray) -> np.ndarray:
        slot = self.final_slot[idx]
        out = self.obs[(idx + self.n_envs) % self.capacity]
        ended = slot >= 0
        out[ended] = self.final_obs[slot[ended]]
        return out

    def sample(self, rng: np.random.Generator, batch_size: int, n_batches: int = 1) -> dict[str, np.ndarray]:
        if not self.valid[: self.size].any():
            raise SoftacError("replay buffer holds no complete transition to sample yet")
        idx = rng.integers(0, self.size, size=(n_batches, batch_size))
        bad = ~self.valid[idx]
        while bad.any():  # invalid rows are few (at most n_envs plus rows that lost their final obs)
            idx[bad] = rng.integers(0, self.size, size=int(bad.sum()))
            bad = ~self.valid[idx]
        last, rewards, steps = self._returns_of(idx)
        return {"obs": self.obs[idx], "actions": self.actions[idx], "rewards": rewards,
                "next_obs": self.next_obs_of(last), "terminated": self.terminated[last], "steps": steps}

    # an n-step walk enters only valid rows; in a valid row, an episode end is exactly a final-obs slot
    def _ends_episode(self, rows: np.ndarray) -> np.ndarray:
        return self.final_slot[rows] >= 0

    def _can_enter(self, rows: np.ndarray) -> np.ndarray:
        return self.valid[rows]

    def state_dict(self) -> dict[str, np.ndarray]:
        written = min(self.size + self.n_envs, self.capacity)  # successors are written ahead of size
        return {"obs": self.obs[:written], "actions": self.actions[: self.size], "rewards": self.rewards[: self.size],
                "terminated": self.terminated[: self.size], "final_slot": self.final_slot[: self.size],
                "valid": self.valid[: self.size], "final_obs": self.final_obs, "final_owner": self.final_owner,
                "pos_size": np.array([self.pos, self.size, self.final_pos], np.int64)}

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        pos, size, final_pos = (int(v) for v in state["pos_size"])
        if size > self.capacity or len(state["final_obs"]) != self.final_capacity:
            raise SoftacError("checkpoint buffer does not match buffer_size/n_envs of this config")
        self.obs[: len(state["obs"])] = state["obs"]
        for name in ("actions", "rewards", "terminated", "final_slot", "valid"):
            getattr(self, name)[:size] = state[name]
        self.final_obs[:] = state["final_obs"]
        self.final_owner[:] = state["final_owner"]
        self.pos, self.size, self.final_pos = pos, size, final_pos
