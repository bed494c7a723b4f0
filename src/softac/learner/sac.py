"""Soft Actor-Critic's update (Haarnoja et al. 2018a, 2018b), and its family's: CrossQ (Bhatt et al. 2024),
CrossQ+WN (Palenicek et al. 2025), TQC (Kuznetsov et al. 2020), DroQ (Hiraoka et al. 2022), SimBa networks
(Lee et al. 2024), DrQ from images (Kostrikov et al. 2021).

Read with `policy.py` (the tanh-squashed Gaussian) and `losses.py` (the critic, actor and entropy
losses). This module composes them: a critic step, an actor-and-alpha step, the target update, then `update`,
which fuses `gradient_steps` of them in one call (`lax.scan`; unrolled for image observations) and sums their
metrics; `build.compiled_update` jits it once for every build. The variants
differ in the losses (`losses.Critics`), the networks and the optimisers (AdamW, weight normalisation), so
nothing here branches on the algorithm but whether there are target critics, the networks' shapes and
whether the observations are images (`pixels.py`: what the actor and critics read of them).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from softac.learner.losses import Batch, Critics, alpha_loss, policy_loss, soft_q_loss
from softac.learner.metrics import ACTOR_STEPS, CRITIC_STEPS, add_to_totals, zero_totals
from softac.learner.pixels import (ImageSettings, actor_head_features, encoded_batch, policy_encoder,
                                   target_encoded_batch)
from softac.learner.policy import Policy


class Variants(NamedTuple):
    """The variants' state beside SAC's, each () where its variant is off."""
    actor_stats: Any = ()  # batch renormalisation's running statistics (CrossQ)
    critic_stats: Any = ()
    target_critic_stats: Any = ()  # the target critics' (CrossQ with target critics, as CrossQ+WN)
    encoder: Any = ()  # the image encoder (image observations) and its optimiser
    encoder_opt: Any = ()
    target_encoder: Any = ()  # the target critics' copy of the encoder (target_encoder)
    actor_head: Any = ()  # the actor's own head on the encoder's convolutions (actor_encoder_head)
    actor_head_opt: Any = ()
    policy_average: Any = ()  # (actor, actor_stats, encoder) averaged over the actor steps (policy_average_tau)


class SACState(NamedTuple):
    actor: Any
    critic: Any
    target_critic: Any  # () with CrossQ, which has none
    log_alpha: jax.Array
    actor_opt: Any
    critic_opt: Any
    alpha_opt: Any
    key: jax.Array
    n_updates: jax.Array  # gradient steps taken so far
    variants: Variants = Variants()

    def with_variants(self, **fields: Any) -> SACState:
        return self._replace(variants=self.variants._replace(**fields))


@dataclass(frozen=True)
class UpdateSettings:
    """Everything the update needs besides the state and the batch: fixed for a config and space sizes. The
    fields in build.NUMBERS are arguments of the compiled update, the rest shape its program (build.Program):
    configs that differ only in their learning rates, gamma, tau, alpha or entropy target share one program
    (issue 64: a sweep over them compiles once). The optimisers run at rate 1; `scaled` applies the learning rates."""
    policy: Policy
    critics: Critics
    actor_tx: optax.GradientTransformation
    critic_tx: optax.GradientTransformation
    alpha_tx: optax.GradientTransformation
    target_entropy: float
    gamma: float
    n_step: int
    tau: float
    target_update_interval: int
    policy_frequency: int
    policy_delay: int
    autotune_alpha: bool
    alpha: float
    batch_renorm_warmup: int
    weight_norm: bool
    image: ImageSettings | None = None  # image observations' settings; None for vectors
    policy_average_tau: float = 0.0  # the deployed policy's averaging rate per actor step; 0: the actor itself
    actor_lr: float = 1.0  # the actor's rate (and an actor head's)
    critic_lr: float = 1.0  # the critics' rate (and the encoder's)
    alpha_lr: float = 1.0
    # 1 - tau, computed in float64 as the constant (1.0 - tau) was before tau became an argument (the same bits);
    # None: from tau, when made
    tau_keep: float | None = None

    def __post_init__(self) -> None:
        if self.tau_keep is None:
            object.__setattr__(self, "tau_keep", 1.0 - self.tau)

    @property
    def has_targets(self) -> bool:
        return self.critics.has_targets


# ---- one gradient step ---------------------------------------------------------------------------

def polyak(target: Any, online: Any, tau: float, keep: float | None = None) -> Any:
    """target <- tau * online + (1 - tau) * target; `keep`: 1 - tau where tau is traced (UpdateSettings.tau_keep)."""
    keep = 1.0 - tau if keep is None else keep
    return jax.tree_util.tree_map(lambda t, o: keep * t + tau * o, target, online)


def alpha_of(state: SACState, settings: UpdateSettings) -> jax.Array:
    return jnp.exp(state.log_alpha) if settings.autotune_alpha else jnp.asarray(settings.alpha, jnp.float32)


def renorm_active(state: SACState, settings: UpdateSettings) -> jax.Array:
    """Batch renormalisation's corrections start after `batch_renorm_warmup` gradient steps."""
    return state.n_updates >= settings.batch_renorm_warmup


