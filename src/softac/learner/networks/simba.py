"""SimBa (Lee et al. 2024, "SimBa: Simplicity Bias for Scaling Up Parameters in Deep RL"):
A linear embedding, then per block x + W2 act(W1 LayerNorm(x)) with an inner width 4x the block's, then a
final LayerNorm before the output layer; the LayerNorms learn their scale and bias. Initialised as the
authors' code does (SonyResearch/simba, scale_rl/networks): orthogonal (gain 1) embedding and output
layers, He-normal (truncated) block layers, zero biases.
Parameters: {"embed": {"w", "b"}, "blocks": [...], "head": {"ln_scale", "ln_bias", "w", "b"}}."""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from softac.learner.networks import onnx_layers
from softac.learner.networks.entry import ActorExport, Network, Params
from softac.learner.networks.layers import ACTIVATIONS, compiled_in_bf16, dense, he_normal, layer_norm, orthogonal
from softac.learner.numpy_forward import dense_bf16_flags, round_bf16, simba_block_count

SIMBA_EXPANSION = 4
SIMBA_LN_EPS = 1e-6  # flax.linen.LayerNorm's, which the authors' networks use


def init_simba(rng: np.random.Generator, in_dim: int, widths: list[int], out_dim: int) -> Params:
    """A SimBa network: one residual block per entry of `widths` (all equal: the residual stream's width)."""
    width = widths[0]
    inner = SIMBA_EXPANSION * width
    zeros, ones = (lambda n: np.zeros(n, np.float32)), (lambda n: np.ones(n, np.float32))
    blocks = [{"ln_scale": ones(width), "ln_bias": zeros(width), "w1": he_normal(rng, width, inner),
               "b1": zeros(inner), "w2": he_normal(rng, inner, width), "b2": zeros(width)} for _ in widths]
    return {"embed": {"w": orthogonal(rng, in_dim, width, 1.0), "b": zeros(width)}, "blocks": blocks,
            "head": {"ln_scale": ones(width), "ln_bias": zeros(width), "w": orthogonal(rng, width, out_dim, 1.0),
                     "b": zeros(out_dim)}}


def _affine_layer_norm(x: jax.Array, scale: jax.Array, bias: jax.Array) -> jax.Array:
    return layer_norm(x, SIMBA_LN_EPS) * scale + bias


def simba(params: Params, x: jax.Array, activation: str, matmul_dtype: str = "float32") -> jax.Array:
    return dense(simba_features(params, x, activation, matmul_dtype), params["head"], matmul_dtype)


def simba_features(params: Params, x: jax.Array, activation: str, matmul_dtype: str = "float32") -> jax.Array:
    """`simba` up to the output layer's input: the residual stream after the final LayerNorm."""
    act = ACTIVATIONS[activation]
    x = dense(x, params["embed"], matmul_dtype)
    for block in params["blocks"]:
        h = _affine_layer_norm(x, block["ln_scale"], block["ln_bias"])
        h = act(dense(h, {"w": block["w1"], "b": block["b1"]}, matmul_dtype))
        x = x + dense(h, {"w": block["w2"], "b": block["b2"]}, matmul_dtype)
    head = params["head"]
    return _affine_layer_norm(x, head["ln_scale"], head["ln_bias"])


def _features(params, stats, x, activation, matmul_dtype, normalize=False, masks=None, batch_renorm=None,
              train=False, renorm=False):
    return simba_features(params, x, activation, matmul_dtype), stats


def output_layer_mask(params: Params) -> Params:
    mask = jax.tree_util.tree_map(lambda _: False, params)
    mask["head"] = {k: k in ("w", "b") for k in params["head"]}
    return mask


def parameters(in_dim: int, widths: list[int], out_dim: int) -> int:
    """The embedding, the residual blocks (inner width 4x, a LayerNorm each) and the head (with its LayerNorm)."""
    w = widths[0]
    block = 2 * w + (w + 1) * SIMBA_EXPANSION * w + (SIMBA_EXPANSION * w + 1) * w
    return (in_dim + 1) * w + len(widths) * block + 2 * w + (w + 1) * out_dim


