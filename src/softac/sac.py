"""Soft Actor-Critic, the algorithm (Haarnoja et al. 2018a, 2018b).

Reads top to bottom: the policy (a tanh-squashed Gaussian), the critic loss,
the actor loss, the entropy-coefficient loss, the target update, then one
jitted `update` that fuses `gradient_steps` of all of them with `lax.scan`.

CrossQ (Bhatt et al. 2024) is the same algorithm without target critics: batch
renormalisation in actor and critics, and one critic pass over the current and
next state-action pairs together, so both are normalised with the same batch
statistics. Its two losses follow SAC's below.

Actions inside the algorithm live in [-1, 1]^|A|; `ActionScaler` maps them to
the env's bounds (asymmetric bounds too). Log-probabilities are densities in
that normalised space, as in Stable-Baselines3, so the default entropy target
-|A| means the same thing for every env.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from softac.config import SACConfig
from softac.cpus import cpu_has_bf16
from softac.networks import (BatchRenorm, actor_sizes, critic_sizes, critics_apply, init_actor, init_critics,
                              init_norm_stats, mlp, normalized_critics_apply, normalized_mlp, stack)

LOG_2 = float(np.log(2.0))
LOG_SQRT_2PI = float(0.5 * np.log(2.0 * np.pi))


class Batch(NamedTuple):
    obs: jax.Array
    actions: jax.Array  # normalised to [-1, 1]
    rewards: jax.Array
    next_obs: jax.Array  # the true next observation, also at the end of an episode
    terminated: jax.Array  # 1.0 only for true terminal states: time-limit truncation still bootstraps
    steps: jax.Array  # rewards summed into `rewards` (n-step returns; 1 for one-step SAC)


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


# ---- the policy -----------------------------------------------------------

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


@dataclass(frozen=True)
class Policy:
    """The actor's settings; its parameters (and, with batch renormalisation, its running statistics
    `stats`) are passed to each method. Acting uses the running statistics; only the actor's own update
    normalises with batch statistics (`sample_training`)."""
    activation: str
    log_std_min: float
    log_std_max: float
    log_std_mode: str
    matmul_dtype: str = "float32"
    norm: BatchRenorm | None = None

    def _outputs(self, actor: Any, obs: jax.Array, stats: Any, train: bool = False,
                 renorm: jax.Array | bool = False) -> tuple[jax.Array, jax.Array, Any]:
        if self.norm is None:
            out = mlp(actor, obs, self.activation, self.matmul_dtype)
        else:
            out, stats = normalized_mlp(actor, stats, obs, self.activation, self.norm, train, renorm, self.matmul_dtype)
        mean, raw_log_std = jnp.split(out, 2, axis=-1)
        return mean, bound_log_std(raw_log_std, self.log_std_min, self.log_std_max, self.log_std_mode), stats

    def mean_and_log_std(self, actor: Any, obs: jax.Array, stats: Any = ()) -> tuple[jax.Array, jax.Array]:
        return self._outputs(actor, obs, stats)[:2]

    @staticmethod
    def _draw(mean: jax.Array, log_std: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        u = mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape)
        return jnp.tanh(u), squashed_gaussian_log_prob(u, mean, log_std)

    def sample(self, actor: Any, obs: jax.Array, key: jax.Array, stats: Any = ()) -> tuple[jax.Array, jax.Array]:
        """A reparameterised action in [-1, 1] and its log-probability."""
        return self._draw(*self.mean_and_log_std(actor, obs, stats), key)

    def sample_training(self, actor: Any, stats: Any, obs: jax.Array, key: jax.Array,
                        renorm: jax.Array | bool) -> tuple[jax.Array, jax.Array, Any]:
        """`sample` in training mode: normalised with the batch's statistics, which also update the running
        ones (returned third). Without batch renormalisation, `sample` and `stats` unchanged."""
        mean, log_std, stats = self._outputs(actor, obs, stats, train=True, renorm=renorm)
        return (*self._draw(mean, log_std, key), stats)

    def deterministic(self, actor: Any, obs: jax.Array, stats: Any = ()) -> jax.Array:
        return jnp.tanh(self.mean_and_log_std(actor, obs, stats)[0])


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


# ---- the critics -------------------------------------------------------------

@dataclass(frozen=True)
class Critics:
    """How the critic ensemble is evaluated (its settings; the parameters are passed to `q_values`)."""
    activation: str
    matmul_dtype: str = "float32"
    layer_norm: bool = False
    unroll: bool = False  # critic by critic (faster on CPU, see critics_apply) instead of vmap
    norm: BatchRenorm | None = None

    def q_values(self, critic: Any, obs: jax.Array, actions: jax.Array, stats: Any = ()) -> jax.Array:
        """Q-values of every critic, shape [n_critics, batch] (with batch renormalisation: its running
        statistics)."""
        if self.norm is not None:
            return normalized_critics_apply(critic, stats, obs, actions, self.activation, self.norm, False,
                                            matmul_dtype=self.matmul_dtype, unroll=self.unroll)[0]
        return critics_apply(critic, obs, actions, self.activation, self.matmul_dtype, self.layer_norm, self.unroll)

    def q_values_training(self, critic: Any, stats: Any, obs: jax.Array, actions: jax.Array,
                          renorm: jax.Array | bool) -> tuple[jax.Array, Any]:
        """Q-values normalised with this batch's statistics, and the updated running statistics."""
        return normalized_critics_apply(critic, stats, obs, actions, self.activation, self.norm, True, renorm,
                                        self.matmul_dtype, self.unroll)


