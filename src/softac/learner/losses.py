"""The losses of SAC (Haarnoja et al. 2018a, 2018b) and its family: pure functions of (parameters, running
statistics, batch, key, settings).

One critic loss and one actor loss serve every variant; each differs from SAC where its paper does, written
once and chosen by `Critics`: CrossQ (Bhatt et al. 2024) normalises the critics' inputs with batch
renormalisation and computes the next-state value in one joint pass over (s, a) and (s', a') (`q_and_next_q`),
with or without target critics (CrossQ+WN, Palenicek et al. 2025, keeps them); TQC (Kuznetsov et al. 2020)
has quantile critics, a truncated pool of next-state atoms and the quantile Huber loss
(`truncated_target_atoms`, `quantile_huber_error`); categorical critics (C51, Bellemare et al. 2017, as XQC
and FastTD3 run it; two-hot and HL-Gauss targets, Farebrother et al. 2024) predict a distribution over a fixed
support and learn it by cross-entropy (`categorical_error`); DroQ (Hiraoka et al. 2022) drops critic units in
every pass (`dropout_keys`); SimBa (Lee et al. 2024) changes only the networks. `critic_loss` and `actor_loss`
are SAC's form of the two (no running statistics), as the loss tests pin them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from softac.learner.networks import Network, critics_apply, network_kind
from softac.learner.networks.layers import BatchRenorm
from softac.learner.policy import Policy


class Batch(NamedTuple):
    obs: jax.Array
    actions: jax.Array  # normalised to [-1, 1]
    rewards: jax.Array
    next_obs: jax.Array  # the true next observation, also at the end of an episode
    terminated: jax.Array  # 1.0 only for true terminal states: time-limit truncation still bootstraps
    steps: jax.Array  # rewards summed into `rewards` (n-step returns; 1 for one-step SAC)


@dataclass(frozen=True)
class Critics:
    """How the critic ensemble is evaluated and what its next-state value is (its settings; parameters and
    statistics are passed in)."""
    activation: str
    matmul_dtype: str = "float32"
    layer_norm: str = ""  # "before" or "after" each hidden activation: its LayerNorm (MLP critics)
    unroll: bool = False  # critic by critic (faster on CPU, see critics_apply) instead of vmap
    batch_renorm: BatchRenorm | None = None  # between layers (CrossQ)
    network: str = "mlp"  # a config's network (mlp, simba); with batch_renorm an MLP is a batch_renorm_mlp
    dropout: float = 0.0  # DroQ: hidden units dropped in every critic pass
    n_quantiles: int = 0  # TQC: quantiles per critic; 0 = one Q-value each (SAC)
    drop_per_critic: int = 0  # TQC: the largest target atoms dropped, per critic
    n_atoms: int = 0  # categorical critics: logits over the atoms of `support`; 0 = none
    v_min: float = -5.0  # the support's first and last atom
    v_max: float = 5.0
    categorical_target: str = "c51"  # c51, two_hot or hl_gauss (categorical_target_distribution)
    hl_gauss_sigma: float = 0.75  # hl_gauss: the Gaussian's standard deviation, in atom spacings
    # Polyak-averaged target critics give the next-state value (off: the online ones); None: SAC's yes, CrossQ's no
    targets: bool | None = None
    target_q: str = "min"  # min: every critic toward the lowest next-state critic; each: each toward its own;
    # subset: toward the lowest of `target_q_subset` next-state critics drawn for the update (REDQ, RLPD)
    target_q_subset: int = 2
    actor_q: str = "min"  # min: the actor climbs the lowest critic; mean: the critics' mean

    @property
    def has_targets(self) -> bool:
        return self.batch_renorm is None if self.targets is None else self.targets

    @property
    def kind(self) -> Network:
        """The network kind (softac.learner.networks.NETWORKS) of the critics."""
        return network_kind(self.network, self.batch_renorm is not None)

    @property
    def quantiles(self) -> bool:
        return self.n_quantiles > 0

    @property
    def categorical(self) -> bool:
        return self.n_atoms > 0

    @property
    def support(self) -> jax.Array:
        """The categorical critics' atoms, evenly spaced from v_min to v_max."""
        return jnp.linspace(self.v_min, self.v_max, self.n_atoms, dtype=jnp.float32)

    def values(self, q: jax.Array) -> jax.Array:
        """Each critic's Q-value per row [n_critics, batch] from its outputs: the categorical distribution's
        mean, the quantiles' mean (TQC), or the output itself."""
        if self.categorical:
            return jax.nn.softmax(q, axis=-1) @ self.support
        return jnp.mean(q, axis=-1) if self.quantiles else q

    def q_values(self, critic: Any, stats: Any, obs: jax.Array, actions: jax.Array,
                 key: jax.Array | None = None) -> jax.Array:
        """Q-values of every critic, shape [n_critics, batch] (TQC: [n_critics, batch, n_quantiles]); with
        batch renormalisation normalised with its running statistics; with dropout, drawn from `key`."""
        return critics_apply(critic, obs, actions, self.activation, self.matmul_dtype, self.layer_norm, self.unroll,
                             self.network, self.dropout, key, self.quantiles or self.categorical, stats,
                             self.batch_renorm)[0]

    def q_values_training(self, critic: Any, stats: Any, obs: jax.Array, actions: jax.Array,
                          renorm: jax.Array | bool) -> tuple[jax.Array, Any]:
        """Q-values normalised with this batch's statistics, and the updated running statistics."""
        return critics_apply(critic, obs, actions, self.activation, self.matmul_dtype, self.layer_norm, self.unroll,
                             self.network, quantiles=self.quantiles or self.categorical, stats=stats,
                             batch_renorm=self.batch_renorm, train=True, renorm=renorm)

    def for_actor(self, q: jax.Array) -> jax.Array:
        """The value the actor climbs, per row: the smallest critic's Q (clipped double Q; of categorical
        critics, of their distributions' means, as XQC), or with actor_q=mean the critics' mean (FastSAC, REDQ),
        or with TQC the mean of every critic's quantiles (Kuznetsov et al. 2020, eq. 9: no truncation for the
        actor)."""
        if self.n_quantiles:
            return jnp.mean(q, axis=(0, 2))
        values = self.values(q)
        return jnp.mean(values, axis=0) if self.actor_q == "mean" else jnp.min(values, axis=0)

    def target_subset(self, key: jax.Array, n_critics: int) -> jax.Array | None:
        """With target_q=subset, the `target_q_subset` critics drawn from `key` for one update's targets, one draw
        for the whole batch (REDQ's in-target minimisation, Chen et al. 2021: a large ensemble without the minimum
        over all of it turning pessimistic; RLPD draws 2 of 10 per update); else None (every critic)."""
        if self.target_q != "subset":
            return None
        return jax.random.permutation(key, n_critics)[: self.target_q_subset]

    def next_value(self, next_q: jax.Array) -> jax.Array:
        """The next-state Q the critics learn toward: the lowest critic's per row [batch] (clipped double Q,
        Fujimoto et al. 2018; with target_q=subset, of the drawn critics `next_q` holds), or with target_q=each
        every critic's own [n_critics, batch] (FastSAC)."""
        return next_q if self.target_q == "each" else jnp.min(next_q, axis=0)