def scaled(updates: Any, lr: float, lr_scale: jax.Array | None) -> Any:
    """One step's updates at learning rate `lr`, times a schedule's factor (lr_schedule; None: constant rates).
    Adam's and AdamW's update is -lr times a direction that does not depend on lr, and the optimisers here run
    at rate 1 (their updates are -1 times it), so scaling their updates by lr is the update at lr: -lr * u
    and lr * (-u) are the same floats."""
    # lr * lr_scale first: the order XLA gave the product when lr was a constant (the same bits on today's JAX).
    # Where it kept the other order (JAX 0.4.30; image updates, unrolled) a scheduled run rounds apart in the
    # last bits from softac before issue 64's change; runs at constant rates are the same everywhere
    rate = lr if lr_scale is None else lr * lr_scale
    return jax.tree_util.tree_map(lambda u: u * rate, updates)


def critic_step(state: SACState, batch: Batch, key: jax.Array, settings: UpdateSettings,
                lr_scale: jax.Array | None = None) -> tuple[SACState, dict, Any]:
    """The critics' step on the soft Bellman error; with image observations through the encoder, which the loss
    trains too, each pass augmented (`pixels.encoded_batch`). Also returns what the actor step reads, stopped:
    the batch's observations, or their features (with an actor head: the features and the conv outputs)."""
    v, image = state.variants, settings.image
    augment_key, loss_key = (None, key) if image is None else jax.random.split(key)
    target_batch = None if image is None else target_encoded_batch(v.target_encoder, batch, augment_key, image)

    def loss(critic: Any, encoder: Any):
        encoded, actor_obs = (batch, batch.obs) if image is None else encoded_batch(encoder, batch, augment_key, image)
        value, (metrics, critic_stats) = soft_q_loss(
            critic, v.critic_stats, state.target_critic, state.actor, v.actor_stats, alpha_of(state, settings),
            encoded, loss_key, settings.policy, settings.critics, settings.gamma, settings.n_step,
            renorm_active(state, settings), v.target_critic_stats, target_batch)
        return value, (metrics, critic_stats, actor_obs)

    (critic_grads, encoder_grads), (metrics, critic_stats, actor_obs) = jax.grad(loss, argnums=(0, 1), has_aux=True)(
        state.critic, v.encoder)
    updates, critic_opt = settings.critic_tx.update(critic_grads, state.critic_opt, state.critic)
    critic = optax.apply_updates(state.critic, scaled(updates, settings.critic_lr, lr_scale))
    if settings.weight_norm:  # CrossQ+WN: hidden units back to unit norm (XQC: every unit, by the kind)
        critic = settings.critics.kind.unit_norm(critic)
    state = state._replace(critic=critic, critic_opt=critic_opt).with_variants(critic_stats=critic_stats)
    if image is not None:
        updates, encoder_opt = image.encoder_tx.update(encoder_grads, v.encoder_opt, v.encoder)
        encoder = optax.apply_updates(v.encoder, scaled(updates, settings.critic_lr, lr_scale))
        state = state.with_variants(encoder=encoder, encoder_opt=encoder_opt)
    return state, metrics, jax.lax.stop_gradient(actor_obs)