# ---- the losses: pure functions of (parameters, batch, key, settings) ---------

def critic_loss(critic: Any, target_critic: Any, actor: Any, alpha: jax.Array, batch: Batch, key: jax.Array,
                policy: Policy, critics: Critics, gamma: float, n_step: int = 1) -> tuple[jax.Array, dict]:
    """Soft Bellman error with the minimum over target critics (clipped double Q, Fujimoto et al. 2018).

    Only `terminated` stops the bootstrap; a time-limit truncation still bootstraps. With n-step returns
    the buffer has summed `steps` discounted rewards (no entropy terms in between, as RLlib and SB3 do),
    so the bootstrap is discounted by gamma^steps (Sutton & Barto 2018, sec. 7.1).
    """
    next_actions, next_log_prob = policy.sample(actor, batch.next_obs, key)
    next_q = jnp.min(critics.q_values(target_critic, batch.next_obs, next_actions), axis=0)
    q = critics.q_values(critic, batch.obs, batch.actions)
    return soft_bellman_error(q, next_q, next_log_prob, alpha, batch, gamma, n_step)


def soft_bellman_error(q: jax.Array, next_q: jax.Array, next_log_prob: jax.Array, alpha: jax.Array, batch: Batch,
                       gamma: float, n_step: int) -> tuple[jax.Array, dict]:
    """0.5 * sum over critics of the mean squared error of q [n_critics, batch] to the soft target
    r + gamma^steps (1 - terminated) (next_q - alpha log pi(a'|s')), held fixed."""
    next_v = next_q - alpha * next_log_prob
    discount = gamma ** batch.steps if n_step > 1 else gamma
    target = jax.lax.stop_gradient(batch.rewards + discount * (1.0 - batch.terminated) * next_v)
    loss = 0.5 * jnp.sum(jnp.mean((q - target) ** 2, axis=1))
    return loss, {"critic_loss": loss, "q1_mean": jnp.mean(q[0]), "q2_mean": jnp.mean(q[min(1, q.shape[0] - 1)])}


def actor_loss(actor: Any, critic: Any, alpha: jax.Array, obs: jax.Array, key: jax.Array, policy: Policy,
               critics: Critics) -> tuple[jax.Array, jax.Array]:
    """Maximise E[min_i Q_i(s, a) - alpha log pi(a|s)] over reparameterised actions (Haarnoja et al.
    2018a, eq. 12); returns the loss and the actions' log-probabilities, which the alpha loss reuses."""
    actions, log_prob = policy.sample(actor, obs, key)
    q = jnp.min(critics.q_values(critic, obs, actions), axis=0)
    return jnp.mean(alpha * log_prob - q), log_prob


def alpha_loss(log_alpha: jax.Array, log_prob: jax.Array, target_entropy: float) -> jax.Array:
    """Entropy coefficient, learned on log(alpha) so alpha stays positive (Haarnoja et al. 2018b, sec. 5):
    alpha grows while the policy's entropy -log_prob is below the target, and shrinks above it."""
    return -jnp.mean(log_alpha * jax.lax.stop_gradient(log_prob + target_entropy))


# ---- CrossQ: the critic and actor losses without target critics -----------------

