"""Soft Actor-Critic's update (Haarnoja et al. 2018a, 2018b), and its family's: CrossQ (Bhatt et al. 2024),
CrossQ+WN (Palenicek et al. 2025), TQC (Kuznetsov et al. 2020), DroQ (Hiraoka et al. 2022), SimBa networks
(Lee et al. 2024).

Read with `policy.py` (the tanh-squashed Gaussian) and `losses.py` (the critic, actor and entropy
losses). This module composes them: a critic step, an actor-and-alpha step, the target update, then one
jitted `update` that fuses `gradient_steps` of them with `lax.scan` and sums their metrics. The variants
differ in the losses (`losses.Critics`), the networks and the optimisers (AdamW, weight normalisation), so
nothing here branches on the algorithm but whether there are target critics and the networks' shapes.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from softac.learner.encoder import apply_head, encode_with_conv, random_shift, split_image_and_state, stack_channels
from softac.learner.losses import Batch, Critics, alpha_loss, policy_loss, soft_q_loss
from softac.learner.metric_names import CRITIC_METRICS, POLICY_METRICS
from softac.learner.networks.layers import unit_norm_hidden_units
from softac.learner.policy import ActionScaler, Policy


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
    actor_stats: Any = ()  # running statistics of batch renormalisation (CrossQ); () without it
    critic_stats: Any = ()
    target_critic_stats: Any = ()  # the target critics' (CrossQ with target critics, as CrossQ+WN); () without
    encoder: Any = ()  # the image encoder (image observations); () without
    encoder_opt: Any = ()
    target_encoder: Any = ()  # the target critics' copy of the encoder (target_encoder); () without
    actor_head: Any = ()  # the actor's own head on the encoder's convolutions (actor_encoder_head); () without
    actor_head_opt: Any = ()
    # (actor, actor_stats, encoder) averaged over the actor steps (policy_average_tau); () without
    policy_average: Any = ()


@dataclass(frozen=True)
class UpdateSettings:
    """Everything the update needs besides the state and the batch: fixed for a config and space sizes. The
    fields in NUMBERS are arguments of the compiled update, the rest shape its program (`Program`): configs
    that differ only in their learning rates, gamma, tau, alpha or entropy target share one program (issue 64:
    a sweep over them compiles once). The optimisers run at rate 1; `scaled` applies the learning rates."""
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
    encoder_tx: optax.GradientTransformation | None = None  # image observations: the encoder's optimiser
    augment_pad: int = 0  # image observations: DrQ's random shift (pixels of padding)
    image_state_dim: int = 0  # image observations: state values packed beside each image (pixels.ImageWithState)
    policy_average_tau: float = 0.0  # the deployed policy's averaging rate per actor step; 0: the actor itself
    target_encoder: bool = False  # image observations: the target critics read through a target copy of the encoder
    encoder_chunk: int = 0  # image observations: the update's batches go through the encoder in pieces of this many
    actor_head_tx: optax.GradientTransformation | None = None  # actor_encoder_head: the actor's head's optimiser
    pixel_offset: float = 0.0  # image observations: subtracted from pixels scaled to [0, 1] (config pixel_range)
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


NUMBERS = ("target_entropy", "gamma", "tau", "tau_keep", "alpha", "actor_lr", "critic_lr", "alpha_lr")


# ---- one gradient step ---------------------------------------------------------------------------

def polyak(target: Any, online: Any, tau: float, keep: float | None = None) -> Any:
    """target <- tau * online + (1 - tau) * target; `keep`: 1 - tau where tau is traced (UpdateSettings.tau_keep)."""
    keep = 1.0 - tau if keep is None else keep
    return jax.tree_util.tree_map(lambda t, o: keep * t + tau * o, target, online)


def alpha_of(state: SACState, s: UpdateSettings) -> jax.Array:
    return jnp.exp(state.log_alpha) if s.autotune_alpha else jnp.asarray(s.alpha, jnp.float32)


def renorm_active(state: SACState, s: UpdateSettings) -> jax.Array:
    """Batch renormalisation's corrections start after `batch_renorm_warmup` gradient steps."""
    return state.n_updates >= s.batch_renorm_warmup


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


def critic_step(state: SACState, batch: Batch, key: jax.Array, s: UpdateSettings,
                lr_scale: jax.Array | None = None) -> tuple[SACState, dict]:
    grads, (metrics, critic_stats) = jax.grad(soft_q_loss, has_aux=True)(
        state.critic, state.critic_stats, state.target_critic, state.actor, state.actor_stats, alpha_of(state, s),
        batch, key, s.policy, s.critics, s.gamma, s.n_step, renorm_active(state, s), state.target_critic_stats)
    critic, critic_opt = apply_critic_grads(state, grads, s, lr_scale)
    return state._replace(critic=critic, critic_opt=critic_opt, critic_stats=critic_stats), metrics


