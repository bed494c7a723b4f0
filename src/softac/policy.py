"""The policy: a tanh-squashed Gaussian over actions in [-1, 1]^|A| (Haarnoja et al. 2018a, appendix C),
and the scaling of those actions to the env's bounds.

Log-probabilities are densities in the normalised space, as in Stable-Baselines3, so the default entropy
target -|A| means the same thing for every env. Every function takes its arguments in one order: the
network's parameters, their running statistics (batch renormalisation; `()` without it), the inputs, the key.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from softac.networks import BatchRenorm, batch_renorm_mlp, mlp, simba

LOG_2 = float(np.log(2.0))
LOG_SQRT_2PI = float(0.5 * np.log(2.0 * np.pi))


def bound_log_std(raw: jax.Array, lo: float, hi: float, mode: str) -> jax.Array:
    if mode == "tanh":  # CleanRL: squash smoothly into [lo, hi]
        return lo + 0.5 * (hi - lo) * (jnp.tanh(raw) + 1.0)
    return jnp.clip(raw, lo, hi)  # SB3


def log_one_minus_tanh_sq(u: jax.Array) -> jax.Array:
    """log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u)), exact and stable for large |u|.

    The naive form log(1 - tanh(u)^2 + eps) saturates once tanh(u) rounds to 1
    (SAC paper appendix C; the form used by TF-Probability's TanhBijector).
    """
    return 2.0 * (LOG_2 - u - jax.nn.softplus(-2.0 * u))


def squashed_gaussian_log_prob(u: jax.Array, mean: jax.Array, log_std: jax.Array) -> jax.Array:
    """log density of a = tanh(u), u ~ N(mean, exp(log_std)^2), summed over action dims."""
    z = (u - mean) * jnp.exp(-log_std)
    gaussian = -0.5 * z**2 - log_std - LOG_SQRT_2PI
    return jnp.sum(gaussian - log_one_minus_tanh_sq(u), axis=-1)


def squashed_sample(mean: jax.Array, log_std: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array]:
    """A reparameterised action tanh(mean + std * noise) and its log-probability."""
    u = mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape)
    return jnp.tanh(u), squashed_gaussian_log_prob(u, mean, log_std)


@dataclass(frozen=True)
class Policy:
    """The actor's settings; its parameters and running statistics are passed to each method. Acting uses
    the running statistics; only the actor's own update normalises with the batch's (`sample_training`)."""
    activation: str
    log_std_min: float
    log_std_max: float
    log_std_mode: str
    matmul_dtype: str = "float32"
    batch_renorm: BatchRenorm | None = None  # between layers (CrossQ)
    network: str = "mlp"  # or simba (networks.simba)

    def _outputs(self, actor: Any, stats: Any, obs: jax.Array, train: bool = False,
                 renorm: jax.Array | bool = False) -> tuple[jax.Array, jax.Array, Any]:
        if self.network == "simba":
            out = simba(actor, obs, self.activation, self.matmul_dtype)
        elif self.batch_renorm is None:
            out = mlp(actor, obs, self.activation, self.matmul_dtype)
        else:
            out, stats = batch_renorm_mlp(actor, stats, obs, self.activation, self.batch_renorm, train, renorm,
                                          self.matmul_dtype)
        mean, raw_log_std = jnp.split(out, 2, axis=-1)
        return mean, bound_log_std(raw_log_std, self.log_std_min, self.log_std_max, self.log_std_mode), stats

    def mean_and_log_std(self, actor: Any, stats: Any, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        return self._outputs(actor, stats, obs)[:2]

    def sample(self, actor: Any, stats: Any, obs: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        """A reparameterised action in [-1, 1] and its log-probability."""
        return squashed_sample(*self.mean_and_log_std(actor, stats, obs), key)

    def sample_training(self, actor: Any, stats: Any, obs: jax.Array, key: jax.Array,
                        renorm: jax.Array | bool = False) -> tuple[jax.Array, jax.Array, Any]:
        """`sample` in training mode: normalised with the batch's statistics, which also update the running
        ones (returned third). Without batch renormalisation, `sample` and `stats` unchanged."""
        mean, log_std, stats = self._outputs(actor, stats, obs, train=True, renorm=renorm)
        return (*squashed_sample(mean, log_std, key), stats)

    def deterministic(self, actor: Any, stats: Any, obs: jax.Array) -> jax.Array:
        return jnp.tanh(self.mean_and_log_std(actor, stats, obs)[0])


class ActionScaler:
    """Maps [-1, 1] to the env's [low, high] and back, per dimension."""

    def __init__(self, low: np.ndarray, high: np.ndarray):
        self.low = np.asarray(low, np.float32)
        self.high = np.asarray(high, np.float32)
        self.scale = (self.high - self.low) / 2.0
        self.bias = (self.high + self.low) / 2.0

    def to_env(self, normalised: Any, xp: Any = np) -> Any:
        """`xp` is np on the host, jnp inside jitted code."""
        return xp.clip(self.bias + self.scale * normalised, self.low, self.high)

    def to_normalised(self, env_action: np.ndarray) -> np.ndarray:
        return np.clip((np.asarray(env_action, np.float32) - self.bias) / self.scale, -1.0, 1.0)