# ---- export (softac export; numpy_forward.simba_forward runs it) ---------------------------------------

def export_arrays(actor: Params, actor_stats: Params, batch_renorm: Any, matmul_dtype: str,
                  act_dim: int) -> dict[str, np.ndarray]:
    """A SimBa actor as numpy_forward lays it out: the embedding, each residual block's LayerNorm and two
    layers, the final LayerNorm and the output layer cut to the mean action's columns; `bf16` marks, in that
    order of the dense layers, the ones that multiply in bfloat16 (weights rounded)."""
    arrays: dict[str, np.ndarray] = {"network": np.asarray("simba"), "ln_eps": np.asarray(SIMBA_LN_EPS, np.float32)}
    bf16_flags = []

    def put_dense(name: str, w: Any, b: Any, columns: int | None = None) -> None:
        w, b = np.asarray(w, np.float32), np.asarray(b, np.float32)
        bf16 = compiled_in_bf16(w.shape, matmul_dtype)  # on the whole layer, as JAX decides it
        w, b = np.ascontiguousarray(w[:, :columns]), np.ascontiguousarray(b[:columns])
        arrays[f"{name}_w"], arrays[f"{name}_b"] = (round_bf16(w) if bf16 else w), b
        bf16_flags.append(bf16)

    put_dense("embed", actor["embed"]["w"], actor["embed"]["b"])
    for i, block in enumerate(actor["blocks"]):
        arrays[f"block{i}_ln_scale"] = np.asarray(block["ln_scale"], np.float32)
        arrays[f"block{i}_ln_bias"] = np.asarray(block["ln_bias"], np.float32)
        put_dense(f"block{i}_1", block["w1"], block["b1"])
        put_dense(f"block{i}_2", block["w2"], block["b2"])
    head = actor["head"]
    arrays["head_ln_scale"] = np.asarray(head["ln_scale"], np.float32)
    arrays["head_ln_bias"] = np.asarray(head["ln_bias"], np.float32)
    put_dense("head", head["w"], head["b"], columns=act_dim)
    if any(bf16_flags):
        arrays["bf16"] = np.array(bf16_flags, np.int8)
    return arrays


def onnx_actor(g: onnx_layers.Graph, arrays: dict[str, np.ndarray], x: str) -> str:
    """numpy_forward.simba_forward's nodes: the embedding, the residual blocks, the final LayerNorm, the output
    layer."""
    eps, n_blocks = float(arrays["ln_eps"]), simba_block_count(arrays)
    bf16 = iter(dense_bf16_flags(arrays))
    x = onnx_layers.dense(g, arrays, x, "embed_w", "embed_b", next(bf16))
    for i in range(n_blocks):
        h = onnx_layers.layer_norm(g, arrays, x, f"block{i}_ln", eps)
        h = onnx_layers.activation(g, str(arrays["activation"]),
                                   onnx_layers.dense(g, arrays, h, f"block{i}_1_w", f"block{i}_1_b", next(bf16)))
        x = g.op("Add", x, onnx_layers.dense(g, arrays, h, f"block{i}_2_w", f"block{i}_2_b", next(bf16)))
    return onnx_layers.dense(g, arrays, onnx_layers.layer_norm(g, arrays, x, "head_ln", eps), "head_w", "head_b",
                             next(bf16))


# the blocks' 4x-wide inner layers and their LayerNorms keep about 6x an MLP's activations per unit
SIMBA = Network(
    init=lambda rng, in_dim, widths, out_dim, init, out_gain: init_simba(rng, in_dim, widths, out_dim),
    features=_features, head=lambda params: params["head"], output_mask=output_layer_mask, parameters=parameters,
    activation_factor=6, export=ActorExport(arrays=export_arrays, onnx=onnx_actor,
                                            input_size=lambda arrays: arrays["embed_w"].shape[0]))
