"""The losses of SAC (Haarnoja et al. 2018a, 2018b) and CrossQ (Bhatt et al. 2024): pure functions of
(parameters, running statistics, batch, key, settings).

One critic loss and one actor loss serve both algorithms. CrossQ differs from SAC in two places, each
written once: its critics normalise their inputs with batch renormalisation (`Critics.batch_renorm`),
and it computes the next-state value with the online critics in one joint pass over (s, a) and (s', a')
instead of with target critics (`q_and_next_q`). `critic_loss` and `actor_loss` are SAC's form of the two (no
running statistics), as the loss tests pin them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from softac.networks import BatchRenorm, critics_apply, batch_renorm_critics_apply
from softac.policy import Policy


class Batch(NamedTuple):
    obs: jax.Array
    actions: jax.Array  # normalised to [-1, 1]
    rewards: jax.Array
    next_obs: jax.Array  # the true next observation, also at the end of an episode
    terminated: jax.Array  # 1.0 only for true terminal states: time-limit truncation still bootstraps
    steps: jax.Array  # rewards summed into `rewards` (n-step returns; 1 for one-step SAC)


@dataclass(frozen=True)
class Critics:
    """How the critic ensemble is evaluated (its settings; parameters and statistics are passed in)."""
    activation: str
    matmul_dtype: str = "float32"
    layer_norm: bool = False
    unroll: bool = False  # critic by critic (faster on CPU, see critics_apply) instead of vmap
    batch_renorm: BatchRenorm | None = None  # between layers (CrossQ)

    def q_values(self, critic: Any, stats: Any, obs: jax.Array, actions: jax.Array) -> jax.Array:
        """Q-values of every critic, shape [n_critics, batch] (with batch renormalisation: normalised with
        its running statistics)."""
        if self.batch_renorm is not None:
            return batch_renorm_critics_apply(critic, stats, obs, actions, self.activation, self.batch_renorm,
                                              False, matmul_dtype=self.matmul_dtype, unroll=self.unroll)[0]
        return critics_apply(critic, obs, actions, self.activation, self.matmul_dtype, self.layer_norm, self.unroll)

    def q_values_training(self, critic: Any, stats: Any, obs: jax.Array, actions: jax.Array,
                          renorm: jax.Array | bool) -> tuple[jax.Array, Any]:
        """Q-values normalised with this batch's statistics, and the updated running statistics."""
        return batch_renorm_critics_apply(critic, stats, obs, actions, self.activation, self.batch_renorm, True,
                                          renorm, self.matmul_dtype, self.unroll)


# ---- the critics' loss --------------------------------------------------------------------------

def q_and_next_q(critic: Any, critic_stats: Any, target_critic: Any, batch: Batch, next_actions: jax.Array,
                 critics: Critics, renorm: jax.Array | bool) -> tuple[jax.Array, jax.Array, Any]:
    """Q(s, a) of every critic, Q(s', a') of every critic the next-state value comes from, and the critics'
    new running statistics.

    SAC: the target critics give Q(s', a'). CrossQ (Bhatt et al. 2024, sec. 3) has none: the online
    critics see (s, a) and (s', a') in one batch, so that batch renormalisation normalises both with the
    same statistics (with separate passes the next pair is out of distribution for the normalisation);
    the target is held fixed by stop_gradient alone."""
    if critics.batch_renorm is None:
        q = critics.q_values(critic, critic_stats, batch.obs, batch.actions)
        return q, critics.q_values(target_critic, critic_stats, batch.next_obs, next_actions), critic_stats
    both, critic_stats = critics.q_values_training(critic, critic_stats, jnp.concatenate([batch.obs, batch.next_obs]),
                                                   jnp.concatenate([batch.actions, next_actions]), renorm)
    q, next_q = jnp.split(both, 2, axis=1)
    return q, next_q, critic_stats


