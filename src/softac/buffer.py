"""A preallocated replay buffer: one NumPy array per field, no per-transition objects."""

from __future__ import annotations

import os

import numpy as np

from softac.errors import SoftacError


class BufferMemoryError(SoftacError):
    pass


def available_memory_bytes() -> int:
    """MemAvailable from /proc/meminfo, else physical memory, else a large number."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return 1 << 62


def _human(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"


class ReplayBuffer:
    """Transitions (obs, action, reward, next_obs, terminated), oldest overwritten first.

    `terminated` and truncation are kept apart by construction: only
    `terminated` is stored, because truncation must still bootstrap, and the
    stored next_obs is the true final observation, never the one after reset.
    """

    FIELDS = ("obs", "actions", "rewards", "next_obs", "terminated")

    def __init__(self, capacity: int, obs_dim: int, act_dim: int, memory_fraction: float = 0.8):
        self.capacity = int(capacity)
        self.obs_dim, self.act_dim = obs_dim, act_dim
        self.check_memory(self.capacity, obs_dim, act_dim, memory_fraction)
        self.obs = np.zeros((self.capacity, obs_dim), np.float32)
        self.next_obs = np.zeros((self.capacity, obs_dim), np.float32)
        self.actions = np.zeros((self.capacity, act_dim), np.float32)
        self.rewards = np.zeros((self.capacity,), np.float32)
        self.terminated = np.zeros((self.capacity,), np.float32)
        self.pos = 0
        self.size = 0

    @classmethod
    def check_memory(cls, capacity: int, obs_dim: int, act_dim: int, memory_fraction: float = 0.8) -> None:
        """Refuse, before allocating anything, a buffer the machine cannot hold."""
        need = capacity * cls.bytes_per_transition(obs_dim, act_dim)
        have = available_memory_bytes()
        if need > memory_fraction * have:
            raise BufferMemoryError(
                f"replay buffer of {capacity:,} transitions needs {_human(need)} but only "
                f"{_human(have)} is available; lower buffer_size (--set buffer_size=N)")

    @staticmethod
    def bytes_per_transition(obs_dim: int, act_dim: int) -> int:
        return 4 * (2 * obs_dim + act_dim + 2)

    def __len__(self) -> int:
        return self.size

    def add(self, obs: np.ndarray, actions: np.ndarray, rewards: np.ndarray,
            next_obs: np.ndarray, terminated: np.ndarray) -> None:
        """Add a batch of transitions (one row per vector env)."""
        n = len(rewards)
        idx = (self.pos + np.arange(n)) % self.capacity
        self.obs[idx] = obs
        self.actions[idx] = actions
        self.rewards[idx] = rewards
        self.next_obs[idx] = next_obs
        self.terminated[idx] = terminated
        self.pos = int((self.pos + n) % self.capacity)
        self.size = int(min(self.size + n, self.capacity))

    def sample(self, rng: np.random.Generator, batch_size: int, n_batches: int = 1) -> dict[str, np.ndarray]:
        """`n_batches` independent batches stacked as [n_batches, batch_size, ...]."""
        idx = rng.integers(0, self.size, size=(n_batches, batch_size))
        return {name: getattr(self, name)[idx] for name in self.FIELDS}

    def state_dict(self) -> dict[str, np.ndarray]:
        out = {name: getattr(self, name)[: self.size] for name in self.FIELDS}
        out["pos_size"] = np.array([self.pos, self.size], np.int64)
        return out

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        pos, size = (int(v) for v in state["pos_size"])
        if size > self.capacity:
            raise SoftacError(f"checkpoint buffer holds {size} transitions, more than buffer_size={self.capacity}")
        for name in self.FIELDS:
            getattr(self, name)[:size] = state[name]
        self.pos, self.size = pos, size
