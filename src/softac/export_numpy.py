"""The forward pass of a policy exported with `softac export RUN --format numpy`, in NumPy alone.

This module imports nothing but NumPy, so it can be copied into any project:

    params = dict(np.load("policy.npz"))
    action = policy_forward(params, obs)   # obs [obs_dim] or [batch, obs_dim]; action in the env's bounds
                                           # (a dict env's obs: the dict, or a dict of batches)

policy.npz holds
    obs_mean, obs_std, obs_clip   float32: observation normalisation, only when the run had obs_norm
    w0, b0, ..., wN, bN           float32: the actor's layers; the last gives the mean action before tanh
                                  (CrossQ's batch renormalisation is folded into the weights)
    bf16                          int8, one per layer, only for runs with bf16 matmuls: 1 where the layer
                                  multiplies in bfloat16 (its input is rounded to bf16; its w already is)
    nI_mean, nI_inv_std,          float32, only for a CrossQ layer I that multiplies in bf16: its input's batch
    nI_scale, nI_bias             renormalisation, kept apart (folded into w, bf16 would round other values)
    mean_clip                     float32, only for gSDE policies: the mean is clipped to [-mean_clip, mean_clip]
                                  before tanh
    action_low, action_high       float32: the env's action bounds
    activation                    the hidden activation's name: relu, tanh, elu or gelu
    obs_keys, obs_key_sizes       only for envs that observe a dict (goal envs): its keys in the order the
                                  flat observation concatenates them, and each one's size
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


ACTIVATIONS = {"relu": lambda x: np.maximum(x, 0), "tanh": np.tanh, "elu": elu, "gelu": gelu}


def layer_count(params: dict) -> int:
    return sum(1 for key in params if key.startswith("w") and key[1:].isdigit())


def round_bf16(x: np.ndarray) -> np.ndarray:
    """`x` rounded to bfloat16's 8 significant bits (to nearest, ties to even), kept in float32: what a
    cast to bf16 and back does, as the hidden layers of a run trained with bf16 matmuls see their inputs."""
    bits = np.ascontiguousarray(x, np.float32).view(np.uint32)
    return ((bits + np.uint32(0x7FFF) + ((bits >> 16) & np.uint32(1))) & np.uint32(0xFFFF0000)).view(np.float32)


def flat_observation(params: dict, obs) -> np.ndarray:
    """A dict observation (or a dict of batches) as the flat vector the actor takes; an array as it is."""
    if not isinstance(obs, dict):
        return np.asarray(obs, np.float32)
    keys, sizes = [str(k) for k in params["obs_keys"]], [int(n) for n in params["obs_key_sizes"]]
    parts = [np.asarray(obs[k], np.float32) for k in keys]
    if all(p.size == n for p, n in zip(parts, sizes)):
        return np.concatenate([p.reshape(-1) for p in parts])
    return np.concatenate([p.reshape(len(p), n) for p, n in zip(parts, sizes)], axis=1)


def policy_forward(params: dict, obs: np.ndarray) -> np.ndarray:
    """The deterministic action for one observation or a batch: tanh of the actor's mean, scaled to bounds."""
    x = flat_observation(params, obs)
    if "obs_mean" in params:
        clip = params["obs_clip"]
        x = np.clip((x - params["obs_mean"]) / params["obs_std"], -clip, clip)
    activation = ACTIVATIONS[str(params["activation"])]
    n_layers = layer_count(params)
    bf16 = params.get("bf16", np.zeros(n_layers, np.int8))
    for i in range(n_layers):
        if f"n{i}_mean" in params:
            x = (x - params[f"n{i}_mean"]) * params[f"n{i}_inv_std"] * params[f"n{i}_scale"] + params[f"n{i}_bias"]
        if bf16[i]:
            x = round_bf16(x)
        x = x @ params[f"w{i}"] + params[f"b{i}"]
        if i < n_layers - 1:
            x = activation(x)
    if "mean_clip" in params:
        x = np.clip(x, -params["mean_clip"], params["mean_clip"])
    low, high = params["action_low"], params["action_high"]
    return np.clip((high + low) / 2.0 + (high - low) / 2.0 * np.tanh(x), low, high)
