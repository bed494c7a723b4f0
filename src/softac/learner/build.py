"""Building SAC's functions for one config: fresh networks and their reset, the optimisers, the update's
settings (`UpdateSettings`), the one compiled update every build shares, and `build`, which returns the jitted
init, reset, update and acting functions (`SACFunctions`). The maths they run is `sac.py`'s."""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache, partial
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from softac.base.cpus import cpu_has_bf16
from softac.base.device import release_compiled_programs_near_map_limit
from softac.config.sac_config import SACConfig
from softac.learner.encoder import image_only_shape, init_encoder, init_head, stacked_image_shape
from softac.learner.losses import Batch, Critics
from softac.learner.networks import init_actor, init_critics, network_kind
from softac.learner.networks.layers import BatchRenorm, jit_keeps_bf16_rounding, stack
from softac.learner.policy import ActionScaler, Policy
from softac.learner.acting import act, act_deterministic, act_with_noise
from softac.learner.pixels import ImageSettings, policy_encoder
from softac.learner.sac import SACState, UpdateSettings, Variants, update


# ---- the state: fresh, and reset -----------------------------------------------------------------------

def fresh_networks(config: SACConfig, obs_dim: int, act_dim: int, rng: np.random.Generator) -> tuple[Any, ...]:
    """New actor and critics, and (with batch renormalisation) their running statistics."""
    c, norm = config, config.crossq
    actor = init_actor(rng, obs_dim, act_dim, c.actor_widths, c.init, norm=norm, network=c.network,
                       sde_log_std_init=c.sde_log_std_init if c.exploration_noise == "gsde" else None)
    critic = init_critics(rng, obs_dim, act_dim, c.critic_widths, c.init, c.n_critics, norm=norm, network=c.network,
                          out_dim=c.critic_outputs)
    kind = network_kind(c.network, norm)
    if c.layer_norm_affine:  # Flax's LayerNorm (Brax, RLPD): a scale and bias per unit, from 1 and 0
        from softac.learner.networks.mlp import with_layer_norm_affine

        actor = with_layer_norm_affine(actor) if c.actor_layer_norm else actor
        critic = with_layer_norm_affine(critic) if c.critic_layer_norm else critic
    if c.zero_actor_head:  # FastSAC: zero mean and one log std in every state to start
        kind.head(actor).update(w=np.zeros_like(kind.head(actor)["w"]), b=np.zeros_like(kind.head(actor)["b"]))
    if c.weight_norm:  # on the sphere from the start, so the running statistics see one scale throughout
        actor, critic = kind.unit_norm(actor, np), kind.unit_norm(critic, np)
    if not norm:
        return actor, critic, (), ()
    return (actor, critic, kind.init_stats(obs_dim, c.actor_widths, 2 * act_dim),
            stack([kind.init_stats(obs_dim + act_dim, c.critic_widths, c.critic_outputs)] * c.n_critics))


def fresh_encoder(config: SACConfig, image_shape: tuple[int, int, int, int] | None, rng: np.random.Generator,
                  state_dim: int = 0) -> Any:
    """A new image encoder for frame stacks of `image_shape` [k, h, w, c] that carry `state_dim` values (drawn
    after the networks, from the same generator), or () for vector observations."""
    if image_shape is None:
        return ()
    return init_encoder(rng, stacked_image_shape(image_only_shape(image_shape, state_dim)), config.encoder_channels,
                        config.encoder_features)


def fresh_actor_head(config: SACConfig, encoder: Any, rng: np.random.Generator) -> Any:
    """The actor's own head on `encoder`'s convolutions, the shape of the encoder's head (actor_encoder_head;
    drawn after the encoder), or ()."""
    if not (config.actor_encoder_head and jax.tree_util.tree_leaves(encoder)):
        return ()
    return init_head(rng, *encoder["head"]["w"].shape)


def assemble(s: UpdateSettings, initial_alpha: float, actor: Any, critic: Any, key: jax.Array, actor_stats: Any,
             critic_stats: Any, encoder: Any = (), actor_head: Any = ()) -> SACState:
    """A state around fresh networks: targets copied from the critics (and their statistics, and the encoder with
    target_encoder), the averaged policy (policy_average_tau) from the actor, fresh optimisers."""
    log_alpha = jnp.asarray(np.log(max(initial_alpha, 1e-30)), jnp.float32)

    def copy(tree: Any, wanted: bool) -> Any:
        return jax.tree_util.tree_map(jnp.copy, tree) if wanted else ()

    image = s.image
    return SACState(
        actor=actor, critic=critic, target_critic=copy(critic, s.has_targets),
        log_alpha=log_alpha, actor_opt=s.actor_tx.init(actor), critic_opt=s.critic_tx.init(critic),
        alpha_opt=s.alpha_tx.init(log_alpha), key=key, n_updates=jnp.zeros((), jnp.int32),
        variants=Variants(
            actor_stats=actor_stats, critic_stats=critic_stats,
            target_critic_stats=copy(critic_stats, s.has_targets),
            encoder=encoder, encoder_opt=image.encoder_tx.init(encoder) if image is not None else (),
            # SACConfig refuses target_encoder without target critics
            target_encoder=copy(encoder, image is not None and image.target_encoder),
            actor_head=actor_head,
            actor_head_opt=(image.actor_head_tx.init(actor_head)
                            if image is not None and image.actor_head_tx is not None else ()),
            policy_average=copy((actor, actor_stats, policy_encoder(encoder, actor_head)), s.policy_average_tau > 0)),
    )


