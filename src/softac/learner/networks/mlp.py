"""The plain MLP (SAC's networks), optionally with LayerNorm before each hidden activation (RLPD) and dropout of
hidden units (DroQ). Parameters: a list of {"w", "b"} layers."""

from __future__ import annotations

import math

import jax
import numpy as np

from softac.learner.networks.entry import Network, Params
from softac.learner.networks.layers import ACTIVATIONS, dense, init_layer, layer_norm


def init_mlp(rng: np.random.Generator, sizes: list[int], init: str, out_gain: float = 1.0,
             norm: bool = False) -> Params:
    """An MLP with layer sizes [in, hidden..., out]; `norm` adds each layer's input normalisation (scale 1,
    bias 0)."""
    layers = []
    for i, (fan_in, fan_out) in enumerate(zip(sizes[:-1], sizes[1:])):
        last = i == len(sizes) - 2
        layer = init_layer(rng, fan_in, fan_out, init, out_gain if last else math.sqrt(2.0))
        if norm:
            layer.update(norm_scale=np.ones(fan_in, np.float32), norm_bias=np.zeros(fan_in, np.float32))
        layers.append(layer)
    return layers


def mlp(params: Params, x: jax.Array, activation: str, matmul_dtype: str = "float32",
        normalize: bool = False, masks: list[jax.Array] | None = None) -> jax.Array:
    """`normalize` puts a LayerNorm (no affine) before each hidden activation (Ball et al. 2023, RLPD):
    it keeps critics stable at high update-to-data ratios. `masks` (dropout_mask's, one per hidden layer) drop
    hidden units before it (DroQ, Hiraoka et al. 2022: dense, dropout, LayerNorm, activation)."""
    return dense(mlp_features(params, x, activation, matmul_dtype, normalize, masks), params[-1], matmul_dtype)


def mlp_features(params: Params, x: jax.Array, activation: str, matmul_dtype: str = "float32",
                 normalize: bool = False, masks: list[jax.Array] | None = None) -> jax.Array:
    """`mlp` up to the output layer's input: the last hidden layer's activations."""
    act = ACTIVATIONS[activation]
    for i, layer in enumerate(params[:-1]):
        h = dense(x, layer, matmul_dtype)
        if masks is not None:
            h = h * masks[i]
        x = act(layer_norm(h) if normalize else h)
    return x


def _features(params, stats, x, activation, matmul_dtype, normalize=False, masks=None, batch_renorm=None,
              train=False, renorm=False):
    return mlp_features(params, x, activation, matmul_dtype, normalize, masks), stats


def output_layer_mask(params: Params) -> Params:
    return [{k: (i == len(params) - 1 and k in ("w", "b")) for k in layer} for i, layer in enumerate(params)]


def parameters(in_dim: int, widths: list[int], out_dim: int) -> int:
    sizes = [in_dim, *widths, out_dim]
    return sum((a + 1) * b for a, b in zip(sizes[:-1], sizes[1:]))


MLP = Network(
    init=lambda rng, in_dim, widths, out_dim, init, out_gain: init_mlp(rng, [in_dim, *widths, out_dim], init, out_gain),
    features=_features, head=lambda params: params[-1], output_mask=output_layer_mask, parameters=parameters)