def dropout_keys(key: jax.Array, critics: Critics) -> tuple[jax.Array | None, jax.Array | None]:
    """Two keys for the critics' dropout (the online and the next-state pass), none without dropout: the
    policy's key stays as it was, so configs without dropout draw the numbers they always drew."""
    if critics.dropout <= 0:
        return None, None
    return tuple(jax.random.split(jax.random.fold_in(key, 0xD70), 2))


# ---- the critics' loss --------------------------------------------------------------------------

def q_and_next_q(critic: Any, critic_stats: Any, target_critic: Any, batch: Batch, next_actions: jax.Array,
                 critics: Critics, renorm: jax.Array | bool, target_stats: Any = (),
                 key: jax.Array | None = None, target_batch: Batch | None = None,
                 drawn: jax.Array | None = None) -> tuple[jax.Array, jax.Array, Any]:
    """Q(s, a) of every critic, Q(s', a') of every critic the next-state value comes from, and the critics'
    new running statistics.

    SAC: the target critics give Q(s', a') (without targets, the online critics; the loss holds the target
    fixed either way). CrossQ (Bhatt et al. 2024, sec. 3): the critics see (s, a) and (s', a') in one batch,
    so that batch renormalisation normalises both with the same statistics (with separate passes the next
    pair is out of distribution for the normalisation); with target critics (CrossQ+WN, Palenicek et al.
    2025) the target critics make the same joint pass in training mode, with their own running statistics
    for the renormalisation, and Q(s', a') is taken from their half. `target_batch`: the observations as the
    target critics read them (image features through a target encoder), else `batch`'s. `drawn` (target_q=subset):
    the critics Q(s', a') comes from; only those run the next-state pass where it is a pass of its own."""
    target_batch = batch if target_batch is None else target_batch
    online_key, next_key = dropout_keys(key, critics) if key is not None else (None, None)
    if critics.batch_renorm is None:
        q = critics.q_values(critic, critic_stats, batch.obs, batch.actions, online_key)
        source, next_obs = (target_critic, target_batch.next_obs) if critics.has_targets else (critic, batch.next_obs)
        if drawn is not None:  # REDQ's M of N: the others' next-state values are never used
            source = jax.tree_util.tree_map(lambda p: p[drawn], source)
        return q, critics.q_values(source, critic_stats, next_obs, next_actions, next_key), critic_stats
    obs = jnp.concatenate([batch.obs, batch.next_obs])
    actions = jnp.concatenate([batch.actions, next_actions])
    both, critic_stats = critics.q_values_training(critic, critic_stats, obs, actions, renorm)
    q, next_q = jnp.split(both, 2, axis=1)
    if critics.has_targets:
        target_obs = jnp.concatenate([target_batch.obs, target_batch.next_obs])
        next_q = jnp.split(critics.q_values_training(target_critic, target_stats, target_obs, actions, renorm)[0], 2,
                           axis=1)[1]
    return q, (next_q if drawn is None else next_q[drawn]), critic_stats


