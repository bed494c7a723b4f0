"""Image observations in the update (issue 44; DrQ, Kostrikov et al. 2021; DrQ-v2, Yarats et al. 2022): what
the actor and the critics read of a batch of frame stacks.

The critic loss trains the encoder; the next state's features are a target (stopped), and the actor reads the
step's features stopped, computed before the encoder moved, as DrQ-v2 does: the actor's gradient through a
shared encoder destabilises it (SAC-AE, Yarats et al. 2021). Each pass augments with its own random shift.
`sac.critic_step` runs these where `UpdateSettings.image` is set; vector observations skip them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import optax

from softac.learner.encoder import apply_head, encode_with_conv, random_shift, split_image_and_state, stack_channels
from softac.learner.losses import Batch


@dataclass(frozen=True)
class ImageSettings:
    """What the update needs of image observations: fixed for a config and an image shape."""
    encoder_tx: optax.GradientTransformation  # the encoder's optimiser (at the critics' rate)
    augment_pad: int = 0  # DrQ's random shift (pixels of padding)
    state_dim: int = 0  # state values packed beside each image (envs.pixels.ImageWithState)
    pixel_offset: float = 0.0  # subtracted from pixels scaled to [0, 1] (config pixel_range)
    target_encoder: bool = False  # the target critics read through a target copy of the encoder
    chunk: int = 0  # the update's batches go through the encoder in pieces of this many (0: whole)
    actor_head_tx: optax.GradientTransformation | None = None  # actor_encoder_head: the actor's head's optimiser


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


def encoded_batch(encoder: Any, batch: Batch, key: jax.Array, image: ImageSettings) -> tuple[Batch, Any]:
    """The batch's observations through `encoder`, each augmented (the same shifts for the same `key`), and what
    the actor step reads of them: their features, or with an actor head (their features, their conv outputs
    with the state values). The next observations' features are targets, stopped."""
    obs_key, next_key = jax.random.split(key)
    obs, conv = image_features_and_conv(encoder, batch.obs, image.state_dim, obs_key, image.augment_pad,
                                        image.chunk, image.pixel_offset)
    next_obs = jax.lax.stop_gradient(image_features(encoder, batch.next_obs, image.state_dim, next_key,
                                                    image.augment_pad, image.chunk, image.pixel_offset))
    return batch._replace(obs=obs, next_obs=next_obs), (obs, conv) if image.actor_head_tx is not None else obs


def target_encoded_batch(target_encoder: Any, batch: Batch, key: jax.Array, image: ImageSettings) -> Batch | None:
    """The batch as the target critics read it: through the target encoder, with the same shifts as the online
    pass (DrQ's target critic carries its own encoder copy, Polyak-averaged with it), stopped; None without a
    target encoder (the targets read the online features). XLA drops the observations' pass where only the
    next observations' is used (critics without batch renormalisation)."""
    if not jax.tree_util.tree_leaves(target_encoder):
        return None
    return jax.lax.stop_gradient(encoded_batch(target_encoder, batch, key, image)[0])
