"""The forward pass of a policy exported with `softac export RUN --format numpy`, in NumPy alone.

This module imports nothing but NumPy, so it can be copied into any project:

    params = dict(np.load("policy.npz"))
    action = policy_forward(params, obs)   # obs [obs_dim] or [batch, obs_dim]; action in the env's bounds
                                           # (a dict env's obs: the dict, or a dict of batches; an image
                                           # agent's: uint8 frame stacks [k, h, w, c] or [batch, k, h, w, c])

policy.npz holds
    obs_mean, obs_std, obs_clip   float32: observation normalisation, only when the run had obs_norm
    w0, b0, ..., wN, bN           float32: the actor's layers; the last gives the mean action before tanh
                                  (CrossQ's batch renormalisation is folded into the weights)
    bf16                          int8, one per layer, only for runs with bf16 matmuls: 1 where the layer
                                  multiplies in bfloat16 (its input is rounded to bf16; its w already is)
    network                       only for a SimBa actor (network=simba, Lee et al. 2024), "simba"; in place of
                                  w0 ... bN it then has, float32:
      embed_w, embed_b            the linear embedding
      blockI_ln_scale, _ln_bias,  residual block I: x + (act(LayerNorm(x) @ blockI_1_w + blockI_1_b))
      blockI_1_w, _1_b, _2_w, _2_b    @ blockI_2_w + blockI_2_b
      head_ln_scale, head_ln_bias, the final LayerNorm and the output layer (the mean action before tanh)
      head_w, head_b
      ln_eps                      the LayerNorms' epsilon
                                  (bf16, if there, marks the dense layers in this order: embed, the blocks'
                                  _1 and _2, head)
                                  for a FlashSAC actor (network=flashsac, Kim et al. 2026), "flashsac"; in
                                  place of w0 ... bN it then has, float32:
      in_mean, in_inv_std,        the input's batch normalisation ((x - mean) * inv_std * scale + bias)
      in_scale, in_bias
      embed_w                     the embedding (no bias)
      blockI_1_w, blockI_n1_*,    block I: x + act(n2(act(n1(x @ blockI_1_w)) @ blockI_2_w)), n1 and n2 batch
      blockI_2_w, blockI_n2_*       normalisations as in_* (_mean, _inv_std, _scale, _bias)
      rms_scale, rms_eps          the RMSNorm: x / sqrt(mean(x^2) + eps) * scale
      head_w, head_b              the output layer (the mean action before tanh)
                                  (bf16, if there, marks the kernels in this order: embed, the blocks' _1 and
                                  _2, head)
    nI_mean, nI_inv_std,          float32, only for a CrossQ layer I that multiplies in bf16: its input's batch
    nI_scale, nI_bias             renormalisation, kept apart (folded into w, bf16 would round other values);
                                  for an XQC actor (network=bn_mlp) n0_* on the input, always
    pI_mean, pI_inv_std,          float32, only for an XQC actor (network=bn_mlp): layer I's batch
    pI_scale, pI_bias             normalisation after its matmul, before the activation
    mean_clip                     float32, only for gSDE policies: the mean is clipped to [-mean_clip, mean_clip]
                                  before tanh
    action_low, action_high       float32: the env's action bounds
    activation                    the hidden activation's name: relu, tanh, elu, gelu or silu
    hidden_ln_eps                 float32, only for an MLP actor with LayerNorm (actor_layer_norm): the epsilon
                                  of the LayerNorm (no scale or bias) before each hidden activation
    hidden_ln_after               int8 1, only where that LayerNorm comes after each hidden activation instead
                                  (layer_norm_position after)
    lnI_scale, lnI_bias           float32, only with layer_norm_affine: hidden layer I's LayerNorm's learned
                                  scale and bias
    obs_keys, obs_key_sizes       only for envs that observe a dict (goal envs): its keys in the order the
                                  flat observation concatenates them, and each one's size (beside an image:
                                  the state keys, after the encoder's features)
    image_shape                   int64 [k, h, w, c], only for image agents: the frame stacks they take
                                  (uint8, channels-last, oldest frame first), and then:
    conv_strides, convI_w, convI_b  the encoder's convolutions (3x3, HWIO weights, no padding, ReLU)
    enc_w, enc_b, enc_ln_scale,   its linear layer, LayerNorm (eps 1e-5) and tanh
    enc_ln_bias
    image_key                     only for an image beside state values: the dict key of the image
and, for the record, env_id, step (the checkpoint's env step) and softac_version.
"""