def soft_bellman_error(q: jax.Array, next_q: jax.Array, next_log_prob: jax.Array, alpha: jax.Array, batch: Batch,
                       gamma: float, n_step: int) -> tuple[jax.Array, dict]:
    """0.5 * sum over critics of the mean squared error of q [n_critics, batch] to the soft target
    r + gamma^steps (1 - terminated) (next_q - alpha log pi(a'|s')), held fixed; next_q [batch] is every
    critic's target, [n_critics, batch] one per critic."""
    next_v = next_q - alpha * next_log_prob
    target = jax.lax.stop_gradient(batch.rewards + discount(batch, gamma, n_step) * (1.0 - batch.terminated) * next_v)
    loss = 0.5 * jnp.sum(jnp.mean((q - target) ** 2, axis=1))
    return loss, {"critic_loss": loss, "q1_mean": jnp.mean(q[0]), "q2_mean": jnp.mean(q[min(1, q.shape[0] - 1)])}


def discount(batch: Batch, gamma: float, n_step: int) -> jax.Array | float:
    return gamma ** batch.steps if n_step > 1 else gamma


def truncated_target_atoms(next_q: jax.Array, drop_per_critic: int) -> tuple[jax.Array, jax.Array]:
    """TQC's next-state atoms (Kuznetsov et al. 2020, sec. 3.2): every critic's quantiles [n, batch, M] pooled per
    row [batch, n * M], and a mask of the atoms kept: all but the n * drop_per_critic largest. The loss does not
    depend on the atoms' order, so they are not sorted: finding the few largest (lax.top_k) costs a tenth of
    sorting the pool on a CPU (0.2 against 2.1 ms for 256 rows of 50 atoms)."""
    n, rows, m = next_q.shape
    pooled = jnp.transpose(next_q, (1, 0, 2)).reshape(rows, n * m)
    keep = jnp.ones_like(pooled)
    if drop_per_critic:
        _, largest = jax.lax.top_k(pooled, n * drop_per_critic)
        keep = keep.at[jnp.arange(rows)[:, None], largest].set(0.0)
    return pooled, keep