def apply_critic_grads(state: SACState, grads: Any, s: UpdateSettings, lr_scale: jax.Array | None) -> tuple[Any, Any]:
    """The critics' optimiser step (and CrossQ+WN's projection back to unit-norm hidden units)."""
    updates, critic_opt = s.critic_tx.update(grads, state.critic_opt, state.critic)
    critic = optax.apply_updates(state.critic, scaled(updates, s.critic_lr, lr_scale))
    if s.weight_norm:
        critic = unit_norm_hidden_units(critic)
    return critic, critic_opt


# ---- image observations (issue 44; DrQ, Kostrikov et al. 2021; DrQ-v2, Yarats et al. 2022) --------------------
# The critic loss trains the encoder; the next state's features are a target (stopped), and the actor reads the
# step's features stopped, computed before the encoder moved, as DrQ-v2 does: the actor's gradient through a
# shared encoder destabilises it (SAC-AE, Yarats et al. 2021). Each pass augments with its own random shift.

def image_features(encoder: Any, stacks: jax.Array, state_dim: int = 0, key: jax.Array | None = None,
                   pad: int = 0, chunk: int = 0, pixel_offset: float = 0.0) -> jax.Array:
    """The encoder's features of frame stacks [batch, k, h, w, c], followed by the state values the frames carry
    (`state_dim` of them); with `key`, each observation shifted at random first (one shift for all its frames).
    `chunk`: `encode`'s pieces; `pixel_offset`: `encode`'s (config pixel_range)."""
    return image_features_and_conv(encoder, stacks, state_dim, key, pad, chunk, pixel_offset)[0]


def image_features_and_conv(encoder: Any, stacks: jax.Array, state_dim: int = 0, key: jax.Array | None = None,
                            pad: int = 0, chunk: int = 0, pixel_offset: float = 0.0) -> tuple[jax.Array, jax.Array]:
    """`image_features`, and the flattened conv outputs they came from followed by the same state values (what
    an actor head reads)."""
    images, state = split_image_and_state(stacks, state_dim)
    images = stack_channels(images)
    features, conv = encode_with_conv(encoder, images if key is None else random_shift(images, key, pad), chunk,
                                      pixel_offset)
    if state is None:
        return features, conv
    return jnp.concatenate([features, state], axis=-1), jnp.concatenate([conv, state], axis=-1)


def actor_head_features(head: Any, conv_and_state: jax.Array) -> jax.Array:
    """The actor's features from its own head: the conv outputs through it, the state values after them."""
    flat = head["w"].shape[0]
    features = apply_head(head, conv_and_state[:, :flat])
    return features if conv_and_state.shape[1] == flat else jnp.concatenate(
        [features, conv_and_state[:, flat:]], axis=-1)


def policy_encoder(encoder: Any, actor_head: Any) -> Any:
    """The encoder the policy acts through: the shared convolutions with the actor's own head (DrQ's actor), or
    the whole shared encoder."""
    return {"convs": encoder["convs"], "head": actor_head} if jax.tree_util.tree_leaves(actor_head) else encoder


def features_of(encoder: Any, obs: jax.Array, state_dim: int = 0, pixel_offset: float = 0.0) -> jax.Array:
    """What actor and critics read: `image_features` of image observations, or vector observations as they are
    (no encoder)."""
    if not jax.tree_util.tree_leaves(encoder):
        return obs
    return image_features(encoder, obs, state_dim, pixel_offset=pixel_offset)


def encoded_batch(encoder: Any, batch: Batch, key: jax.Array, s: UpdateSettings) -> tuple[Batch, jax.Array]:
    """The batch's observations through `encoder`, each augmented (the same shifts for the same `key`), and the
    observations' conv outputs (with their state values); the next observations' features are targets, stopped."""
    obs_key, next_key = jax.random.split(key)
    obs, conv = image_features_and_conv(encoder, batch.obs, s.image_state_dim, obs_key, s.augment_pad,
                                        s.encoder_chunk, s.pixel_offset)
    next_obs = jax.lax.stop_gradient(image_features(encoder, batch.next_obs, s.image_state_dim, next_key,
                                                    s.augment_pad, s.encoder_chunk, s.pixel_offset))
    return batch._replace(obs=obs, next_obs=next_obs), conv


