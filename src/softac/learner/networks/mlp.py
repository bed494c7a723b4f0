"""The plain MLP (SAC's networks), optionally with LayerNorm before each hidden activation (RLPD) or after it
(Brax), and dropout of hidden units (DroQ). Parameters: a list of {"w", "b"} layers."""

from __future__ import annotations

import math
from typing import Any

import jax
import numpy as np

from softac.learner.networks import onnx_layers
from softac.learner.networks.entry import ActorExport, Network, Params
from softac.learner.networks.layers import ACTIVATIONS, compiled_in_bf16, dense, init_layer, layer_norm
from softac.learner.numpy_forward import dense_bf16_flags, round_bf16


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


def with_layer_norm_affine(params: Params) -> Params:
    """Each hidden layer of an MLP (or a stacked ensemble of them) given its LayerNorm's scale (1) and bias (0), the
    affine Flax's LayerNorm learns (layer_norm_affine): drawn from no generator, so the weights stay as drawn."""
    def add(layer: dict) -> dict:
        shape = np.shape(layer["b"])
        return {**layer, "ln_scale": np.ones(shape, np.float32), "ln_bias": np.zeros(shape, np.float32)}

    return [add(layer) for layer in params[:-1]] + [params[-1]]


def _normed(h: jax.Array, layer: dict) -> jax.Array:
    """A hidden layer's LayerNorm, with its learned scale and bias where the layer has them."""
    h = layer_norm(h)
    return h * layer["ln_scale"] + layer["ln_bias"] if "ln_scale" in layer else h


def mlp(params: Params, x: jax.Array, activation: str, matmul_dtype: str = "float32",
        normalize: bool | str = False, masks: list[jax.Array] | None = None) -> jax.Array:
    """`normalize` puts a LayerNorm (no affine) before each hidden activation (True or "before": Ball et al. 2023,
    RLPD; it keeps critics stable at high update-to-data ratios) or after it ("after": Brax's MLP). `masks` (dropout_mask's, one per hidden layer) drop
    hidden units before it (DroQ, Hiraoka et al. 2022: dense, dropout, LayerNorm, activation)."""
    return dense(mlp_features(params, x, activation, matmul_dtype, normalize, masks), params[-1], matmul_dtype)


def mlp_features(params: Params, x: jax.Array, activation: str, matmul_dtype: str = "float32",
                 normalize: bool | str = False, masks: list[jax.Array] | None = None) -> jax.Array:
    """`mlp` up to the output layer's input: the last hidden layer's activations (LayerNormed, with "after")."""
    act = ACTIVATIONS[activation]
    for i, layer in enumerate(params[:-1]):
        h = dense(x, layer, matmul_dtype)
        if masks is not None:
            h = h * masks[i]
        if normalize == "after":
            x = _normed(act(h), layer)
        else:
            x = act(_normed(h, layer) if normalize else h)
    return x


def _features(params, stats, x, activation, matmul_dtype, normalize=False, masks=None, batch_renorm=None,
              train=False, renorm=False):
    return mlp_features(params, x, activation, matmul_dtype, normalize, masks), stats


def output_layer_mask(params: Params) -> Params:
    return [{k: (i == len(params) - 1 and k in ("w", "b")) for k in layer} for i, layer in enumerate(params)]


def parameters(in_dim: int, widths: list[int], out_dim: int) -> int:
    sizes = [in_dim, *widths, out_dim]
    return sum((a + 1) * b for a, b in zip(sizes[:-1], sizes[1:]))


# ---- export (softac export; numpy_forward.mlp_forward runs it) ----------------------------------------

def _batch_renorm_steps(layer: dict, stats: dict, eps: float) -> dict[str, np.ndarray]:
    """A layer input's batch renormalisation as networks.BatchRenorm computes it in evaluation mode, step by
    step in float32 ((x - mean) * inv_std * scale + bias, inv_std from JAX's own rsqrt): the values a bf16
    layer then rounds are JAX's to the last bit, so the rounding is too."""
    inv_std = jax.lax.rsqrt(jax.numpy.asarray(stats["var"], np.float32) + np.float32(eps))
    return {"mean": np.asarray(stats["mean"], np.float32), "inv_std": np.asarray(inv_std, np.float32),
            "scale": np.asarray(layer["norm_scale"], np.float32), "bias": np.asarray(layer["norm_bias"], np.float32)}