def soft_bellman_error(q: jax.Array, next_q: jax.Array, next_log_prob: jax.Array, alpha: jax.Array, batch: Batch,
                       gamma: float, n_step: int) -> tuple[jax.Array, dict]:
    """0.5 * sum over critics of the mean squared error of q [n_critics, batch] to the soft target
    r + gamma^steps (1 - terminated) (next_q - alpha log pi(a'|s')), held fixed."""
    next_v = next_q - alpha * next_log_prob
    discount = gamma ** batch.steps if n_step > 1 else gamma
    target = jax.lax.stop_gradient(batch.rewards + discount * (1.0 - batch.terminated) * next_v)
    loss = 0.5 * jnp.sum(jnp.mean((q - target) ** 2, axis=1))
    return loss, {"critic_loss": loss, "q1_mean": jnp.mean(q[0]), "q2_mean": jnp.mean(q[min(1, q.shape[0] - 1)])}


def soft_q_loss(critic: Any, critic_stats: Any, target_critic: Any, actor: Any, actor_stats: Any, alpha: jax.Array,
                batch: Batch, key: jax.Array, policy: Policy, critics: Critics, gamma: float, n_step: int = 1,
                renorm: jax.Array | bool = False) -> tuple[jax.Array, tuple[dict, Any]]:
    """Soft Bellman error with the minimum over the next-state critics (clipped double Q, Fujimoto et al.
    2018); returns the loss and (metrics, the critics' new running statistics).

    Only `terminated` stops the bootstrap; a time-limit truncation still bootstraps. With n-step returns
    the buffer has summed `steps` discounted rewards (no entropy terms in between, as RLlib and SB3 do),
    so the bootstrap is discounted by gamma^steps (Sutton & Barto 2018, sec. 7.1). The next action is
    drawn with the actor's running statistics.
    """
    next_actions, next_log_prob = policy.sample(actor, actor_stats, batch.next_obs, key)
    q, next_q, critic_stats = q_and_next_q(critic, critic_stats, target_critic, batch, next_actions, critics, renorm)
    loss, metrics = soft_bellman_error(q, jnp.min(next_q, axis=0), next_log_prob, alpha, batch, gamma, n_step)
    return loss, (metrics, critic_stats)


def critic_loss(critic: Any, target_critic: Any, actor: Any, alpha: jax.Array, batch: Batch, key: jax.Array,
                policy: Policy, critics: Critics, gamma: float, n_step: int = 1) -> tuple[jax.Array, dict]:
    """`soft_q_loss` of SAC (target critics, no running statistics): the loss and its metrics."""
    loss, (metrics, _) = soft_q_loss(critic, (), target_critic, actor, (), alpha, batch, key, policy, critics, gamma,
                                     n_step)
    return loss, metrics


# ---- the actor's and the entropy coefficient's losses ---------------------------------------------

def policy_loss(actor: Any, actor_stats: Any, critic: Any, critic_stats: Any, alpha: jax.Array, obs: jax.Array,
                key: jax.Array, policy: Policy, critics: Critics,
                renorm: jax.Array | bool = False) -> tuple[jax.Array, tuple[jax.Array, Any]]:
    """Maximise E[min_i Q_i(s, a) - alpha log pi(a|s)] over reparameterised actions (Haarnoja et al.
    2018a, eq. 12). The actor runs in training mode (with batch renormalisation: the batch's statistics),
    the critics in evaluation mode (their running statistics), as CrossQ does. Returns the loss and (the
    actions' log-probabilities, which the alpha loss reuses; the actor's new running statistics)."""
    actions, log_prob, actor_stats = policy.sample_training(actor, actor_stats, obs, key, renorm)
    q = jnp.min(critics.q_values(critic, critic_stats, obs, actions), axis=0)
    return jnp.mean(alpha * log_prob - q), (log_prob, actor_stats)


def actor_loss(actor: Any, critic: Any, alpha: jax.Array, obs: jax.Array, key: jax.Array, policy: Policy,
               critics: Critics) -> tuple[jax.Array, jax.Array]:
    """`policy_loss` of SAC (no running statistics): the loss and the actions' log-probabilities."""
    loss, (log_prob, _) = policy_loss(actor, (), critic, (), alpha, obs, key, policy, critics)
    return loss, log_prob


def alpha_loss(log_alpha: jax.Array, log_prob: jax.Array, target_entropy: float) -> jax.Array:
    """Entropy coefficient, learned on log(alpha) so alpha stays positive (Haarnoja et al. 2018b, sec. 5):
    alpha grows while the policy's entropy -log_prob is below the target, and shrinks above it."""
    return -jnp.mean(log_alpha * jax.lax.stop_gradient(log_prob + target_entropy))