from __future__ import annotations

import numpy as np

SQRT_2_OVER_PI = np.float32(np.sqrt(2.0 / np.pi))


def gelu(x: np.ndarray) -> np.ndarray:
    """GELU's tanh approximation, the form jax.nn.gelu computes by default (approximate=True)."""
    return x * (0.5 * (1.0 + np.tanh(SQRT_2_OVER_PI * (x + 0.044715 * (x * x * x)))))


def elu(x: np.ndarray) -> np.ndarray:
    return np.where(x > 0, x, np.expm1(np.minimum(x, 0)))


def silu(x: np.ndarray) -> np.ndarray:
    """x * sigmoid(x), as jax.nn.silu, the sigmoid from exp(-|x|) so that no exp overflows."""
    e = np.exp(-np.abs(x))
    return x * np.where(x >= 0, np.float32(1.0), e) / (np.float32(1.0) + e)


ACTIVATIONS = {"relu": lambda x: np.maximum(x, 0), "tanh": np.tanh, "elu": elu, "gelu": gelu, "silu": silu}


def layer_count(params: dict) -> int:
    return sum(1 for key in params if key.startswith("w") and key[1:].isdigit())


def round_bf16(x: np.ndarray) -> np.ndarray:
    """`x` rounded to bfloat16's 8 significant bits (to nearest, ties to even), kept in float32: what a
    cast to bf16 and back does, as the hidden layers of a run trained with bf16 matmuls see their inputs."""
    bits = np.ascontiguousarray(x, np.float32).view(np.uint32)
    return ((bits + np.uint32(0x7FFF) + ((bits >> 16) & np.uint32(1))) & np.uint32(0xFFFF0000)).view(np.float32)


FLASHSAC_RMS_EPS = 1e-6  # FlashSAC's RMSNorm epsilon (networks/flashsac.py)


def network_name(params: dict) -> str:
    return str(params.get("network", "mlp"))


def is_simba(params: dict) -> bool:
    return network_name(params) == "simba"


def simba_block_count(params: dict) -> int:
    return sum(1 for key in params if key.startswith("block") and key.endswith("_ln_scale"))


def flashsac_block_count(params: dict) -> int:
    return sum(1 for key in params if key.startswith("block") and key.endswith("_1_w"))


def dense_bf16_flags(params: dict) -> list[bool]:
    """Whether each dense layer of the actor multiplies in bfloat16, in the order the forward pass takes them
    (an MLP's w0 ... wN; a SimBa or FlashSAC actor's embed, each block's _1 and _2, head): all False without
    `bf16`."""
    name = network_name(params)
    blocks = simba_block_count(params) if name == "simba" else flashsac_block_count(params)
    count = 2 * blocks + 2 if name in ("simba", "flashsac") else layer_count(params)
    return [bool(flag) for flag in params.get("bf16", np.zeros(count, np.int8))]


def layer_norm(x: np.ndarray, scale: np.ndarray, bias: np.ndarray, eps: np.float32) -> np.ndarray:
    """LayerNorm over the last axis, as softac's JAX code computes it: (x - mean) / sqrt(var + eps) * scale + bias."""
    centred = x - x.mean(axis=-1, keepdims=True)
    inv_std = np.float32(1.0) / np.sqrt((centred * centred).mean(axis=-1, keepdims=True) + np.float32(eps))
    return centred * inv_std * scale + bias


