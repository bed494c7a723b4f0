"""The image encoder and its augmentation (issue 44): what turns a stack of camera frames into the vector that
actor and critics read.

The encoder is DrQ's (Kostrikov et al. 2021, "Image Augmentation Is All You Need"; Yarats et al. 2021, SAC-AE):
four 3x3 convolutions of `channels` filters (strides 2, 1, 1, 1, no padding, ReLU), then a linear layer to
`features` units, a LayerNorm (with scale and bias) and tanh. Pixels go in as uint8 and are scaled inside to
[0, 1] (DrQ's obs / 255, and SB3's), or to [-0.5, 0.5] with `pixel_offset` 0.5 (DrQ-v2's; config `pixel_range`).
One encoder serves actor and critics; the critic loss alone trains it and the actor reads its output stopped
(`jax.lax.stop_gradient`), as in DrQ and DrQ-v2: the actor's gradient through a shared encoder destabilises it
(SAC-AE, sec. 4).

`random_shift` is DrQ's augmentation (its K = M = 1 form): each image padded by `pad` pixels (edge copies)
and cropped back at a uniformly random offset, a fresh shift per image per pass.

The encoder takes channels-last images, [batch, height, width, channels]; `stack_channels` lays a batch of
frame stacks ([batch, k, h, w, c], as the envs and the replay buffer hold them) out so, the frames one after
the other along the channels, oldest first.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from softac.learner.networks.layers import orthogonal
from softac.envs.pixels import state_rows

Params = Any

CONV_STRIDES = (2, 1, 1, 1)
KERNEL = 3
LN_EPS = 1e-5  # torch.nn.LayerNorm's, which DrQ's encoder uses


def conv_output_size(size: int, strides: tuple[int, ...] = CONV_STRIDES) -> int:
    """An image side after the convolutions (no padding): 84 -> 41 -> 39 -> 37 -> 35."""
    for stride in strides:
        size = (size - KERNEL) // stride + 1
    return size


def smallest_image(strides: tuple[int, ...] = CONV_STRIDES) -> int:
    """The smallest side the convolutions can take (one pixel out)."""
    size = 1
    for stride in reversed(strides):
        size = (size - 1) * stride + KERNEL
    return size


def init_encoder(rng: np.random.Generator, image_shape: tuple[int, int, int], channels: int = 32,
                 features: int = 50) -> Params:
    """DrQ's initialisation: each convolution delta-orthogonal (an orthogonal matrix with ReLU's gain at the
    kernel's centre, zeros elsewhere; Xiao et al. 2018), the linear layer orthogonal, biases zero, LayerNorm
    scale 1 and bias 0."""
    height, width, in_channels = image_shape
    convs = []
    for fan_in in (in_channels, *[channels] * (len(CONV_STRIDES) - 1)):
        w = np.zeros((KERNEL, KERNEL, fan_in, channels), np.float32)
        w[KERNEL // 2, KERNEL // 2] = orthogonal(rng, fan_in, channels, math.sqrt(2.0))
        convs.append({"w": w, "b": np.zeros(channels, np.float32)})
    return {"convs": convs, "head": init_head(rng, conv_output_size(height) * conv_output_size(width) * channels,
                                              features)}


def init_head(rng: np.random.Generator, flat: int, features: int) -> Params:
    """The encoder's head (Linear from the `flat` conv outputs to `features`, LayerNorm, tanh): orthogonal
    weights, zero biases, LayerNorm scale 1 and bias 0 (DrQ's)."""
    return {"w": orthogonal(rng, flat, features, 1.0), "b": np.zeros(features, np.float32),
            "ln_scale": np.ones(features, np.float32), "ln_bias": np.zeros(features, np.float32)}


def encoder_parameters(image_shape: tuple[int, int, int], channels: int = 32, features: int = 50) -> int:
    """The encoder's parameter count (for the memory check before anything is allocated)."""
    height, width, in_channels = image_shape
    convs = sum((KERNEL * KERNEL * fan_in + 1) * channels
                for fan_in in (in_channels, *[channels] * (len(CONV_STRIDES) - 1)))
    return convs + head_parameters(conv_output_size(height) * conv_output_size(width) * channels, features)


def head_parameters(flat: int, features: int) -> int:
    """A head's parameter count: Linear `flat` -> `features` with its bias, LayerNorm's scale and bias."""
    return (flat + 1) * features + 2 * features


def stack_channels(stacks: jax.Array) -> jax.Array:
    """[batch, k, h, w, c] frame stacks as [batch, h, w, k * c] images (on the device: the host moves whole
    frames only)."""
    batch, k, height, width, channels = stacks.shape
    return jnp.moveaxis(stacks, 1, 3).reshape(batch, height, width, k * channels)


def split_image_and_state(stacks: jax.Array, state_dim: int) -> tuple[jax.Array, jax.Array | None]:
    """Frame stacks [batch, k, h + r, w, c] that carry `state_dim` state values in each frame's last r rows
    (softac.envs.pixels.ImageWithState) as the images [batch, k, h, w, c] and the newest frame's state [batch,
    state_dim] (float32, its bytes as packed); `state_dim` 0: the stacks as they are, and None."""
    if state_dim == 0:
        return stacks, None
    batch, _, height, width, channels = stacks.shape
    rows = state_rows(state_dim, width, channels)
    raw = stacks[:, -1, height - rows:].reshape(batch, -1)[:, : 4 * state_dim].reshape(batch, state_dim, 4)
    return stacks[:, :, : height - rows], jax.lax.bitcast_convert_type(raw, jnp.float32)


def image_only_shape(stack_shape: tuple[int, int, int, int], state_dim: int) -> tuple[int, int, int, int]:
    """The images' stack shape [k, h, w, c] within frame stacks of `stack_shape` that carry `state_dim` values."""
    k, height, width, channels = stack_shape
    return k, height - state_rows(state_dim, width, channels), width, channels


def stacked_image_shape(stack_shape: tuple[int, int, int, int]) -> tuple[int, int, int]:
    """The encoder's input shape [h, w, k * c] for frame stacks of shape [k, h, w, c]."""
    k, height, width, channels = stack_shape
    return height, width, k * channels


def scale_pixels(images: jax.Array, pixel_offset: float = 0.0) -> jax.Array:
    """uint8 pixels to float32 in [-pixel_offset, 1 - pixel_offset]: [0, 1] (DrQ's) at 0, [-0.5, 0.5] (DrQ-v2's)
    at 0.5. At [0, 1] a black background is zero and the convolutions (zero biases at the start) answer only to what is
    drawn; at [-0.5, 0.5] the background of a dark scene (MuJoCo's InvertedPendulum) gave every image the same
    large activations, its pole a small part of them, and the critic could not tell the pole's angles apart."""
    return images.astype(jnp.float32) / 255.0 - pixel_offset  # exact at 0: x - 0.0 is x


def conv_features(params: Params, images: jax.Array, pixel_offset: float = 0.0) -> jax.Array:
    """The convolutions' output, flattened: [batch, conv_output_size(h) * conv_output_size(w) * channels], of
    uint8 images scaled by `scale_pixels` at `pixel_offset`."""
    x = scale_pixels(images, pixel_offset)
    for layer, stride in zip(params["convs"], CONV_STRIDES):
        x = jax.lax.conv_general_dilated(x, layer["w"], (stride, stride), "VALID",
                                         dimension_numbers=("NHWC", "HWIO", "NHWC"))
        x = jax.nn.relu(x + layer["b"])
    return x.reshape(x.shape[0], -1)


def apply_head(head: Params, conv: jax.Array) -> jax.Array:
    """The flattened conv outputs [batch, flat] through the head: features [batch, features] in (-1, 1)."""
    h = conv @ head["w"] + head["b"]
    mean = jnp.mean(h, axis=-1, keepdims=True)
    var = jnp.mean(jnp.square(h - mean), axis=-1, keepdims=True)
    h = (h - mean) * jax.lax.rsqrt(var + LN_EPS) * head["ln_scale"] + head["ln_bias"]
    return jnp.tanh(h)


def encode(params: Params, images: jax.Array, chunk: int = 0, pixel_offset: float = 0.0) -> jax.Array:
    """uint8 images [batch, h, w, c] to features [batch, features] in (-1, 1). `chunk` > 0: the batch goes
    through in pieces of that many images, each recomputed in the backward pass (`chunked_encode`).
    `pixel_offset`: `scale_pixels`'."""
    return encode_with_conv(params, images, chunk, pixel_offset)[0]


def encode_with_conv(params: Params, images: jax.Array, chunk: int = 0,
                     pixel_offset: float = 0.0) -> tuple[jax.Array, jax.Array]:
    """`encode`'s features and the flattened conv outputs they came from (what a second head reads)."""
    if 0 < chunk < images.shape[0]:
        return chunked_encode(params, images, chunk, pixel_offset)
    return _features_and_conv(params, images, pixel_offset)


def _features_and_conv(params: Params, images: jax.Array, pixel_offset: float = 0.0) -> tuple[jax.Array, jax.Array]:
    conv = conv_features(params, images, pixel_offset)
    return apply_head(params["head"], conv), conv


def chunked_encode(params: Params, images: jax.Array, chunk: int,
                   pixel_offset: float = 0.0) -> tuple[jax.Array, jax.Array]:
    """`encode_with_conv` of the batch in pieces of `chunk` images, each piece's activations recomputed for its backward
    pass (jax.checkpoint). Every image's features are its own, so the result is `encode`'s; on a CPU it is
    faster: XLA's CPU convolutions slow per image as the batch's feature maps outgrow the caches (one AMD EPYC
    core, a whole SAC update on 3 frames of 48x48: 58 ms at batch 32 and 578 ms at 128 whole, 44 and 229 ms
    in pieces of 8; 84x84, batch 32: 478 and 252 ms; docs/performance.md)."""
    piece = jax.checkpoint(_features_and_conv, static_argnums=(2,))
    parts = [piece(params, part, pixel_offset)
             for part in jnp.split(images, list(range(chunk, images.shape[0], chunk)))]
    return jnp.concatenate([f for f, _ in parts]), jnp.concatenate([c for _, c in parts])


def random_shift(images: jax.Array, key: jax.Array, pad: int) -> jax.Array:
    """Each image of [batch, h, w, c] shifted by its own uniform offset in [-pad, pad] along each axis, the
    border filled with copies of the edge pixels (DrQ's random shift); pad 0 returns the images."""
    if pad == 0:
        return images
    batch, height, width, channels = images.shape
    padded = jnp.pad(images, ((0, 0), (pad, pad), (pad, pad), (0, 0)), mode="edge")
    offsets = jax.random.randint(key, (batch, 2), 0, 2 * pad + 1)

    def crop(image: jax.Array, offset: jax.Array) -> jax.Array:
        return jax.lax.dynamic_slice(image, (offset[0], offset[1], 0), (height, width, channels))

    return jax.vmap(crop)(padded, offsets)