def resolve_matmul_dtype(setting: str) -> str:
    """`auto` is bfloat16 where bf16 matmuls are fast (a GPU; a CPU with AVX-512 BF16 or AMX) and this JAX's
    compiler keeps their rounding, else float32 (docs/performance.md has the measurements; JAX 0.4.30's CPU
    backend multiplies bf16 layers in float32 anyway, and the run's config says so)."""
    if setting != "auto":
        return setting
    fast = jax.default_backend() != "cpu" or cpu_has_bf16()
    return "bfloat16" if fast and jit_keeps_bf16_rounding() else "float32"


def optimizer(config: SACConfig, lr: float) -> optax.GradientTransformation:
    """Adam, or AdamW (Loshchilov & Hutter 2019) with weight_decay: on every parameter (SimBa) or on the
    output layers only (CrossQ+WN, whose hidden units weight_norm keeps on the unit sphere)."""
    mask = network_kind(config.network, config.crossq).output_mask if config.weight_decay_layers == "output" else None
    return _adam(lr, config.adam_b1, config.adam_b2, config.weight_decay, mask)


@lru_cache(maxsize=None)
def _adam(lr: float, b1: float, b2: float = 0.999, weight_decay: float = 0.0,
          mask: Callable[[Any], Any] | None = None) -> optax.GradientTransformation:
    # one object per setting, so that two builds of one config have equal UpdateSettings and share the compiled
    # update within a process, not only through the compile cache
    if weight_decay == 0:
        return optax.adam(lr, b1=b1, b2=b2)
    return optax.adamw(lr, b1=b1, b2=b2, weight_decay=weight_decay, mask=mask)


def resolve_target_entropy(config: SACConfig, act_dim: int) -> float:
    """`auto` is -target_entropy_scale * |A| (Haarnoja et al. 2018b: -|A|; SimBa and CrossQ+WN: -|A|/2), or with
    target_entropy_std the entropy of a Gaussian of that std per action dim (FlashSAC's unified target)."""
    if config.target_entropy == "auto" and config.target_entropy_std > 0:
        return 0.5 * act_dim * float(np.log(2.0 * np.pi * np.e * config.target_entropy_std**2))
    if config.target_entropy == "auto":
        return -config.target_entropy_scale * float(act_dim)
    return float(config.target_entropy)


def update_settings(config: SACConfig, act_dim: int, matmul_dtype: str, images: bool = False,
                    image_state_dim: int = 0) -> UpdateSettings:
    c = config
    norm = BatchRenorm(c.batch_norm_momentum, c.batch_norm_eps) if c.crossq else None
    # critics with batch renormalisation stay vmapped: unrolled, they were no faster (docs/performance.md)
    unroll = jax.default_backend() == "cpu" and c.n_critics <= 8 and norm is None
    return UpdateSettings(
        policy=Policy(c.activation, c.log_std_min, c.log_std_max, c.log_std_mode, matmul_dtype, norm, c.network,
                      sde=c.exploration_noise == "gsde", layer_norm=c.layer_norm_position if c.actor_layer_norm else ""),
        critics=Critics(c.activation, matmul_dtype, c.layer_norm_position if c.critic_layer_norm else "", unroll=unroll, batch_renorm=norm,
                        network=c.network, dropout=c.critic_dropout, n_quantiles=c.n_quantiles,
                        drop_per_critic=c.top_quantiles_to_drop_per_net, targets=c.has_target_critics,
                        n_atoms=c.n_atoms, v_min=c.v_min, v_max=c.v_max, categorical_target=c.categorical_target,
                        hl_gauss_sigma=c.hl_gauss_sigma, target_q=c.target_q, actor_q=c.actor_q,
                        target_q_subset=c.target_q_subset if c.target_q == "subset" else 2),
        # the optimisers at rate 1, `scaled` applying each rate (AdamW's decay lr * weight_decay * p with the rest)
        actor_tx=optimizer(c, 1.0), critic_tx=optimizer(c, 1.0), alpha_tx=_adam(1.0, c.adam_b1, c.adam_b2),
        actor_lr=c.actor_lr, critic_lr=c.critic_lr, alpha_lr=c.alpha_lr,
        target_entropy=resolve_target_entropy(c, act_dim),
        gamma=c.gamma, n_step=c.n_step, tau=c.tau, target_update_interval=c.target_update_interval,
        policy_frequency=c.policy_frequency, policy_delay=c.policy_delay, autotune_alpha=c.autotune_alpha,
        alpha=c.alpha, batch_renorm_warmup=c.batch_renorm_warmup, weight_norm=c.weight_norm,
        image=image_settings(c, image_state_dim) if images else None, policy_average_tau=c.policy_average_tau)


