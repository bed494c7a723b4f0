"""A replay buffer of device arrays (issue 67): pure functions on a `DeviceReplay` pytree, so that inserting a
vector step's transitions and drawing the gradient steps' batches run inside the same jitted `lax.scan` as the
envs and the update, with no trip to the host.

Rows are written N at a time (one per env) at a position that advances by N, over a capacity rounded down to
a multiple of N, so a write never wraps inside itself (`dynamic_update_slice`). Each row holds its observation
and its true next observation (an episode's last one too), the action in [-1, 1], the reward and the
termination flag: a truncated episode's last row is bootstrapped like any other. Batches are drawn uniformly
with replacement from the rows written, as the host's buffer draws them.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp


class DeviceReplay(NamedTuple):
    obs: jax.Array  # [capacity, obs_dim] float32
    actions: jax.Array  # [capacity, act_dim] float32, in [-1, 1]
    rewards: jax.Array  # [capacity] float32
    next_obs: jax.Array  # [capacity, obs_dim] float32
    terminated: jax.Array  # [capacity] float32: 1 only for a true terminal state
    position: jax.Array  # int32: the next row written
    size: jax.Array  # int32: rows held


ROWS = ("obs", "actions", "rewards", "next_obs", "terminated")  # DeviceReplay's per-row arrays


class Sampled(NamedTuple):
    """Batches drawn for `n` gradient steps: each field with a leading axis [n, batch_size]."""
    obs: jax.Array
    actions: jax.Array
    rewards: jax.Array
    next_obs: jax.Array
    terminated: jax.Array


def capacity_for(buffer_size: int, n_envs: int) -> int:
    """The rows a buffer of `buffer_size` holds when written `n_envs` at a time: a multiple of n_envs, at least one
    vector step's worth."""
    return max(n_envs, (int(buffer_size) // n_envs) * n_envs)


def bytes_per_row(obs_dim: int, act_dim: int) -> int:
    return 4 * (2 * obs_dim + act_dim + 2)


def empty(capacity: int, obs_dim: int, act_dim: int) -> DeviceReplay:
    f32 = jnp.float32
    return DeviceReplay(jnp.zeros((capacity, obs_dim), f32), jnp.zeros((capacity, act_dim), f32),
                        jnp.zeros(capacity, f32), jnp.zeros((capacity, obs_dim), f32), jnp.zeros(capacity, f32),
                        jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32))


def insert(replay: DeviceReplay, obs: jax.Array, actions: jax.Array, rewards: jax.Array, next_obs: jax.Array,
           terminated: jax.Array) -> DeviceReplay:
    """N rows (one vector step) written at the current position; the oldest overwritten once full."""
    n, capacity = obs.shape[0], replay.obs.shape[0]
    at = replay.position

    def put(column: jax.Array, rows: jax.Array) -> jax.Array:
        rows = rows.astype(column.dtype).reshape((n,) + column.shape[1:])
        return jax.lax.dynamic_update_slice_in_dim(column, rows, at, axis=0)

    return DeviceReplay(put(replay.obs, obs), put(replay.actions, actions), put(replay.rewards, rewards),
                        put(replay.next_obs, next_obs), put(replay.terminated, terminated),
                        (at + n) % capacity, jnp.minimum(replay.size + n, capacity))


def sample(replay: DeviceReplay, key: jax.Array, n: int, batch_size: int) -> Sampled:
    """`n` batches of `batch_size` rows drawn uniformly with replacement from the rows held (at least one)."""
    rows = jax.random.randint(key, (n, batch_size), 0, jnp.maximum(replay.size, 1))
    return Sampled(replay.obs[rows], replay.actions[rows], replay.rewards[rows], replay.next_obs[rows],
                   replay.terminated[rows])