def crossq_critic_loss(critic: Any, critic_stats: Any, actor: Any, actor_stats: Any, alpha: jax.Array, batch: Batch,
                       key: jax.Array, policy: Policy, critics: Critics, gamma: float, n_step: int = 1,
                       renorm: jax.Array | bool = False) -> tuple[jax.Array, tuple[dict, Any]]:
    """CrossQ's soft Bellman error (Bhatt et al. 2024, sec. 3): the target comes from the online critics,
    which see (s, a) and (s', a') in one batch so that batch renormalisation normalises both with the same
    statistics (with separate passes the next pair is out of distribution for the normalisation); the
    target is held fixed by stop_gradient alone. Returns the loss and (metrics, new critic statistics)."""
    next_actions, next_log_prob = policy.sample(actor, batch.next_obs, key, actor_stats)
    both, critic_stats = critics.q_values_training(critic, critic_stats, jnp.concatenate([batch.obs, batch.next_obs]),
                                                   jnp.concatenate([batch.actions, next_actions]), renorm)
    q, next_q = jnp.split(both, 2, axis=1)
    loss, metrics = soft_bellman_error(q, jnp.min(next_q, axis=0), next_log_prob, alpha, batch, gamma, n_step)
    return loss, (metrics, critic_stats)


def crossq_actor_loss(actor: Any, actor_stats: Any, critic: Any, critic_stats: Any, alpha: jax.Array,
                      obs: jax.Array, key: jax.Array, policy: Policy, critics: Critics,
                      renorm: jax.Array | bool = False) -> tuple[jax.Array, tuple[jax.Array, Any]]:
    """SAC's actor loss with the actor in training mode (batch statistics) and the critics in evaluation
    mode (their running statistics), as CrossQ does; returns the loss and (log-probabilities, new actor
    statistics)."""
    actions, log_prob, actor_stats = policy.sample_training(actor, actor_stats, obs, key, renorm)
    q = jnp.min(critics.q_values(critic, obs, actions, critic_stats), axis=0)
    return jnp.mean(alpha * log_prob - q), (log_prob, actor_stats)


# ---- the learner ------------------------------------------------------------

def polyak(target: Any, online: Any, tau: float) -> Any:
    """target <- tau * online + (1 - tau) * target."""
    return jax.tree_util.tree_map(lambda t, o: (1.0 - tau) * t + tau * o, target, online)


def resolve_matmul_dtype(setting: str) -> str:
    """`auto` is bfloat16 where bf16 matmuls are fast (a GPU; a CPU with AVX-512 BF16 or AMX), else float32:
    on an AMD EPYC without AVX-512, bf16 made the update slower (Hopper, batch 256: 21 vs 30-39 steps/s)."""
    if setting != "auto":
        return setting
    return "bfloat16" if jax.default_backend() != "cpu" or cpu_has_bf16() else "float32"


class SACFunctions(NamedTuple):
    init: Callable[[int], SACState]
    reset: Callable[[SACState, int, int], SACState]
    update: Callable[[SACState, Batch], tuple[SACState, dict]]
    act: Callable[[Any, Any, jax.Array, jax.Array], tuple[jax.Array, jax.Array, jax.Array]]  # (actor, its stats, ...)
    act_deterministic: Callable[[Any, Any, jax.Array], jax.Array]
    policy: Policy
    target_entropy: float
    scaler: ActionScaler
    matmul_dtype: str  # as resolved (`auto` becomes float32 or bfloat16 here)


