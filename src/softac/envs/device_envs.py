"""Many envs stepped on the device, in pure JAX (issue 67): any env with MuJoCo Playground's and Brax's API
(`reset(key) -> state`, `step(state, action) -> state`, the state carrying `obs`, `reward` and `done`), `vmap`ped
over N copies and auto-reset inside the step, so that collection runs inside one jitted `lax.scan`.

The step keeps what a replay buffer needs at an episode's end: the true final observation (`next_obs`) of an
episode that ended, before the env's reset replaces it (Playground's Brax auto-reset wrapper drops it:
mujoco_playground #305, which FastTD3 patches), and terminations (the env's `done`) apart from truncations (the
episode length reached), so that a truncated episode's last transition is bootstrapped and a terminated one's is
not. An env's own `action_repeat` is applied inside the step, the rewards summed until the episode ends.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp


class EnvBatch(NamedTuple):
    """N envs between two steps: what the next step starts from (a pytree, carried through `lax.scan`)."""
    states: Any  # the env's state pytree with a leading axis of N
    obs: jax.Array  # [N, obs_dim] what the policy acts on next (a fresh episode's first observation after a reset)
    steps: jax.Array  # [N] int32: steps into each env's episode
    returns: jax.Array  # [N] float32: each episode's return so far
    key: jax.Array  # the key resets draw from


class EnvStep(NamedTuple):
    """One step of N envs: the transitions to store and the episodes that ended."""
    obs: jax.Array  # [N, obs_dim] the observations acted on
    actions: jax.Array  # [N, act_dim] the actions taken
    rewards: jax.Array  # [N] summed over the env's action repeat
    next_obs: jax.Array  # [N, obs_dim] the true next observation, also where the episode ended
    terminated: jax.Array  # [N] bool: the env's done (not bootstrapped)
    truncated: jax.Array  # [N] bool: the episode length reached without a termination (bootstrapped)
    episode_returns: jax.Array  # [N] the return of each episode that ended here (0 elsewhere)
    episode_lengths: jax.Array  # [N] int32: its length (0 where none ended)


def state_obs(obs: Any) -> jax.Array:
    """The policy's observation from an env's: a dict's `state` entry (Playground's locomotion envs), as a
    float32 vector per env."""
    if isinstance(obs, dict) or hasattr(obs, "keys"):
        obs = obs["state"]
    return jnp.asarray(obs, jnp.float32).reshape(obs.shape[0], -1)


class DeviceEnvs:
    """`n` copies of one env stepped together on the device: `reset` makes an `EnvBatch`, `step` advances it by
    one action each and resets the envs whose episodes ended; both pure, to be jitted or scanned by the caller."""

    def __init__(self, env: Any, n: int, episode_length: int, action_repeat: int = 1):
        if n < 1 or episode_length < 1 or action_repeat < 1:
            raise ValueError("n, episode_length and action_repeat must be >= 1")
        self.env, self.n = env, int(n)
        self.episode_length, self.action_repeat = int(episode_length), int(action_repeat)
        self._reset: Callable = jax.vmap(env.reset)
        self._step: Callable = jax.vmap(env.step)

    # equal for one env object at equal settings: a static argument of the jitted chunks, shared by the agents
    # (and runs) of a process that train on the same env
    def _identity(self) -> tuple:
        return (id(self.env), self.n, self.episode_length, self.action_repeat)

    def __hash__(self) -> int:
        return hash(self._identity())

    def __eq__(self, other: object) -> bool:
        return isinstance(other, DeviceEnvs) and other.env is self.env and other._identity() == self._identity()

    def reset(self, key: jax.Array) -> EnvBatch:
        key, reset_key = jax.random.split(key)
        states = self._reset(jax.random.split(reset_key, self.n))
        zeros = jnp.zeros(self.n, jnp.float32)
        return EnvBatch(states, state_obs(states.obs), jnp.zeros(self.n, jnp.int32), zeros, key)

    def step(self, batch: EnvBatch, actions: jax.Array) -> tuple[EnvBatch, EnvStep]:
        states, rewards, terminated = self._repeat(batch.states, actions)
        next_obs = state_obs(states.obs)
        steps = batch.steps + 1
        truncated = (steps >= self.episode_length) & ~terminated
        ended = terminated | truncated
        returns = batch.returns + rewards

        key, reset_key = jax.random.split(batch.key)
        # a reset only in steps where an episode ended (a vmapped select would pay for N resets every step)
        states = jax.lax.cond(ended.any(), lambda: self._reset_ended(states, ended, reset_key), lambda: states)
        step = EnvStep(batch.obs, actions, rewards, next_obs, terminated, truncated,
                       jnp.where(ended, returns, 0.0), jnp.where(ended, steps, 0))
        after = EnvBatch(states, jnp.where(ended[:, None], state_obs(states.obs), next_obs),
                         jnp.where(ended, 0, steps), jnp.where(ended, 0.0, returns), key)
        return after, step

    def _repeat(self, states: Any, actions: jax.Array) -> tuple[Any, jax.Array, jax.Array]:
        """The env's step `action_repeat` times with one action, rewards summed; an env whose episode ends inside
        the repeat stays at its last state."""
        if self.action_repeat == 1:
            stepped = self._step(states, actions)
            return stepped, jnp.asarray(stepped.reward, jnp.float32), jnp.asarray(stepped.done) > 0

        # a scan, not a Python loop: one env step in the program however many repeats (as Brax's EpisodeWrapper),
        # so that an MJX env's step is traced and compiled once, not action_repeat times (issue 64)
        def repeat(carry, _):
            states, rewards, done = carry
            stepped = self._step(states, actions)
            rewards = rewards + jnp.where(done, 0.0, jnp.asarray(stepped.reward, jnp.float32))
            return (_where(done, states, stepped), rewards, done | (jnp.asarray(stepped.done) > 0)), None

        start = (states, jnp.zeros(self.n, jnp.float32), jnp.zeros(self.n, bool))
        (states, rewards, done), _ = jax.lax.scan(repeat, start, None, length=self.action_repeat)
        return states, rewards, done

    def _reset_ended(self, states: Any, ended: jax.Array, key: jax.Array) -> Any:
        fresh = self._reset(jax.random.split(key, self.n))
        return _where(ended, fresh, states)


def _where(mask: jax.Array, new: Any, old: Any) -> Any:
    """Each leaf of `new` where `mask` (one flag per env, the leaves' first axis), else `old`'s."""
    return jax.tree_util.tree_map(
        lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - 1)), a, b), new, old)
