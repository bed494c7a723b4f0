"""XQC's networks (Palenicek et al. 2026, danielpalenicek/xqc, networks/critic_net.py and policies.py): batch
normalisation of the input, then per hidden layer a dense layer without bias, batch normalisation and the
activation; the output layer a plain dense one. Where CrossQ's batch_renorm_mlp normalises each layer's input
(after the activation), this normalises before it. With weight_norm every dense layer's kernel, the output
layer's too, is projected so that each unit's incoming weights have unit norm (XQC's norm_dense_layer; biases
and the normalisations' scales stay free). Initialised as the authors' code: orthogonal kernels (gain sqrt 2;
the output layer's at the actor's or critic's gain), zero biases, normalisations at scale 1, bias 0.

Parameters: {"input": {"norm_scale", "norm_bias"}, "layers": [{"w", "norm_scale", "norm_bias"}, ...],
"head": {"w", "b"}}; running statistics: {"input": {"mean", "var"}, "layers": [{"mean", "var"}, ...]}."""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from softac.learner.networks import mlp
from softac.learner.networks.entry import ActorExport, Network, Params
from softac.learner.networks.layers import ACTIVATIONS, compiled_in_bf16, init_layer, matmul
from softac.learner.numpy_forward import round_bf16


def _norm(n: int) -> dict:
    return {"norm_scale": np.ones(n, np.float32), "norm_bias": np.zeros(n, np.float32)}


def _stats(n: int) -> dict:
    return {"mean": np.zeros(n, np.float32), "var": np.ones(n, np.float32)}


def init_bn_mlp(rng: np.random.Generator, in_dim: int, widths: list[int], out_dim: int, init: str,
                out_gain: float) -> Params:
    sizes = [in_dim, *widths]
    layers = [{"w": init_layer(rng, a, b, init, math.sqrt(2.0))["w"], **_norm(b)} for a, b in zip(sizes, sizes[1:])]
    head = init_layer(rng, widths[-1], out_dim, init, out_gain)
    return {"input": _norm(in_dim), "layers": layers, "head": {"w": head["w"], "b": np.zeros(out_dim, np.float32)}}


def init_stats(in_dim: int, widths: list[int], out_dim: int) -> Params:
    return {"input": _stats(in_dim), "layers": [_stats(w) for w in widths]}


def bn_mlp_features(params: Params, stats: Params, x: jax.Array, activation: str, norm: Any, train: bool,
                    renorm: jax.Array | bool = False, matmul_dtype: str = "float32") -> tuple[jax.Array, Params]:
    """The output layer's input, and the running statistics (new ones in training mode)."""
    act = ACTIVATIONS[activation]
    x, input_stats = norm(x, params["input"], stats["input"], train, renorm)
    new_stats = []
    for layer, layer_stats in zip(params["layers"], stats["layers"]):
        h, layer_stats = norm(matmul(x, layer["w"], matmul_dtype), layer, layer_stats, train, renorm)
        new_stats.append(layer_stats)
        x = act(h)
    return x, {"input": input_stats, "layers": new_stats}


def _features(params, stats, x, activation, matmul_dtype, normalize=False, masks=None, batch_renorm=None,
              train=False, renorm=False):
    return bn_mlp_features(params, stats, x, activation, batch_renorm, train, renorm, matmul_dtype)


def unit_norm_kernels(params: Params, xp: Any = jnp) -> Params:
    """Every kernel's columns (a unit's incoming weights) scaled to unit norm, the output layer's too; biases and
    the normalisations as they are. One network or a stacked ensemble; NumPy (`xp=np`, at init) or JAX."""
    def project(w: Any) -> Any:
        return w / xp.sqrt(xp.sum(xp.square(w), axis=-2, keepdims=True))

    return {"input": params["input"], "layers": [{**layer, "w": project(layer["w"])} for layer in params["layers"]],
            "head": {**params["head"], "w": project(params["head"]["w"])}}


def output_layer_mask(params: Params) -> Params:
    mask = jax.tree_util.tree_map(lambda _: False, params)
    mask["head"] = {k: k in ("w", "b") for k in params["head"]}
    return mask


def parameters(in_dim: int, widths: list[int], out_dim: int) -> int:
    sizes = [in_dim, *widths]
    return 2 * in_dim + sum(a * b + 2 * b for a, b in zip(sizes, sizes[1:])) + (widths[-1] + 1) * out_dim


# ---- export (softac export; numpy_forward.mlp_forward runs it) ----------------------------------------

def _steps(layer: dict, stats: dict, eps: float) -> dict[str, np.ndarray]:
    """A batch normalisation in evaluation mode as BatchRenorm computes it, step by step in float32 ((x - mean)
    * inv_std * scale + bias, inv_std from JAX's own rsqrt), so that the export computes JAX's values."""
    inv_std = jax.lax.rsqrt(jnp.asarray(stats["var"], np.float32) + np.float32(eps))
    return {"mean": np.asarray(stats["mean"], np.float32), "inv_std": np.asarray(inv_std, np.float32),
            "scale": np.asarray(layer["norm_scale"], np.float32), "bias": np.asarray(layer["norm_bias"], np.float32)}


def export_arrays(actor: Params, actor_stats: Params, batch_renorm: Any, matmul_dtype: str,
                  act_dim: int) -> dict[str, np.ndarray]:
    """The actor in the MLP layout (w0, b0, ...), its normalisations kept apart as steps: n0_* on the input
    before w0, pI_* after layer I's matmul (before the activation); hidden biases zero (its dense layers have
    none), the output layer cut to the mean action's columns."""
    eps = batch_renorm.eps
    arrays: dict[str, np.ndarray] = {f"n0_{k}": v for k, v in _steps(actor["input"], actor_stats["input"], eps).items()}
    flags = []
    for i, (layer, stats) in enumerate(zip(actor["layers"], actor_stats["layers"])):
        w = np.asarray(layer["w"], np.float32)
        bf16 = compiled_in_bf16(w.shape, matmul_dtype)
        arrays[f"w{i}"], arrays[f"b{i}"] = (round_bf16(w) if bf16 else w), np.zeros(w.shape[1], np.float32)
        arrays.update({f"p{i}_{k}": v for k, v in _steps(layer, stats, eps).items()})
        flags.append(bf16)
    head = actor["head"]
    w = np.asarray(head["w"], np.float32)
    bf16 = compiled_in_bf16(w.shape, matmul_dtype)
    w = np.ascontiguousarray(w[:, :act_dim])
    last = len(actor["layers"])
    arrays[f"w{last}"] = round_bf16(w) if bf16 else w
    arrays[f"b{last}"] = np.ascontiguousarray(np.asarray(head["b"], np.float32)[:act_dim])
    flags.append(bf16)
    if any(flags):
        arrays["bf16"] = np.array(flags, np.int8)
    return arrays


BN_MLP = Network(
    init=init_bn_mlp, features=_features, head=lambda params: params["head"], output_mask=output_layer_mask,
    parameters=parameters, init_stats=init_stats, unit_norm=unit_norm_kernels,
    # each hidden unit keeps its matmul's output and its normalisation's for the backward pass
    activation_factor=2,
    export=ActorExport(arrays=export_arrays, onnx=mlp.onnx_actor,
                       input_size=lambda arrays: arrays["w0"].shape[0]))