def target_encoded_batch(state: SACState, batch: Batch, key: jax.Array, s: UpdateSettings) -> Batch | None:
    """The batch as the target critics read it: through the target encoder, with the same shifts as the online
    pass (DrQ's target critic carries its own encoder copy, Polyak-averaged with it), stopped; None without a
    target encoder (the targets read the online features). XLA drops the observations' pass where only the
    next observations' is used (critics without batch renormalisation)."""
    if not jax.tree_util.tree_leaves(state.target_encoder):
        return None
    return jax.lax.stop_gradient(encoded_batch(state.target_encoder, batch, key, s)[0])


def image_critic_step(state: SACState, batch: Batch, key: jax.Array, s: UpdateSettings,
                      lr_scale: jax.Array | None = None) -> tuple[SACState, dict, Any]:
    """`critic_step` through the encoder, which the critic loss trains too; also returns what the actor step
    reads, stopped: the features of the batch's observations, and with an actor head (critic features, conv
    outputs with the state values)."""
    augment_key, loss_key = jax.random.split(key)
    target_batch = target_encoded_batch(state, batch, augment_key, s)

    def loss(critic: Any, encoder: Any):
        encoded, conv = encoded_batch(encoder, batch, augment_key, s)
        value, (metrics, critic_stats) = soft_q_loss(
            critic, state.critic_stats, state.target_critic, state.actor, state.actor_stats, alpha_of(state, s),
            encoded, loss_key, s.policy, s.critics, s.gamma, s.n_step, renorm_active(state, s),
            state.target_critic_stats, target_batch)
        return value, (metrics, critic_stats, (encoded.obs, conv) if s.actor_head_tx is not None else encoded.obs)

    (critic_grads, encoder_grads), (metrics, critic_stats, features) = jax.grad(loss, argnums=(0, 1), has_aux=True)(
        state.critic, state.encoder)
    critic, critic_opt = apply_critic_grads(state, critic_grads, s, lr_scale)
    updates, encoder_opt = s.encoder_tx.update(encoder_grads, state.encoder_opt, state.encoder)
    encoder = optax.apply_updates(state.encoder, scaled(updates, s.critic_lr, lr_scale))
    state = state._replace(critic=critic, critic_opt=critic_opt, critic_stats=critic_stats, encoder=encoder,
                           encoder_opt=encoder_opt)
    return state, metrics, jax.lax.stop_gradient(features)


def actor_and_alpha_step(state: SACState, obs: Any, key: jax.Array, s: UpdateSettings,
                         lr_scale: jax.Array | None = None) -> tuple[SACState, dict]:
    """`obs`: what the actor and the critics read; with an actor head, (the critics' features, the conv outputs
    the actor's head reads), and the actor loss trains that head too (DrQ's actor)."""
    if s.actor_head_tx is None:
        (loss, (log_prob, actor_stats)), grads = jax.value_and_grad(policy_loss, has_aux=True)(
            state.actor, state.actor_stats, state.critic, state.critic_stats, alpha_of(state, s), obs, key, s.policy,
            s.critics, renorm_active(state, s))
    else:
        critic_obs, conv = obs

        def head_loss(actor: Any, head: Any):
            return policy_loss(actor, state.actor_stats, state.critic, state.critic_stats, alpha_of(state, s),
                               actor_head_features(head, conv), key, s.policy, s.critics, renorm_active(state, s),
                               critic_obs)

        (loss, (log_prob, actor_stats)), (grads, head_grads) = jax.value_and_grad(
            head_loss, argnums=(0, 1), has_aux=True)(state.actor, state.actor_head)
        head_updates, head_opt = s.actor_head_tx.update(head_grads, state.actor_head_opt, state.actor_head)
        state = state._replace(actor_head=optax.apply_updates(state.actor_head,
                                                              scaled(head_updates, s.actor_lr, lr_scale)),
                               actor_head_opt=head_opt)
    updates, actor_opt = s.actor_tx.update(grads, state.actor_opt, state.actor)
    actor = optax.apply_updates(state.actor, scaled(updates, s.actor_lr, lr_scale))
    if s.weight_norm:
        actor = unit_norm_hidden_units(actor)
    state = state._replace(actor=actor, actor_opt=actor_opt, actor_stats=actor_stats)
    if s.policy_average_tau > 0:
        state = state._replace(policy_average=averaged_policy(state, s))
    if s.autotune_alpha:
        a_loss, grad = jax.value_and_grad(alpha_loss)(state.log_alpha, log_prob, s.target_entropy)
        updates, alpha_opt = s.alpha_tx.update(grad, state.alpha_opt, state.log_alpha)
        # the schedule scales alpha's rate too, as SB3 sets its lr schedule on the entropy coefficient's optimiser
        state = state._replace(log_alpha=optax.apply_updates(state.log_alpha, scaled(updates, s.alpha_lr, lr_scale)),
                               alpha_opt=alpha_opt)
    else:
        a_loss = alpha_loss(state.log_alpha, log_prob, s.target_entropy)
    return state, {"actor_loss": loss, "alpha_loss": a_loss, "log_prob_mean": jnp.mean(log_prob)}