def _fold_batch_renorm(layer: dict, stats: dict, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """(w, b) of one dense layer with its input's batch renormalisation (evaluation mode: running statistics)
    folded in: ((x - mean) / sqrt(var + eps) * scale + bias) @ w + b == x @ (s[:, None] * w) + (t @ w + b),
    with s = scale / sqrt(var + eps) and t = bias - mean * s. Folded in float64, then rounded once."""
    w, b = np.asarray(layer["w"], np.float64), np.asarray(layer["b"], np.float64)
    s = np.asarray(layer["norm_scale"], np.float64) / np.sqrt(np.asarray(stats["var"], np.float64) + eps)
    t = np.asarray(layer["norm_bias"], np.float64) - np.asarray(stats["mean"], np.float64) * s
    return (s[:, None] * w).astype(np.float32), (t @ w + b).astype(np.float32)


def export_arrays(actor: Params, actor_stats: Params, batch_renorm: Any, matmul_dtype: str,
                  act_dim: int) -> dict[str, np.ndarray]:
    """The actor's layers as numpy_forward lays them out: w0, b0, ...; nI_* for the input's batch
    renormalisation of a CrossQ layer that multiplies in bf16 (folded into w and b otherwise); bf16, where a
    layer does, marking which. The last layer cut to the mean action's columns (the log-std is not needed)."""
    stats = actor_stats if batch_renorm is not None else [None] * len(actor)
    arrays: dict[str, np.ndarray] = {}
    flags = []
    for i, (layer, layer_stats) in enumerate(zip(actor, stats)):
        bf16 = compiled_in_bf16(np.shape(layer["w"]), matmul_dtype)
        w, b = np.asarray(layer["w"], np.float32), np.asarray(layer["b"], np.float32)
        steps = {}
        if batch_renorm is not None and bf16:  # folded, the weights would be rounded after scaling: not what JAX does
            steps = _batch_renorm_steps(layer, layer_stats, batch_renorm.eps)
        elif batch_renorm is not None:
            w, b = _fold_batch_renorm(layer, layer_stats, batch_renorm.eps)
        if i == len(actor) - 1:
            w, b = np.ascontiguousarray(w[:, :act_dim]), np.ascontiguousarray(b[:act_dim])
        arrays[f"w{i}"], arrays[f"b{i}"] = (round_bf16(w) if bf16 else w), b
        if "ln_scale" in layer:  # the hidden LayerNorm's learned affine (layer_norm_affine)
            arrays[f"ln{i}_scale"] = np.asarray(layer["ln_scale"], np.float32)
            arrays[f"ln{i}_bias"] = np.asarray(layer["ln_bias"], np.float32)
        arrays.update({f"n{i}_{k}": v for k, v in steps.items()})
        flags.append(bf16)
    if any(flags):
        arrays["bf16"] = np.array(flags, np.int8)
    return arrays


def onnx_actor(g: onnx_layers.Graph, arrays: dict[str, np.ndarray], x: str) -> str:
    """numpy_forward.mlp_forward's nodes."""
    bf16 = dense_bf16_flags(arrays)
    for i in range(len(bf16)):
        if f"n{i}_mean" in arrays:
            x = g.op("Mul", g.op("Sub", x, g.const(f"n{i}_mean", arrays[f"n{i}_mean"])),
                     g.const(f"n{i}_inv_std", arrays[f"n{i}_inv_std"]))
            x = g.op("Add", g.op("Mul", x, g.const(f"n{i}_scale", arrays[f"n{i}_scale"])),
                     g.const(f"n{i}_bias", arrays[f"n{i}_bias"]))
        x = onnx_layers.dense(g, arrays, x, f"w{i}", f"b{i}", bf16[i])
        if f"p{i}_mean" in arrays:  # a normalisation after the layer, before its activation (bn_mlp)
            x = g.op("Mul", g.op("Sub", x, g.const(f"p{i}_mean", arrays[f"p{i}_mean"])),
                     g.const(f"p{i}_inv_std", arrays[f"p{i}_inv_std"]))
            x = g.op("Add", g.op("Mul", x, g.const(f"p{i}_scale", arrays[f"p{i}_scale"])),
                     g.const(f"p{i}_bias", arrays[f"p{i}_bias"]))
        ln_after = bool(arrays.get("hidden_ln_after", False))
        if i < len(bf16) - 1 and "hidden_ln_eps" in arrays and not ln_after:
            x = onnx_layers.layer_norm(g, arrays, x, f"ln{i}", float(arrays["hidden_ln_eps"]))
        if i < len(bf16) - 1:
            x = onnx_layers.activation(g, str(arrays["activation"]), x)
        if i < len(bf16) - 1 and "hidden_ln_eps" in arrays and ln_after:
            x = onnx_layers.layer_norm(g, arrays, x, f"ln{i}", float(arrays["hidden_ln_eps"]))
    return x


MLP_EXPORT = ActorExport(arrays=export_arrays, onnx=onnx_actor, input_size=lambda arrays: arrays["w0"].shape[0])

MLP = Network(
    init=lambda rng, in_dim, widths, out_dim, init, out_gain: init_mlp(rng, [in_dim, *widths, out_dim], init, out_gain),
    features=_features, head=lambda params: params[-1], output_mask=output_layer_mask, parameters=parameters,
    export=MLP_EXPORT)
