"""Actor and critic networks as plain JAX pytrees.

Parameters are lists of {"w", "b"} dicts, one per layer. The critic ensemble
holds every critic's parameters stacked on a leading axis and is evaluated
with one `jax.vmap`, so n critics cost one batched matmul per layer.
"""

from __future__ import annotations

from typing import Any, Callable

import math

import jax
import jax.numpy as jnp

Params = Any

ACTIVATIONS: dict[str, Callable[[jax.Array], jax.Array]] = {
    "relu": jax.nn.relu,
    "tanh": jnp.tanh,
    "elu": jax.nn.elu,
    "gelu": jax.nn.gelu,
}


def _init_layer(key: jax.Array, fan_in: int, fan_out: int, init: str, gain: float) -> dict:
    wkey, bkey = jax.random.split(key)
    if init == "orthogonal":
        w = jax.nn.initializers.orthogonal(scale=gain)(wkey, (fan_in, fan_out), jnp.float32)
        b = jnp.zeros((fan_out,), jnp.float32)
    else:  # PyTorch nn.Linear's default: U(-1/sqrt(fan_in), 1/sqrt(fan_in)) for weights and biases
        bound = 1.0 / math.sqrt(fan_in)
        w = jax.random.uniform(wkey, (fan_in, fan_out), jnp.float32, -bound, bound)
        b = jax.random.uniform(bkey, (fan_out,), jnp.float32, -bound, bound)
    return {"w": w, "b": b}


def init_mlp(key: jax.Array, sizes: list[int], init: str, out_gain: float = 1.0) -> Params:
    """An MLP with layer sizes [in, hidden..., out]."""
    keys = jax.random.split(key, len(sizes) - 1)
    layers = []
    for i, (fan_in, fan_out) in enumerate(zip(sizes[:-1], sizes[1:])):
        last = i == len(sizes) - 2
        gain = out_gain if last else math.sqrt(2.0)
        layers.append(_init_layer(keys[i], fan_in, fan_out, init, gain))
    return layers


def mlp(params: Params, x: jax.Array, activation: str) -> jax.Array:
    act = ACTIVATIONS[activation]
    for layer in params[:-1]:
        x = act(x @ layer["w"] + layer["b"])
    last = params[-1]
    return x @ last["w"] + last["b"]


def init_actor(key: jax.Array, obs_dim: int, act_dim: int, hidden: list[int], init: str) -> Params:
    """The actor outputs [mean, log_std] for each action dimension."""
    # a small last layer starts the policy near zero mean, as in SB3/CleanRL practice with orthogonal init
    return init_mlp(key, [obs_dim, *hidden, 2 * act_dim], init, out_gain=0.01)


def init_critics(key: jax.Array, obs_dim: int, act_dim: int, hidden: list[int], init: str, n: int) -> Params:
    """n critics Q(s, a), parameters stacked on a leading axis of size n."""
    keys = jax.random.split(key, n)
    return jax.vmap(lambda k: init_mlp(k, [obs_dim + act_dim, *hidden, 1], init))(keys)


def critics_apply(params: Params, obs: jax.Array, actions: jax.Array, activation: str) -> jax.Array:
    """Q-values of every critic: shape [n_critics, batch]."""
    x = jnp.concatenate([obs, actions], axis=-1)
    q = jax.vmap(lambda p: mlp(p, x, activation))(params)
    return q[..., 0]