def actor_and_alpha_step(state: SACState, obs: Any, key: jax.Array, settings: UpdateSettings,
                         lr_scale: jax.Array | None = None) -> tuple[SACState, dict]:
    """`obs`: what the actor and the critics read; with an actor head, (the critics' features, the conv outputs
    the actor's head reads), and the actor loss trains that head too (DrQ's actor)."""
    v = state.variants
    if settings.image is None or settings.image.actor_head_tx is None:
        (loss, (log_prob, actor_stats)), grads = jax.value_and_grad(policy_loss, has_aux=True)(
            state.actor, v.actor_stats, state.critic, v.critic_stats, alpha_of(state, settings), obs, key,
            settings.policy, settings.critics, renorm_active(state, settings))
    else:
        critic_obs, conv = obs

        def head_loss(actor: Any, head: Any):
            return policy_loss(actor, v.actor_stats, state.critic, v.critic_stats, alpha_of(state, settings),
                               actor_head_features(head, conv), key, settings.policy, settings.critics,
                               renorm_active(state, settings), critic_obs)

        (loss, (log_prob, actor_stats)), (grads, head_grads) = jax.value_and_grad(
            head_loss, argnums=(0, 1), has_aux=True)(state.actor, v.actor_head)
        head_updates, head_opt = settings.image.actor_head_tx.update(head_grads, v.actor_head_opt, v.actor_head)
        head = optax.apply_updates(v.actor_head, scaled(head_updates, settings.actor_lr, lr_scale))
        state = state.with_variants(actor_head=head, actor_head_opt=head_opt)
    updates, actor_opt = settings.actor_tx.update(grads, state.actor_opt, state.actor)
    actor = optax.apply_updates(state.actor, scaled(updates, settings.actor_lr, lr_scale))
    if settings.weight_norm:
        actor = settings.policy.kind.unit_norm(actor)
    state = state._replace(actor=actor, actor_opt=actor_opt).with_variants(actor_stats=actor_stats)
    if settings.policy_average_tau > 0:
        state = state.with_variants(policy_average=averaged_policy(state, settings))
    if settings.autotune_alpha:
        a_loss, grad = jax.value_and_grad(alpha_loss)(state.log_alpha, log_prob, settings.target_entropy)
        updates, alpha_opt = settings.alpha_tx.update(grad, state.alpha_opt, state.log_alpha)
        # the schedule scales alpha's rate too, as SB3 sets its lr schedule on the entropy coefficient's optimiser
        log_alpha = optax.apply_updates(state.log_alpha, scaled(updates, settings.alpha_lr, lr_scale))
        state = state._replace(log_alpha=log_alpha, alpha_opt=alpha_opt)
    else:
        a_loss = alpha_loss(state.log_alpha, log_prob, settings.target_entropy)
    return state, {"actor_loss": loss, "alpha_loss": a_loss, "log_prob_mean": jnp.mean(log_prob)}


def averaged_policy(state: SACState, settings: UpdateSettings) -> tuple[Any, Any, Any]:
    """The deployed policy moved toward the actor (weight averaging, Nikishin et al. 2018: an average of the
    actor's recent weights acts more steadily than the last of them). Under weight_norm the average is put back
    on the unit sphere, where the actor's own hidden units live."""
    actor, stats, encoder = polyak(state.variants.policy_average, acting_actor(state), settings.policy_average_tau)
    return (settings.policy.kind.unit_norm(actor) if settings.weight_norm else actor), stats, encoder


def deployed(state: SACState) -> tuple[Any, Any, Any]:
    """(actor, actor_stats, encoder) that evaluation, predict, sample and export run: the averaged policy with
    policy_average_tau, else the actor itself."""
    return state.variants.policy_average or acting_actor(state)


def acting_actor(state: SACState) -> tuple[Any, Any, Any]:
    """(actor, actor_stats, encoder) of the actor that explores (its own head on the shared convolutions with
    actor_encoder_head)."""
    v = state.variants
    return state.actor, v.actor_stats, policy_encoder(v.encoder, v.actor_head)


