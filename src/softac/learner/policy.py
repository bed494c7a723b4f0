"""The policy: a tanh-squashed Gaussian over actions in [-1, 1]^|A| (Haarnoja et al. 2018a, appendix C),
and the scaling of those actions to the env's bounds.

Log-probabilities are densities in the normalised space, as in Stable-Baselines3, so the default entropy
target -|A| means the same thing for every env. Every function takes its arguments in one order: the
network's parameters, their running statistics (batch renormalisation; `()` without it), the inputs, the key.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from softac.learner.networks import Network, network_kind
from softac.learner.networks.layers import BatchRenorm, dense

LOG_2 = float(np.log(2.0))
LOG_SQRT_2PI = float(0.5 * np.log(2.0 * np.pi))


def bound_log_std(raw: jax.Array, lo: float, hi: float, mode: str) -> jax.Array:
    if mode == "tanh":  # CleanRL: squash smoothly into [lo, hi]
        return lo + 0.5 * (hi - lo) * (jnp.tanh(raw) + 1.0)
    if mode == "softplus":  # Brax's NormalTanhDistribution: std = softplus(raw) + min_std, no upper bound
        return jnp.log(jax.nn.softplus(raw) + math.exp(lo))
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


# gSDE (Raffin et al. 2022, "Smooth Exploration for Robotic Reinforcement Learning"), as SB3's SAC `use_sde`:
# the noise is a linear function of the features the mean's layer reads, u = mean + f(s) @ W, with the
# exploration matrix W ~ N(0, std^2) drawn every so often rather than each step, so that exploration is smooth
# along a trajectory and consistent in a state. For a fixed state u is Gaussian with variance
# (f(s)^2) @ std^2 per action dim. The features learn through the noise and the variance too, as SB3's SAC
# has them (its actor passes learn_features=True), and the mean is clipped to [-2, 2] (SB3's clip_mean: tanh
# saturates beyond it).
SDE_CLIP_MEAN = 2.0
SDE_EPSILON = 1e-6  # added to the variance, as SB3's StateDependentNoiseDistribution


def sde_log_std(features: jax.Array, log_std_matrix: jax.Array) -> jax.Array:
    """Per action dim, log of the state-dependent std sqrt(f(s)^2 @ exp(log_std)^2 + eps)."""
    return 0.5 * jnp.log(jnp.square(features) @ jnp.exp(2.0 * log_std_matrix) + SDE_EPSILON)


def sde_noise(features: jax.Array, log_std_matrix: jax.Array, weights: jax.Array) -> jax.Array:
    """f(s) @ W with W = exp(log_std) * weights: one matrix `weights` (features x act) for a batch, or one per
    row (batch x features x act); `weights` standard normal."""
    matrix = jnp.exp(log_std_matrix) * weights
    return features @ matrix if weights.ndim == 2 else jnp.einsum("bf,bfa->ba", features, matrix)


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
    network: str = "mlp"  # a config's network (mlp, simba); with batch_renorm an MLP is a batch_renorm_mlp
    sde: bool = False  # gSDE: the actor outputs the mean; its head holds the exploration matrix's log std
    layer_norm: str = ""  # "before" or "after" each hidden activation: its LayerNorm (MLP actors; FastSAC, Brax)

    @property
    def kind(self) -> Network:
        """The network kind (softac.learner.networks.NETWORKS) of the actor."""
        return network_kind(self.network, self.batch_renorm is not None)

    def _features(self, actor: Any, stats: Any, obs: jax.Array, train: bool = False,
                  renorm: jax.Array | bool = False) -> tuple[jax.Array, Any]:
        """The input of the actor's output layer, and the running statistics (new ones in training mode)."""
        return self.kind.features(actor, stats, obs, self.activation, self.matmul_dtype, self.layer_norm, None,
                                  self.batch_renorm, train, renorm)

    def _outputs(self, actor: Any, stats: Any, obs: jax.Array, train: bool = False,
                 renorm: jax.Array | bool = False) -> tuple[jax.Array, jax.Array, Any, jax.Array]:
        """(mean, log std per action dim, running statistics, features)."""
        features, stats = self._features(actor, stats, obs, train, renorm)
        head = self.kind.head(actor)
        out = dense(features, head, self.matmul_dtype)
        if self.sde:
            mean = jnp.clip(out, -SDE_CLIP_MEAN, SDE_CLIP_MEAN)
            return mean, sde_log_std(features, head["sde_log_std"]), stats, features
        mean, raw_log_std = jnp.split(out, 2, axis=-1)
        log_std = bound_log_std(raw_log_std, self.log_std_min, self.log_std_max, self.log_std_mode)
        return mean, log_std, stats, features

    def _sample(self, actor: Any, outputs: tuple, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        mean, log_std, _, features = outputs
        if not self.sde:
            return squashed_sample(mean, log_std, key)
        # one exploration matrix for the whole batch, fresh for each call (SB3 draws one per gradient step)
        log_std_matrix = self.kind.head(actor)["sde_log_std"]
        u = mean + sde_noise(features, log_std_matrix, jax.random.normal(key, log_std_matrix.shape))
        return jnp.tanh(u), squashed_gaussian_log_prob(u, mean, log_std)

    def mean_and_log_std(self, actor: Any, stats: Any, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The Gaussian's mean and log std per action dim before tanh (with gSDE: the state-dependent std)."""
        return self._outputs(actor, stats, obs)[:2]

    def sample(self, actor: Any, stats: Any, obs: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        """A reparameterised action in [-1, 1] and its log-probability."""
        return self._sample(actor, self._outputs(actor, stats, obs), key)

    def sample_training(self, actor: Any, stats: Any, obs: jax.Array, key: jax.Array,
                        renorm: jax.Array | bool = False) -> tuple[jax.Array, jax.Array, Any]:
        """`sample` in training mode: normalised with the batch's statistics, which also update the running
        ones (returned third). Without batch renormalisation, `sample` and `stats` unchanged."""
        outputs = self._outputs(actor, stats, obs, train=True, renorm=renorm)
        return (*self._sample(actor, outputs, key), outputs[2])

    def with_noise(self, actor: Any, stats: Any, obs: jax.Array, noise: jax.Array) -> jax.Array:
        """The action in [-1, 1] for given standard-normal noise: tanh(mean + std * noise), noise (batch x
        act) white or coloured (softac.replay.exploration); with gSDE tanh(mean + f(s) @ (std * noise)), noise the
        exploration matrices' weights (batch x features x act)."""
        mean, log_std, _, features = self._outputs(actor, stats, obs)
        if self.sde:
            return jnp.tanh(mean + sde_noise(features, self.kind.head(actor)["sde_log_std"], noise))
        return jnp.tanh(mean + jnp.exp(log_std) * noise)

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
