"""The policy's calls per env step, as `build` jits them. Each takes the encoder last (`()` for vector
observations): the policy reads `pixels.features_of(encoder, obs, state_dim, pixel_offset)`, `state_dim` and
`pixel_offset` bound when built."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from softac.learner.pixels import features_of
from softac.learner.policy import ActionScaler, Policy


def act(policy: Policy, scaler: ActionScaler, actor: Any, actor_stats: Any, obs: jax.Array,
        key: jax.Array, encoder: Any = (), state_dim: int = 0,
        pixel_offset: float = 0.0) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(action in [-1, 1], the same action in env bounds, next key): one call per env step."""
    key, sample_key = jax.random.split(key)
    action = policy.sample(actor, actor_stats, features_of(encoder, obs, state_dim, pixel_offset), sample_key)[0]
    return action, scaler.to_env(action, jnp), key


def act_with_noise(policy: Policy, scaler: ActionScaler, actor: Any, actor_stats: Any, obs: jax.Array,
                   noise: jax.Array, encoder: Any = (), state_dim: int = 0,
                   pixel_offset: float = 0.0) -> tuple[jax.Array, jax.Array]:
    """(action in [-1, 1], in env bounds) for given standard-normal noise (`Policy.with_noise`: coloured noise
    or gSDE's exploration matrices, softac.replay.exploration)."""
    action = policy.with_noise(actor, actor_stats, features_of(encoder, obs, state_dim, pixel_offset), noise)
    return action, scaler.to_env(action, jnp)


def act_deterministic(policy: Policy, actor: Any, actor_stats: Any, obs: jax.Array, encoder: Any = (),
                      state_dim: int = 0, pixel_offset: float = 0.0) -> jax.Array:
    """The mean action in [-1, 1]."""
    return policy.deterministic(actor, actor_stats, features_of(encoder, obs, state_dim, pixel_offset))