def policy_round(state: SACState, totals: dict, obs: jax.Array, key: jax.Array, settings: UpdateSettings,
                 lr_scale: jax.Array | None = None) -> tuple[SACState, dict]:
    """CleanRL's delayed policy update: every `policy_frequency` critic steps, that many actor steps (same
    batch, fresh noise), so actor and critic take the same number of steps overall."""
    for k in jax.random.split(key, settings.policy_frequency):
        state, metrics = actor_and_alpha_step(state, obs, k, settings, lr_scale)
        totals = add_to_totals(totals, metrics, ACTOR_STEPS)
    return state, totals


def update_targets(state: SACState, n_updates: jax.Array, settings: UpdateSettings) -> SACState:
    """Polyak averaging every `target_update_interval` gradient steps (of the running statistics too, where
    the critics have them, as SBX averages its target batch statistics, and of a target encoder, as DrQ
    averages its target critic's encoder with it)."""
    due = (n_updates % settings.target_update_interval) == 0

    def averaged(target: Any, online: Any) -> Any:
        return jax.tree_util.tree_map(lambda new, old: jnp.where(due, new, old),
                                      polyak(target, online, settings.tau, settings.tau_keep), target)

    v = state.variants
    target_encoder = averaged(v.target_encoder, v.encoder) if jax.tree_util.tree_leaves(
        v.target_encoder) else v.target_encoder
    return state._replace(target_critic=averaged(state.target_critic, state.critic)).with_variants(
        target_critic_stats=averaged(v.target_critic_stats, v.critic_stats), target_encoder=target_encoder)


def gradient_step(settings: UpdateSettings, lr_scale: jax.Array | None, carry: tuple[SACState, dict],
                  batch: Batch) -> tuple[tuple[SACState, dict], None]:
    """One critic step; a policy round when due; the target update; their metrics added to the totals. TD3's
    policy delay (Fujimoto et al. 2018, sec. 5.2) spaces the policy rounds `policy_delay` times further apart
    with no catch-up: the actor takes 1/policy_delay of the steps, and the update costs less."""
    state, totals = carry
    key, critic_key, actor_key = jax.random.split(state.key, 3)
    alpha = alpha_of(state, settings)
    state, critic_metrics, actor_obs = critic_step(state._replace(key=key), batch, critic_key, settings, lr_scale)
    totals = add_to_totals(totals, {**critic_metrics, "alpha": alpha}, CRITIC_STEPS)
    n = state.n_updates + 1
    period = settings.policy_frequency * settings.policy_delay
    if period == 1:
        state, totals = policy_round(state, totals, actor_obs, actor_key, settings, lr_scale)
    else:
        state, totals = jax.lax.cond(n % period == 0,
                                     lambda st, tot: policy_round(st, tot, actor_obs, actor_key, settings, lr_scale),
                                     lambda st, tot: (st, tot), state, totals)
    if settings.has_targets:
        state = update_targets(state, n, settings)
    return (state._replace(n_updates=n), totals), None


def update(settings: UpdateSettings, state: SACState, batches: Batch, totals: dict | None = None,
           lr_scale: jax.Array | None = None) -> tuple[SACState, dict]:
    """`batches` has a leading axis of gradient steps; all of them run in this one call. Returns the new state
    and `totals` (zero_totals() when None) with this call's metrics added (`metrics.metric_means` reads them).
    `lr_scale`: the learning rates' factor for this call's steps (lr_schedule), None for constant rates."""
    totals = zero_totals() if totals is None else totals
    step = partial(gradient_step, settings, lr_scale)
    if settings.image is not None:
        # unrolled: XLA's CPU backend runs the encoder's convolutions far slower inside scan's while loop (3 frames
        # of 84x84, batch 32: 14.3 s per update in it, 2.2 s unrolled; docs/performance.md), and image runs take
        # few gradient steps per env step
        for i in range(batches.rewards.shape[0]):
            (state, totals), _ = step((state, totals), jax.tree_util.tree_map(lambda x: x[i], batches))
        return state, totals
    (state, totals), _ = jax.lax.scan(step, (state, totals), batches)
    return state, totals