def quantile_huber_error(q: jax.Array, next_atoms: jax.Array, keep: jax.Array, next_log_prob: jax.Array,
                         alpha: jax.Array, batch: Batch, gamma: float, n_step: int) -> tuple[jax.Array, dict]:
    """TQC's critic loss: each critic's M quantiles [n, batch, M] (at tau_i = (i + 1/2) / M) regressed on every
    kept soft target atom z_j = r + gamma^steps (1 - terminated) (atom_j - alpha log pi(a'|s')), held fixed, with
    the quantile Huber loss |tau_i - 1{z_j < q_i}| * Huber_1(z_j - q_i); the mean over rows, quantiles and kept
    atoms, summed over critics (as SBX's TQC sums its two critics' losses)."""
    target = jax.lax.stop_gradient(
        batch.rewards[:, None] + (discount(batch, gamma, n_step) * (1.0 - batch.terminated))[..., None]
        * (next_atoms - alpha * next_log_prob[:, None]))
    m = q.shape[-1]
    taus = (jnp.arange(m, dtype=jnp.float32) + 0.5) / m
    delta = target[None, :, None, :] - q[..., None]  # [n, batch, M, atoms]
    abs_delta = jnp.abs(delta)
    huber = jnp.where(abs_delta > 1.0, abs_delta - 0.5, 0.5 * delta**2)
    per_atom = jnp.abs(taus[:, None] - (delta < 0.0)) * huber * keep[None, :, None, :]
    loss = jnp.sum(per_atom) / (q.shape[1] * m * jnp.sum(keep[0]))
    return loss, {"critic_loss": loss, "q1_mean": jnp.mean(q[0]), "q2_mean": jnp.mean(q[min(1, q.shape[0] - 1)])}


# ---- categorical critics ----------------------------------------------------------------------------

def lowest_mean_distribution(next_probs: jax.Array, support: jax.Array) -> jax.Array:
    """Clipped double Q on distributions: per row, the whole distribution [batch, atoms] of the next-state critic
    whose mean is lowest (XQC's and FlashSAC's choice; every online critic learns toward that one)."""
    lowest = jnp.argmin(next_probs @ support, axis=0)  # [batch]
    return jnp.take_along_axis(next_probs, lowest[None, :, None], axis=0)[0]


def target_distributions(next_probs: jax.Array, critics: Critics) -> jax.Array:
    """The next-state distributions the targets are made from: the lowest-mean one [batch, atoms] (target_q=min),
    or every critic's own [n_critics, batch, atoms] (target_q=each: FastSAC's critics, each toward its own
    target critic's projection)."""
    return next_probs if critics.target_q == "each" else lowest_mean_distribution(next_probs, critics.support)


def project_onto_support(atoms: jax.Array, probs: jax.Array, support: jax.Array) -> jax.Array:
    """C51's projection (Bellemare et al. 2017, alg. 1): each atom's probability [batch, n] split between the two
    atoms of `support` [K] around it, in proportion to its nearness; atoms beyond the support land on its ends.
    The split is the triangle kernel max(0, 1 - |a - z_i| / dz), which is C51's floor/ceil rule written once for
    every atom (an atom on a support point gives it all its mass), so each row's mass is kept."""
    spacing = support[1] - support[0]
    atoms = jnp.clip(atoms, support[0], support[-1])
    nearness = jnp.maximum(1.0 - jnp.abs(atoms[:, None, :] - support[None, :, None]) / spacing, 0.0)  # [batch, K, n]
    return jnp.einsum("bkn,bn->bk", nearness, probs)


