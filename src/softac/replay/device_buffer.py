"""A replay buffer of device arrays (issue 67): pure functions on a `DeviceReplay` pytree, so that inserting a
vector step's transitions and drawing the gradient steps' batches run inside the same jitted `lax.scan` as the
envs and the update, with no trip to the host.

Rows are written N at a time (one per env) at a position that advances by N, over a capacity rounded down to
a multiple of N, so a write never wraps inside itself (`dynamic_update_slice`). Each row holds its observation
and its true next observation (an episode's last one too), the action in [-1, 1], the reward and the
termination flag (a truncated episode's last row is bootstrapped like any other) and whether the row ended its
episode. Batches are drawn uniformly with replacement from the rows written, as the host's buffer draws them;
with n_step > 1 each row's return sums the rewards of its env's next rows (N apart) up to n_step, stopping after
an episode's end and before a row not written yet, as the host's RingBuffer walks them.

With `buffer_obs_once` each observation is stored once, as the host's ObsOnceReplayBuffer stores it: row i's
next observation is row i + N (the same env one vector step later, written at once), and where an episode
ended, the true final observation sits in a side ring of final observations (`final_obs`, `final_slot`). Rows
whose next observation is gone (the oldest N of a full buffer, whose successors hold the newest observations;
rows whose final observation left the side ring) are marked invalid, and a draw that lands on one is drawn
again. The plain layout keeps the obs-once arrays empty (shape 0), the obs-once one `next_obs`: shapes are
static, so each program is one layout's.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from softac.replay.buffer import ObsOnceReplayBuffer

final_ring_size = ObsOnceReplayBuffer.final_ring_size  # the side ring: the host's size, the same rows held


class DeviceReplay(NamedTuple):
    obs: jax.Array  # [capacity, obs_dim] float32
    actions: jax.Array  # [capacity, act_dim] float32, in [-1, 1]
    rewards: jax.Array  # [capacity] float32
    next_obs: jax.Array  # [capacity, obs_dim] float32 ([0, obs_dim] with obs once)
    terminated: jax.Array  # [capacity] float32: 1 only for a true terminal state
    done: jax.Array  # [capacity] bool: the row ended its episode, terminated or truncated ([0] with obs once, whose
    # final_slot marks the ends)
    position: jax.Array  # int32: the next row written
    size: jax.Array  # int32: rows held
    # obs once (else shape 0): where row i's episode ended, its final observation's slot in final_obs (-1: the
    # next observation is row i + N); whether the row can be drawn; the side ring and each slot's row; its position
    final_slot: jax.Array  # [capacity] int32
    valid: jax.Array  # [capacity] bool
    final_obs: jax.Array  # [final ring, obs_dim] float32
    final_owner: jax.Array  # [final ring] int32
    final_pos: jax.Array  # int32


ROWS = ("obs", "actions", "rewards", "next_obs", "terminated", "done")  # the plain layout's per-row arrays
OBS_ONCE_ROWS = ("actions", "rewards", "terminated", "final_slot", "valid")  # obs once: per row held; obs beyond
OBS_ONCE_RING = ("final_obs", "final_owner")  # ... and the side ring, whole


def obs_once(replay: DeviceReplay) -> bool:
    """Whether `replay` stores each observation once (static: its shapes say)."""
    return replay.next_obs.shape[0] == 0 and replay.obs.shape[0] > 0


class Sampled(NamedTuple):
    """Batches drawn for `n` gradient steps: each field with a leading axis [n, batch_size]; `rewards` the n-step
    discounted sums and `steps` how many rewards each holds (1 with n_step 1)."""
    obs: jax.Array
    actions: jax.Array
    rewards: jax.Array
    next_obs: jax.Array
    terminated: jax.Array
    steps: jax.Array


def capacity_for(buffer_size: int, n_envs: int) -> int:
    """The rows a buffer of `buffer_size` holds when written `n_envs` at a time: a multiple of n_envs, at least one
    vector step's worth."""
    return max(n_envs, (int(buffer_size) // n_envs) * n_envs)


def bytes_per_row(obs_dim: int, act_dim: int, once: bool = False, capacity: int = 1, n_envs: int = 1) -> float:
    """Device memory per transition: both observations, or (obs once) one, the row's slot and flag, and its share
    of the side ring."""
    if not once:
        return 4 * (2 * obs_dim + act_dim + 2) + 1  # + the episode-end flag
    return 4 * (obs_dim + act_dim + 2) + 4 + 1 + final_ring_size(capacity, n_envs) * 4 * (obs_dim + 1) / capacity


def empty(capacity: int, obs_dim: int, act_dim: int, once: bool = False, n_envs: int = 1) -> DeviceReplay:
    f32, i32 = jnp.float32, jnp.int32
    ring = final_ring_size(capacity, n_envs) if once else 0
    rows = capacity if once else 0
    return DeviceReplay(jnp.zeros((capacity, obs_dim), f32), jnp.zeros((capacity, act_dim), f32),
                        jnp.zeros(capacity, f32), jnp.zeros((0 if once else capacity, obs_dim), f32),
                        jnp.zeros(capacity, f32), jnp.zeros(0 if once else capacity, bool),
                        jnp.zeros((), i32), jnp.zeros((), i32),
                        jnp.full(rows, -1, i32), jnp.zeros(rows, bool), jnp.zeros((ring, obs_dim), f32),
                        jnp.full(ring, -1, i32), jnp.zeros((), i32))


def insert(replay: DeviceReplay, obs: jax.Array, actions: jax.Array, rewards: jax.Array, next_obs: jax.Array,
           terminated: jax.Array, done: jax.Array | None = None) -> DeviceReplay:
    """N rows (one vector step) written at the current position; the oldest overwritten once full. `done`: the
    envs whose episode ended here (terminated or truncated), which obs once needs."""
    n, capacity = obs.shape[0], replay.obs.shape[0]
    at = replay.position

    def put(column: jax.Array, rows: jax.Array) -> jax.Array:
        rows = rows.astype(column.dtype).reshape((n,) + column.shape[1:])
        return jax.lax.dynamic_update_slice_in_dim(column, rows, at, axis=0)

    held = (at + n) % capacity, jnp.minimum(replay.size + n, capacity)
    if not obs_once(replay):
        ended = terminated > 0 if done is None else done
        return replay._replace(obs=put(replay.obs, obs), actions=put(replay.actions, actions),
                               rewards=put(replay.rewards, rewards), next_obs=put(replay.next_obs, next_obs),
                               terminated=put(replay.terminated, terminated), done=put(replay.done, ended),
                               position=held[0], size=held[1])
    rows = at + jnp.arange(n, dtype=jnp.int32)
    ring = replay.final_obs.shape[0]
    final_slot = put(replay.final_slot, jnp.full(n, -1, jnp.int32))
    valid = put(replay.valid, jnp.ones(n, bool))
    # the ended envs' final observations into the side ring, in env order; a slot's previous row loses its own
    ended = done.astype(bool)
    slots = (replay.final_pos + jnp.cumsum(ended) - 1) % ring
    owners = replay.final_owner[slots]
    lost = ended & (owners >= 0) & (final_slot[jnp.maximum(owners, 0)] == slots)
    lost_rows = jnp.where(lost, owners, capacity)  # out of range: dropped
    valid = valid.at[lost_rows].set(False, mode="drop")
    final_slot = final_slot.at[lost_rows].set(-1, mode="drop")
    into = jnp.where(ended, slots, ring)
    final_obs = replay.final_obs.at[into].set(next_obs.astype(jnp.float32), mode="drop")
    final_owner = replay.final_owner.at[into].set(rows, mode="drop")
    final_slot = final_slot.at[jnp.where(ended, rows, capacity)].set(slots.astype(jnp.int32), mode="drop")
    # the others' next observations are their successors' observations, written now (a full buffer's oldest
    # rows after this write then hold newer observations than their own: not drawn until rewritten)
    successors = jnp.where(ended, capacity, (rows + n) % capacity)
    stored = put(replay.obs, obs).at[successors].set(next_obs.astype(jnp.float32), mode="drop")
    valid = valid.at[successors].set(False, mode="drop")
    return replay._replace(obs=stored, actions=put(replay.actions, actions), rewards=put(replay.rewards, rewards),
                           terminated=put(replay.terminated, terminated), position=held[0], size=held[1],
                           final_slot=final_slot, valid=valid, final_obs=final_obs, final_owner=final_owner,
                           final_pos=(replay.final_pos + jnp.sum(ended, dtype=jnp.int32)) % ring)


def n_step_rows(replay: DeviceReplay, rows: jax.Array, n_envs: int, n_step: int,
                gamma: float) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(last row, discounted reward sum, rewards summed) of the n-step returns from `rows`, as the host's
    RingBuffer._n_step_rows: each row's env's next rows, n_envs apart round the ring, entered while written and
    while the row before did not end its episode (obs once: and while valid)."""
    capacity = replay.rewards.shape[0]
    k = jnp.arange(n_step)
    walk = (rows[..., None] + k * n_envs) % capacity  # [..., n_step]
    ahead = (replay.position - 1 - rows) % capacity  # rows written after each sampled row
    enters = k * n_envs <= ahead[..., None]
    once = obs_once(replay)
    ends = replay.final_slot[walk] >= 0 if once else replay.done[walk]
    follow = ~ends[..., :-1] & (replay.valid[walk[..., 1:]] if once else True)
    enters = jnp.concatenate([enters[..., :1], enters[..., 1:] & follow], axis=-1)
    taken = jnp.cumprod(enters, axis=-1).astype(bool)
    steps = jnp.sum(taken, axis=-1)
    last = jnp.take_along_axis(walk, steps[..., None] - 1, axis=-1)[..., 0]
    discounts = (gamma ** k).astype(jnp.float32)
    rewards = jnp.sum(replay.rewards[walk] * jnp.where(taken, discounts, 0.0), axis=-1)
    return last, rewards, steps.astype(jnp.float32)


def sample(replay: DeviceReplay, key: jax.Array, n: int, batch_size: int, n_envs: int = 1, n_step: int = 1,
           gamma: float = 0.99) -> Sampled:
    """`n` batches of `batch_size` rows drawn uniformly with replacement from the rows held (at least one); with obs
    once, from the valid ones (a draw on an invalid row drawn again, as the host's buffer does) and each next
    observation rebuilt from the row `n_envs` on or the side ring; with n_step > 1, n-step returns (n_step_rows)."""
    held = jnp.maximum(replay.size, 1)
    rows = jax.random.randint(key, (n, batch_size), 0, held)
    if not obs_once(replay):
        last, rewards, steps = _returns(replay, rows, n_envs, n_step, gamma)
        return Sampled(replay.obs[rows], replay.actions[rows], rewards, replay.next_obs[last],
                       replay.terminated[last], steps)

    def redraw(carry):
        rows, key = carry
        key, draw = jax.random.split(key)
        return jnp.where(replay.valid[rows], rows, jax.random.randint(draw, rows.shape, 0, held)), key

    # the newest N rows are always valid, so the loop ends; invalid rows are few (N and the ring's losses)
    rows, _ = jax.lax.while_loop(lambda carry: ~jnp.all(replay.valid[carry[0]]), redraw,
                                 (rows, jax.random.fold_in(key, 1)))
    last, rewards, steps = _returns(replay, rows, n_envs, n_step, gamma)
    slot = replay.final_slot[last]
    successor = replay.obs[(last + n_envs) % replay.obs.shape[0]]
    next_obs = jnp.where((slot >= 0)[..., None], replay.final_obs[jnp.maximum(slot, 0)], successor)
    return Sampled(replay.obs[rows], replay.actions[rows], rewards, next_obs, replay.terminated[last], steps)


def _returns(replay: DeviceReplay, rows: jax.Array, n_envs: int, n_step: int,
             gamma: float) -> tuple[jax.Array, jax.Array, jax.Array]:
    if n_step == 1:  # one-step runs compute what they always did
        return rows, replay.rewards[rows], jnp.ones(rows.shape, jnp.float32)
    return n_step_rows(replay, rows, n_envs, n_step, gamma)