def flat_observation(params: dict, obs) -> np.ndarray:
    """A dict observation (or a dict of batches) as the flat vector the actor takes; an array as it is."""
    if not isinstance(obs, dict):
        return np.asarray(obs, np.float32)
    keys, sizes = [str(k) for k in params["obs_keys"]], [int(n) for n in params["obs_key_sizes"]]
    parts = [np.asarray(obs[k], np.float32) for k in keys]
    if all(p.size == n for p, n in zip(parts, sizes)):
        return np.concatenate([p.reshape(-1) for p in parts])
    return np.concatenate([p.reshape(len(p), n) for p, n in zip(parts, sizes)], axis=1)


def conv2d(x: np.ndarray, w: np.ndarray, stride: int) -> np.ndarray:
    """A VALID convolution (cross-correlation) of images [batch, h, w, c] with HWIO weights, in float32."""
    kh, kw = w.shape[:2]
    windows = np.lib.stride_tricks.sliding_window_view(x, (kh, kw), axis=(1, 2))[:, ::stride, ::stride]
    return np.tensordot(windows, w, axes=([3, 4, 5], [2, 0, 1]))  # windows: [batch, h', w', c, kh, kw]


def encoded(params: dict, obs) -> np.ndarray:
    """An image agent's actor input: the encoder's features of uint8 frame stacks [batch, k, h, w, c] (or one
    [k, h, w, c]), followed, for an image beside state values (a dict), by the state keys' values."""
    state = None
    if isinstance(obs, dict):
        image = np.asarray(obs[str(params["image_key"])], np.uint8)
        state = flat_observation(params, {k: v for k, v in obs.items() if k != str(params["image_key"])})
    else:
        image = np.asarray(obs, np.uint8)
    k, height, width, channels = (int(n) for n in params["image_shape"])
    stacks = image.reshape(-1, k, height, width, channels)
    x = np.moveaxis(stacks, 1, 3).reshape(len(stacks), height, width, k * channels)  # frames along the channels
    offset = params["pixel_offset"] if "pixel_offset" in params else 0.5  # files from before pixel_range: 0.5
    x = x.astype(np.float32) / np.float32(255.0) - np.float32(offset)
    for i, stride in enumerate(params["conv_strides"]):
        x = np.maximum(conv2d(x, params[f"conv{i}_w"], int(stride)) + params[f"conv{i}_b"], 0)
    h = x.reshape(len(x), -1) @ params["enc_w"] + params["enc_b"]
    features = np.tanh(layer_norm(h, params["enc_ln_scale"], params["enc_ln_bias"], np.float32(1e-5)))
    return features if state is None else np.concatenate([features, state.reshape(len(features), -1)], axis=1)


def dense(x: np.ndarray, w: np.ndarray, b: np.ndarray, bf16: bool) -> np.ndarray:
    return (round_bf16(x) if bf16 else x) @ w + b


def mlp_forward(params: dict, x: np.ndarray) -> np.ndarray:
    """The MLP actor's mean action before tanh."""
    activation = ACTIVATIONS[str(params["activation"])]
    bf16 = dense_bf16_flags(params)
    for i in range(len(bf16)):
        if f"n{i}_mean" in params:
            x = (x - params[f"n{i}_mean"]) * params[f"n{i}_inv_std"] * params[f"n{i}_scale"] + params[f"n{i}_bias"]
        x = dense(x, params[f"w{i}"], params[f"b{i}"], bf16[i])
        if f"p{i}_mean" in params:
            x = (x - params[f"p{i}_mean"]) * params[f"p{i}_inv_std"] * params[f"p{i}_scale"] + params[f"p{i}_bias"]
        ln_after = bool(params.get("hidden_ln_after", False))
        if i < len(bf16) - 1 and "hidden_ln_eps" in params and not ln_after:
            x = layer_norm(x, params.get(f"ln{i}_scale", np.float32(1.0)), params.get(f"ln{i}_bias", np.float32(0.0)),
                           params["hidden_ln_eps"])
        if i < len(bf16) - 1:
            x = activation(x)
        if i < len(bf16) - 1 and "hidden_ln_eps" in params and ln_after:
            x = layer_norm(x, params.get(f"ln{i}_scale", np.float32(1.0)), params.get(f"ln{i}_bias", np.float32(0.0)),
                           params["hidden_ln_eps"])
    return x