def build(config: SACConfig, obs_dim: int, act_dim: int, low: np.ndarray | None = None,
          high: np.ndarray | None = None) -> SACFunctions:
    """The jitted SAC functions for one config, space sizes and action bounds (default [-1, 1])."""
    c = config
    matmul_dtype = resolve_matmul_dtype(c.matmul_dtype)
    norm = BatchRenorm(c.batch_norm_momentum) if c.crossq else None
    policy = Policy(c.activation, c.log_std_min, c.log_std_max, c.log_std_mode, matmul_dtype, norm)
    target_entropy = -float(act_dim) if c.target_entropy == "auto" else float(c.target_entropy)
    actor_tx = optax.adam(c.actor_lr, b1=c.adam_b1)
    critic_tx = optax.adam(c.critic_lr, b1=c.adam_b1)
    alpha_tx = optax.adam(c.alpha_lr, b1=c.adam_b1)

    # critics with batch renormalisation stay vmapped: on CPU their unrolled form was no faster (CrossQ update
    # at HalfCheetah's sizes, batch 128: bf16 1.58 vs 1.54 ms, f32 1.87 vs 1.80)
    critics = Critics(c.activation, matmul_dtype, c.critic_layer_norm,
                      unroll=jax.default_backend() == "cpu" and c.n_critics <= 8 and not c.crossq, norm=norm)

    def assemble(actor: Any, critic: Any, key: jax.Array, actor_stats: Any, critic_stats: Any) -> SACState:
        log_alpha = jnp.asarray(np.log(max(c.alpha, 1e-30)), jnp.float32)
        return SACState(
            actor=actor, critic=critic, target_critic=() if c.crossq else jax.tree_util.tree_map(jnp.copy, critic),
            log_alpha=log_alpha, actor_opt=actor_tx.init(actor), critic_opt=critic_tx.init(critic),
            alpha_opt=alpha_tx.init(log_alpha), key=key, n_updates=jnp.zeros((), jnp.int32),
            actor_stats=actor_stats, critic_stats=critic_stats,
        )

    assemble = jax.jit(assemble)  # one compiled call (cached across processes) instead of dozens of eager ops

    def networks(rng: np.random.Generator) -> tuple[Any, Any, Any, Any]:
        """Fresh actor, critics and (with batch renormalisation) their running statistics."""
        actor = init_actor(rng, obs_dim, act_dim, c.hidden_sizes, c.init, norm=c.crossq)
        critic = init_critics(rng, obs_dim, act_dim, c.hidden_sizes, c.init, c.n_critics, norm=c.crossq)
        if not c.crossq:
            return actor, critic, (), ()
        return (actor, critic, init_norm_stats(actor_sizes(obs_dim, act_dim, c.hidden_sizes)),
                stack([init_norm_stats(critic_sizes(obs_dim, act_dim, c.hidden_sizes))] * c.n_critics))

    def init(seed: int) -> SACState:
        rng = np.random.default_rng([seed, 0x5AC])
        actor, critic, actor_stats, critic_stats = networks(rng)
        key = rng.integers(0, 2**32, 2, dtype=np.uint32)  # a raw PRNGKey
        return assemble(actor, critic, key, actor_stats, critic_stats)

    # Periodic resets (Nikishin et al. 2022, "The Primacy Bias in Deep RL"; D'Oro et al. 2023, SR-SAC):
    # new actor, critics, targets and their optimisers, drawn from the k-th reset's own seed; the replay
    # buffer, the entropy coefficient (with its optimiser), the key and the update counter carry over.
    def reset(state: SACState, seed: int, k: int) -> SACState:
        actor, critic, actor_stats, critic_stats = networks(np.random.default_rng([seed, 0x5AC, k]))
        fresh = assemble(actor, critic, state.key, actor_stats, critic_stats)
        return fresh._replace(log_alpha=state.log_alpha, alpha_opt=state.alpha_opt, n_updates=state.n_updates)

    def alpha_of(state: SACState) -> jax.Array:
        return jnp.exp(state.log_alpha) if c.autotune_alpha else jnp.asarray(c.alpha, jnp.float32)

    def renorm(state: SACState) -> jax.Array:
        """Batch renormalisation's corrections start after `batch_renorm_warmup` gradient steps."""
        return state.n_updates >= c.batch_renorm_warmup

    def critic_step(state: SACState, batch: Batch, key: jax.Array) -> tuple[SACState, dict]:
        if c.crossq:
            grads, (metrics, critic_stats) = jax.grad(crossq_critic_loss, has_aux=True)(
                state.critic, state.critic_stats, state.actor, state.actor_stats, alpha_of(state), batch, key, policy,
                critics, c.gamma, c.n_step, renorm(state))
            state = state._replace(critic_stats=critic_stats)
        else:
            grads, metrics = jax.grad(critic_loss, has_aux=True)(
                state.critic, state.target_critic, state.actor, alpha_of(state), batch, key, policy, critics, c.gamma,
                c.n_step)
        updates, critic_opt = critic_tx.update(grads, state.critic_opt, state.critic)
        return state._replace(critic=optax.apply_updates(state.critic, updates), critic_opt=critic_opt), metrics

    def actor_and_alpha_step(state: SACState, obs: jax.Array, key: jax.Array) -> tuple[SACState, dict]:
        alpha = alpha_of(state)
        if c.crossq:
            (loss, (log_prob, actor_stats)), grads = jax.value_and_grad(crossq_actor_loss, has_aux=True)(
                state.actor, state.actor_stats, state.critic, state.critic_stats, alpha, obs, key, policy, critics,
                renorm(state))
            state = state._replace(actor_stats=actor_stats)
        else:
            (loss, log_prob), grads = jax.value_and_grad(actor_loss, has_aux=True)(
                state.actor, state.critic, alpha, obs, key, policy, critics)
        updates, actor_opt = actor_tx.update(grads, state.actor_opt, state.actor)
        state = state._replace(actor=optax.apply_updates(state.actor, updates), actor_opt=actor_opt)
        a_loss = alpha_loss(state.log_alpha, log_prob, target_entropy)
        if c.autotune_alpha:
            grad = jax.grad(alpha_loss)(state.log_alpha, log_prob, target_entropy)
            updates, alpha_opt = alpha_tx.update(grad, state.alpha_opt, state.log_alpha)
            state = state._replace(log_alpha=optax.apply_updates(state.log_alpha, updates), alpha_opt=alpha_opt)
        return state, {"actor_loss": loss, "alpha_loss": a_loss, "log_prob_mean": jnp.mean(log_prob)}

    # CleanRL's delayed policy update: every `policy_frequency` critic steps, that many actor
    # steps (same batch, fresh noise), so actor and critic take the same number of steps overall.
    # TD3's policy delay (Fujimoto et al. 2018, sec. 5.2) spaces the rounds `policy_delay` times further
    # apart with no catch-up: the actor takes 1/policy_delay of the steps, and the update costs less.
    def policy_round(state: SACState, obs: jax.Array, key: jax.Array) -> tuple[SACState, dict]:
        metrics = None
        for k in jax.random.split(key, c.policy_frequency):
            state, metrics = actor_and_alpha_step(state, obs, k)
        return state, metrics

    def gradient_step(carry: tuple[SACState, dict], batch: Batch):
        state, policy_metrics = carry
        key, critic_key, actor_key = jax.random.split(state.key, 3)
        state, critic_metrics = critic_step(state._replace(key=key), batch, critic_key)
        n = state.n_updates + 1
        period = c.policy_frequency * c.policy_delay
        if period == 1:
            state, policy_metrics = policy_round(state, batch.obs, actor_key)
        else:
            state, policy_metrics = jax.lax.cond(
                n % period == 0,
                lambda s: policy_round(s, batch.obs, actor_key),
                lambda s: (s, policy_metrics),
                state,
            )
        if not c.crossq:
            do_target = (n % c.target_update_interval) == 0
            target = jax.tree_util.tree_map(
                lambda new, old: jnp.where(do_target, new, old),
                polyak(state.target_critic, state.critic, c.tau), state.target_critic)
            state = state._replace(target_critic=target)
        state = state._replace(n_updates=n)
        return (state, policy_metrics), critic_metrics

    def update(state: SACState, batches: Batch) -> tuple[SACState, dict]:
        """`batches` has a leading axis of gradient steps; all of them run in this one call."""
        zero = jnp.zeros((), jnp.float32)
        start = {"actor_loss": zero, "alpha_loss": zero, "log_prob_mean": zero}
        (state, policy_metrics), critic_metrics = jax.lax.scan(gradient_step, (state, start), batches)
        metrics = {k: jnp.mean(v) for k, v in critic_metrics.items()}
        metrics.update(policy_metrics)
        metrics["alpha"] = alpha_of(state)
        return state, metrics

    scaler = ActionScaler(np.full(act_dim, -1.0) if low is None else low, np.ones(act_dim) if high is None else high)

    def act(actor: Any, actor_stats: Any, obs: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
        """(action in [-1, 1], the same action in env bounds, next key): one call per env step."""
        key, sample_key = jax.random.split(key)
        action = policy.sample(actor, obs, sample_key, actor_stats)[0]
        return action, scaler.to_env(action, jnp), key

    def act_deterministic(actor: Any, actor_stats: Any, obs: jax.Array) -> jax.Array:
        return policy.deterministic(actor, obs, actor_stats)

    return SACFunctions(
        init=init,
        reset=reset,
        update=jax.jit(update, donate_argnums=0),
        act=jax.jit(act),
        act_deterministic=jax.jit(act_deterministic),
        policy=policy,
        target_entropy=target_entropy,
        scaler=scaler,
        matmul_dtype=matmul_dtype,
    )