def image_settings(config: SACConfig, state_dim: int) -> ImageSettings:
    c = config
    return ImageSettings(
        # the encoder learns at the critics' rate (DrQ's and DrQ-v2's one encoder optimiser at the critic's lr)
        encoder_tx=_adam(1.0, c.adam_b1, c.adam_b2), augment_pad=c.augment_pad, state_dim=state_dim,
        pixel_offset=c.pixel_offset, target_encoder=c.target_encoder,
        # on a CPU the convolutions run faster in pieces of 8 images (encoder.chunked_encode); a GPU wants the batch
        chunk=8 if jax.default_backend() == "cpu" else 0,
        actor_head_tx=_adam(1.0, c.adam_b1, c.adam_b2) if c.actor_encoder_head else None)


# ---- the compiled update: one program per shape, its numbers traced (issue 64) ------------------

NUMBERS = ("target_entropy", "gamma", "tau", "tau_keep", "alpha", "actor_lr", "critic_lr", "alpha_lr")


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


class SACFunctions(NamedTuple):
    init: Callable[[int], SACState]
    reset: Callable[[SACState, int, int], SACState]
    update: Callable[..., tuple[SACState, dict]]  # (state, batches, totals=None) -> (state, totals)
    act: Callable[[Any, Any, jax.Array, jax.Array], tuple[jax.Array, jax.Array, jax.Array]]  # (actor, its stats, ...)
    act_deterministic: Callable[[Any, Any, jax.Array], jax.Array]
    act_with_noise: Callable[[Any, Any, jax.Array, jax.Array], tuple[jax.Array, jax.Array]]
    policy: Policy
    target_entropy: float
    scaler: ActionScaler
    matmul_dtype: str  # as resolved (`auto` becomes float32 or bfloat16 here)
    settings: UpdateSettings  # what the update runs with (device collection compiles it into its chunks)


def build(config: SACConfig, obs_dim: int, act_dim: int, low: np.ndarray | None = None,
          high: np.ndarray | None = None, image_shape: tuple[int, int, int, int] | None = None,
          image_state_dim: int = 0) -> SACFunctions:
    """The jitted SAC functions for one config, space sizes and action bounds (default [-1, 1]). With
    `image_shape` (uint8 frame stacks [k, h, w, c]) an encoder turns them into `encoder_features` values first,
    followed by the `image_state_dim` state values the frames carry."""
    release_compiled_programs_near_map_limit()  # an agent's programs are compiled below: room for their code
    matmul_dtype = resolve_matmul_dtype(config.matmul_dtype)
    s = update_settings(config, act_dim, matmul_dtype, images=image_shape is not None, image_state_dim=image_state_dim)
    if image_shape is not None:
        obs_dim = config.encoder_features + image_state_dim
    scaler = ActionScaler(np.full(act_dim, -1.0) if low is None else low, np.ones(act_dim) if high is None else high)
    # one compiled call (cached across processes) instead of dozens of eager ops
    new_state = jax.jit(partial(assemble, s, config.alpha))

    def init(seed: int) -> SACState:
        rng = np.random.default_rng([seed, 0x5AC])
        actor, critic, actor_stats, critic_stats = fresh_networks(config, obs_dim, act_dim, rng)
        key = rng.integers(0, 2**32, 2, dtype=np.uint32)  # a raw PRNGKey
        encoder = fresh_encoder(config, image_shape, rng, image_state_dim)
        return new_state(actor, critic, key, actor_stats, critic_stats, encoder,
                         fresh_actor_head(config, encoder, rng))

    # Periodic resets (Nikishin et al. 2022, "The Primacy Bias in Deep RL"; D'Oro et al. 2023, SR-SAC):
    # new actor, critics, targets and their optimisers, drawn from the k-th reset's own seed; the replay
    # buffer, the entropy coefficient (with its optimiser), the key and the update counter carry over. An image
    # encoder is drawn afresh too.
    def reset(state: SACState, seed: int, k: int) -> SACState:
        rng = np.random.default_rng([seed, 0x5AC, k])
        networks = fresh_networks(config, obs_dim, act_dim, rng)
        encoder = fresh_encoder(config, image_shape, rng, image_state_dim)
        fresh = new_state(networks[0], networks[1], state.key, networks[2], networks[3], encoder,
                          fresh_actor_head(config, encoder, rng))
        return fresh._replace(log_alpha=state.log_alpha, alpha_opt=state.alpha_opt, n_updates=state.n_updates)

    return SACFunctions(
        init=init,
        reset=reset,
        update=partial(compiled_update, Program(s), numbers_of(s)),
        act=jax.jit(partial(act, s.policy, scaler, state_dim=image_state_dim, pixel_offset=config.pixel_offset)),
        act_deterministic=jax.jit(partial(act_deterministic, s.policy, state_dim=image_state_dim,
                                          pixel_offset=config.pixel_offset)),
        act_with_noise=jax.jit(partial(act_with_noise, s.policy, scaler, state_dim=image_state_dim,
                                       pixel_offset=config.pixel_offset)),
        policy=s.policy,
        target_entropy=s.target_entropy,
        scaler=scaler,
        matmul_dtype=matmul_dtype,
        settings=s,
    )