def simba_forward(params: dict, x: np.ndarray) -> np.ndarray:
    """The SimBa actor's mean action before tanh."""
    activation = ACTIVATIONS[str(params["activation"])]
    eps, n_blocks = params["ln_eps"], simba_block_count(params)
    bf16 = iter(dense_bf16_flags(params))
    x = dense(x, params["embed_w"], params["embed_b"], next(bf16))
    for i in range(n_blocks):
        h = layer_norm(x, params[f"block{i}_ln_scale"], params[f"block{i}_ln_bias"], eps)
        h = activation(dense(h, params[f"block{i}_1_w"], params[f"block{i}_1_b"], next(bf16)))
        x = x + dense(h, params[f"block{i}_2_w"], params[f"block{i}_2_b"], next(bf16))
    x = layer_norm(x, params["head_ln_scale"], params["head_ln_bias"], eps)
    return dense(x, params["head_w"], params["head_b"], next(bf16))


def batch_norm(x: np.ndarray, params: dict, prefix: str) -> np.ndarray:
    """A batch normalisation in evaluation mode: (x - mean) * inv_std * scale + bias, as softac's JAX code."""
    return ((x - params[f"{prefix}_mean"]) * params[f"{prefix}_inv_std"] * params[f"{prefix}_scale"]
            + params[f"{prefix}_bias"])


def flashsac_forward(params: dict, x: np.ndarray) -> np.ndarray:
    """The FlashSAC actor's mean action before tanh."""
    activation = ACTIVATIONS[str(params["activation"])]
    bf16 = iter(dense_bf16_flags(params))
    zero = np.float32(0.0)
    x = dense(batch_norm(x, params, "in"), params["embed_w"], zero, next(bf16))
    for i in range(flashsac_block_count(params)):
        h = activation(batch_norm(dense(x, params[f"block{i}_1_w"], zero, next(bf16)), params, f"block{i}_n1"))
        h = activation(batch_norm(dense(h, params[f"block{i}_2_w"], zero, next(bf16)), params, f"block{i}_n2"))
        x = h + x
    inv_rms = np.float32(1.0) / np.sqrt((x * x).mean(axis=-1, keepdims=True) + params["rms_eps"])
    return dense(x * inv_rms * params["rms_scale"], params["head_w"], params["head_b"], next(bf16))


def policy_forward(params: dict, obs: np.ndarray) -> np.ndarray:
    """The deterministic action for one observation or a batch: tanh of the actor's mean, scaled to bounds."""
    images = "image_shape" in params
    x = encoded(params, obs) if images else flat_observation(params, obs)
    if "obs_mean" in params:
        clip = params["obs_clip"]
        x = np.clip((x - params["obs_mean"]) / params["obs_std"], -clip, clip)
    forward = {"simba": simba_forward, "flashsac": flashsac_forward}.get(network_name(params), mlp_forward)
    x = forward(params, x)
    if "mean_clip" in params:
        x = np.clip(x, -params["mean_clip"], params["mean_clip"])
    low, high = params["action_low"], params["action_high"]
    action = np.clip((high + low) / 2.0 + (high - low) / 2.0 * np.tanh(x), low, high)
    # the encoder works on batches: one frame stack [k, h, w, c] in, one action out
    single = images and np.ndim(obs[str(params["image_key"])] if isinstance(obs, dict) else obs) == 4
    return action[0] if single else action