def averaged_policy(state: SACState, s: UpdateSettings) -> tuple[Any, Any, Any]:
    """The deployed policy moved toward the actor (weight averaging, Nikishin et al. 2018: an average of the
    actor's recent weights acts more steadily than the last of them). Under weight_norm the average is put back
    on the unit sphere, where the actor's own hidden units live."""
    actor, stats, encoder = polyak(state.policy_average, (state.actor, state.actor_stats,
                                                          policy_encoder(state.encoder, state.actor_head)),
                                   s.policy_average_tau)
    return (unit_norm_hidden_units(actor) if s.weight_norm else actor), stats, encoder


def deployed(state: SACState) -> tuple[Any, Any, Any]:
    """(actor, actor_stats, encoder) that evaluation, predict, sample and export run: the averaged policy with
    policy_average_tau, else the actor itself."""
    return state.policy_average or acting_actor(state)


def acting_actor(state: SACState) -> tuple[Any, Any, Any]:
    """(actor, actor_stats, encoder) of the actor that explores (its own head on the shared convolutions with
    actor_encoder_head)."""
    return state.actor, state.actor_stats, policy_encoder(state.encoder, state.actor_head)


# ---- metrics over many updates ------------------------------------------------------------------------
# Each metric is summed over the gradient steps that computed it and divided once, when a progress row is
# written (issue 42): the actor's over actor steps only, so a row under policy_delay never shows a step that
# did not update the actor, and each row is the interval's mean as SB3 and CleanRL log it.
CRITIC_STEPS, ACTOR_STEPS = "critic_steps", "actor_steps"


def zero_totals() -> dict[str, jax.Array]:
    """Sums of every metric and the counts of critic and actor steps behind them, all zero."""
    return {name: jnp.zeros((), jnp.float32) for name in (*CRITIC_METRICS, *POLICY_METRICS, CRITIC_STEPS, ACTOR_STEPS)}


def add_to_totals(totals: dict, metrics: dict, counter: str) -> dict:
    return {**totals, **{k: totals[k] + v for k, v in metrics.items()}, counter: totals[counter] + 1.0}


def metric_means(totals: dict[str, Any]) -> dict[str, float]:
    """The mean of each metric over the steps that computed it; a metric no step computed is left out."""
    means = {}
    for names, counter in ((CRITIC_METRICS, CRITIC_STEPS), (POLICY_METRICS, ACTOR_STEPS)):
        count = float(totals[counter])
        if count > 0:
            means.update({k: float(totals[k]) / count for k in names})
    return means


def policy_round(state: SACState, totals: dict, obs: jax.Array, key: jax.Array, s: UpdateSettings,
                 lr_scale: jax.Array | None = None) -> tuple[SACState, dict]:
    """CleanRL's delayed policy update: every `policy_frequency` critic steps, that many actor steps (same
    batch, fresh noise), so actor and critic take the same number of steps overall."""
    for k in jax.random.split(key, s.policy_frequency):
        state, metrics = actor_and_alpha_step(state, obs, k, s, lr_scale)
        totals = add_to_totals(totals, metrics, ACTOR_STEPS)
    return state, totals


def update_targets(state: SACState, n_updates: jax.Array, s: UpdateSettings) -> SACState:
    """Polyak averaging every `target_update_interval` gradient steps (of the running statistics too, where
    the critics have them, as SBX averages its target batch statistics, and of a target encoder, as DrQ
    averages its target critic's encoder with it)."""
    due = (n_updates % s.target_update_interval) == 0

    def averaged(target: Any, online: Any) -> Any:
        return jax.tree_util.tree_map(lambda new, old: jnp.where(due, new, old),
                                      polyak(target, online, s.tau, s.tau_keep), target)

    target_encoder = averaged(state.target_encoder, state.encoder) if jax.tree_util.tree_leaves(
        state.target_encoder) else state.target_encoder
    return state._replace(target_critic=averaged(state.target_critic, state.critic),
                          target_critic_stats=averaged(state.target_critic_stats, state.critic_stats),
                          target_encoder=target_encoder)