def two_hot(values: jax.Array, support: jax.Array) -> jax.Array:
    """Each scalar [batch] as a distribution on `support`: its mass on the two atoms around it, in proportion to
    its nearness (the projection of a single atom); beyond the support, on its end."""
    return project_onto_support(values[:, None], jnp.ones_like(values)[:, None], support)


def hl_gauss(values: jax.Array, support: jax.Array, sigma: float) -> jax.Array:
    """HL-Gauss (Imani & White 2018; Farebrother et al. 2024): each scalar [batch] as the mass a normal
    N(value, sigma^2) puts on each atom's bin (the support's atoms at the bins' centres), renormalised to the
    support's range so that a value near an end keeps a whole distribution."""
    half = 0.5 * (support[1] - support[0])
    edges = jnp.concatenate([support - half, support[-1:] + half])
    cdf = jax.scipy.special.erf((edges[None, :] - values[:, None]) / (jnp.sqrt(2.0) * sigma))
    mass = cdf[:, 1:] - cdf[:, :-1]
    return mass / (cdf[:, -1:] - cdf[:, :1])


def categorical_target_distribution(next_probs: jax.Array, next_log_prob: jax.Array, alpha: jax.Array,
                                    batch: Batch, gamma: float, n_step: int, critics: Critics) -> jax.Array:
    """The soft target as a distribution on the support [batch, atoms] (target_q=each: one per critic,
    [n_critics, batch, atoms]), from the next-state distribution p (`target_distributions`): `c51` moves each
    atom z_j to r + gamma^steps (1 - terminated) (z_j - alpha log pi(a'|s')) and projects them back with their
    probabilities (the entropy term shifts every atom, as XQC, FastTD3 and FastSAC's C51 critics do); `two_hot`
    and `hl_gauss` take the scalar soft target r + gamma^steps (1 - terminated) (E_p[z] - alpha log pi) and
    spread it on the support."""
    support = critics.support
    bootstrap = discount(batch, gamma, n_step) * (1.0 - batch.terminated)

    def from_distribution(chosen: jax.Array) -> jax.Array:
        if critics.categorical_target == "c51":
            atoms = batch.rewards[:, None] + bootstrap[..., None] * (support[None, :] - alpha * next_log_prob[:, None])
            return project_onto_support(atoms, chosen, support)
        value = batch.rewards + bootstrap * (chosen @ support - alpha * next_log_prob)
        if critics.categorical_target == "two_hot":
            return two_hot(value, support)
        return hl_gauss(value, support, critics.hl_gauss_sigma * (support[1] - support[0]))

    chosen = target_distributions(next_probs, critics)
    return jax.vmap(from_distribution)(chosen) if critics.target_q == "each" else from_distribution(chosen)


def categorical_error(logits: jax.Array, next_logits: jax.Array, next_log_prob: jax.Array, alpha: jax.Array,
                      batch: Batch, gamma: float, n_step: int, critics: Critics) -> tuple[jax.Array, dict]:
    """The categorical critics' loss: the cross-entropy -sum_i p_i log softmax(logits)_i of each critic's
    predicted distribution [n, batch, atoms] to the target distribution p (held fixed), the mean over rows,
    summed over critics (as XQC's loss); Q-values in the metrics are the distributions' means."""
    target = jax.lax.stop_gradient(categorical_target_distribution(
        jax.nn.softmax(next_logits, axis=-1), next_log_prob, alpha, batch, gamma, n_step, critics))
    per_critic = target if target.ndim == 3 else target[None]  # target_q=each: one target per critic
    cross_entropy = -jnp.sum(per_critic * jax.nn.log_softmax(logits, axis=-1), axis=-1)  # [n, batch]
    loss = jnp.sum(jnp.mean(cross_entropy, axis=1))
    q = critics.values(logits)
    return loss, {"critic_loss": loss, "q1_mean": jnp.mean(q[0]), "q2_mean": jnp.mean(q[min(1, q.shape[0] - 1)])}