def gradient_step(s: UpdateSettings, lr_scale: jax.Array | None, carry: tuple[SACState, dict],
                  batch: Batch) -> tuple[tuple[SACState, dict], None]:
    """One critic step; a policy round when due; the target update; their metrics added to the totals. TD3's
    policy delay (Fujimoto et al. 2018, sec. 5.2) spaces the policy rounds `policy_delay` times further apart
    with no catch-up: the actor takes 1/policy_delay of the steps, and the update costs less."""
    state, totals = carry
    key, critic_key, actor_key = jax.random.split(state.key, 3)
    alpha = alpha_of(state, s)
    if s.encoder_tx is None:
        state, critic_metrics = critic_step(state._replace(key=key), batch, critic_key, s, lr_scale)
        actor_obs = batch.obs
    else:
        state, critic_metrics, actor_obs = image_critic_step(state._replace(key=key), batch, critic_key, s, lr_scale)
    totals = add_to_totals(totals, {**critic_metrics, "alpha": alpha}, CRITIC_STEPS)
    n = state.n_updates + 1
    period = s.policy_frequency * s.policy_delay
    if period == 1:
        state, totals = policy_round(state, totals, actor_obs, actor_key, s, lr_scale)
    else:
        state, totals = jax.lax.cond(n % period == 0,
                                     lambda st, tot: policy_round(st, tot, actor_obs, actor_key, s, lr_scale),
                                     lambda st, tot: (st, tot), state, totals)
    if s.has_targets:
        state = update_targets(state, n, s)
    return (state._replace(n_updates=n), totals), None


def update(s: UpdateSettings, state: SACState, batches: Batch, totals: dict | None = None,
           lr_scale: jax.Array | None = None) -> tuple[SACState, dict]:
    """`batches` has a leading axis of gradient steps; all of them run in this one call. Returns the new state
    and `totals` (zero_totals() when None) with this call's metrics added (`metric_means` reads them).
    `lr_scale`: the learning rates' factor for this call's steps (lr_schedule), None for constant rates."""
    totals = zero_totals() if totals is None else totals
    step = partial(gradient_step, s, lr_scale)
    if s.encoder_tx is not None:
        # unrolled: XLA's CPU backend runs the encoder's convolutions far slower inside scan's while loop (3 frames
        # of 84x84, batch 32: 14.3 s per update in it, 2.2 s unrolled; docs/performance.md), and image runs take
        # few gradient steps per env step
        for i in range(batches.rewards.shape[0]):
            (state, totals), _ = step((state, totals), jax.tree_util.tree_map(lambda x: x[i], batches))
        return state, totals
    (state, totals), _ = jax.lax.scan(step, (state, totals), batches)
    return state, totals


# ---- the compiled update: one program per shape, its numbers traced (issue 64) ------------------

class Program:
    """What shapes the compiled update: UpdateSettings without its NUMBERS. Hashed once (JAX hashes a static
    argument at every call), equal to another of equal settings, so that equal configs share the program."""

    def __init__(self, s: UpdateSettings) -> None:
        self.settings = replace(s, **{name: 0.0 for name in NUMBERS})
        self.hash = hash(self.settings)

    def __hash__(self) -> int:
        return self.hash

    def __eq__(self, other: object) -> bool:
        return self is other or (isinstance(other, Program) and self.settings == other.settings)


def numbers_of(s: UpdateSettings) -> tuple[jax.Array, ...]:
    """`s`'s NUMBERS as JAX scalars, made once (Python floats would be converted at every call); weakly typed,
    as the Python floats were, so rounded to float32 once, the same."""
    return tuple(jnp.asarray(getattr(s, name)) for name in NUMBERS)


def update_program(program: Program, numbers: tuple[jax.Array, ...], state: SACState, batches: Batch,
                   totals: dict | None = None, lr_scale: jax.Array | None = None) -> tuple[SACState, dict]:
    return update(replace(program.settings, **dict(zip(NUMBERS, numbers))), state, batches, totals, lr_scale)


# One jitted update for every build (issue 64): the program's settings static, their numbers traced; the state
# and the totals donated (updated in place).
compiled_update = jax.jit(update_program, static_argnums=0, donate_argnums=(2, 4))


# ---- acting ------------------------------------------------------------------------------------------

# Each takes the encoder last (`()` for vector observations): the policy reads `features_of(encoder, obs,
# state_dim, pixel_offset)`, `state_dim` and `pixel_offset` bound when built.

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