def soft_q_loss(critic: Any, critic_stats: Any, target_critic: Any, actor: Any, actor_stats: Any, alpha: jax.Array,
                batch: Batch, key: jax.Array, policy: Policy, critics: Critics, gamma: float, n_step: int = 1,
                renorm: jax.Array | bool = False, target_stats: Any = (),
                target_batch: Batch | None = None) -> tuple[jax.Array, tuple[dict, Any]]:
    """Soft Bellman error with the minimum over the next-state critics (clipped double Q, Fujimoto et al.
    2018; target_q=each: each critic's own), with TQC quantile critics the quantile Huber loss to the truncated
    atoms, with categorical critics the cross-entropy to the lowest-mean (or each critic's own) next
    distribution's soft target; returns the loss and
    (metrics, the critics' new running statistics).

    Only `terminated` stops the bootstrap; a time-limit truncation still bootstraps. With n-step returns
    the buffer has summed `steps` discounted rewards (no entropy terms in between, as RLlib and SB3 do),
    so the bootstrap is discounted by gamma^steps (Sutton & Barto 2018, sec. 7.1). The next action is
    drawn with the actor's running statistics. `target_batch`: the observations as the target critics read
    them, where they differ from `batch`'s (a target encoder's features).
    """
    next_actions, next_log_prob = policy.sample(actor, actor_stats, batch.next_obs, key)
    n_critics = jax.tree_util.tree_leaves(critic)[0].shape[0]
    drawn = critics.target_subset(jax.random.fold_in(key, 0x5E7), n_critics)  # None but with target_q=subset
    q, next_q, critic_stats = q_and_next_q(critic, critic_stats, target_critic, batch, next_actions, critics, renorm,
                                           target_stats, key, target_batch, drawn)
    if critics.n_quantiles:
        atoms, keep = truncated_target_atoms(next_q, critics.drop_per_critic)
        loss, metrics = quantile_huber_error(q, atoms, keep, next_log_prob, alpha, batch, gamma, n_step)
    elif critics.categorical:
        loss, metrics = categorical_error(q, next_q, next_log_prob, alpha, batch, gamma, n_step, critics)
    else:
        loss, metrics = soft_bellman_error(q, critics.next_value(next_q), next_log_prob, alpha, batch, gamma, n_step)
    return loss, (metrics, critic_stats)


def critic_loss(critic: Any, target_critic: Any, actor: Any, alpha: jax.Array, batch: Batch, key: jax.Array,
                policy: Policy, critics: Critics, gamma: float, n_step: int = 1) -> tuple[jax.Array, dict]:
    """`soft_q_loss` of SAC (target critics, no running statistics): the loss and its metrics."""
    loss, (metrics, _) = soft_q_loss(critic, (), target_critic, actor, (), alpha, batch, key, policy, critics, gamma,
                                     n_step)
    return loss, metrics


# ---- the actor's and the entropy coefficient's losses ---------------------------------------------

def policy_loss(actor: Any, actor_stats: Any, critic: Any, critic_stats: Any, alpha: jax.Array, obs: jax.Array,
                key: jax.Array, policy: Policy, critics: Critics, renorm: jax.Array | bool = False,
                critic_obs: jax.Array | None = None) -> tuple[jax.Array, tuple[jax.Array, Any]]:
    """Maximise E[min_i Q_i(s, a) - alpha log pi(a|s)] over reparameterised actions (Haarnoja et al.
    2018a, eq. 12; TQC: the mean of all quantiles in place of the minimum; categorical critics: their
    distributions' means). The actor runs in training mode (with batch renormalisation: the batch's statistics),
    the critics in evaluation mode (their running statistics), as CrossQ does. Returns the loss and (the
    actions' log-probabilities, which the alpha loss reuses; the actor's new running statistics). `critic_obs`:
    the observations as the critics read them, where they differ from the actor's (an actor's own image head)."""
    actions, log_prob, actor_stats = policy.sample_training(actor, actor_stats, obs, key, renorm)
    dropout_key = dropout_keys(key, critics)[0]
    critic_obs = obs if critic_obs is None else critic_obs
    q = critics.for_actor(critics.q_values(critic, critic_stats, critic_obs, actions, dropout_key))
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
