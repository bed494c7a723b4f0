"""FlashSAC's networks (Kim et al. 2026, Holiday-Robot/FlashSAC, flash_rl/agents/flashSAC/layer.py and
network.py): batch normalisation of the input and a linear embedding without bias; per block an inverted
residual x + act(BN(act(BN(x W1)) W2)) with W1 widening to 4x the stream's width and W2 narrowing back (dense
layers without bias, batch normalisation before each activation); an RMSNorm with a learned scale; the output
layer (weights and a bias). With weight_norm every kernel's units are kept at unit norm, and each normalisation's
parameters at norm sqrt(width) (a batch normalisation's scale and bias as one vector, the RMSNorm's scale), as
FlashSAC's normalize_parameters does after initialisation and after each optimiser step; the output layer's bias
stays free. Initialised as the authors' code: orthogonal kernels of gain 1, normalisations at scale 1, bias 0.

Parameters: {"input": {"norm_scale", "norm_bias"}, "embed": {"w"}, "blocks": [{"w1", "norm1": {...}, "w2",
"norm2": {...}}, ...], "head": {"rms_scale", "w", "b"}}; running statistics: {"input": {"mean", "var"},
"blocks": [{"norm1": {...}, "norm2": {...}}, ...]}."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from softac.learner.networks import onnx_layers
from softac.learner.networks.entry import ActorExport, Network, Params
from softac.learner.networks.layers import ACTIVATIONS, compiled_in_bf16, init_layer, matmul
from softac.learner.numpy_forward import FLASHSAC_RMS_EPS, dense_bf16_flags, flashsac_block_count, round_bf16

EXPANSION = 4
NORM_EPS = 1e-8  # FlashSAC's in normalize_parameters (and F.normalize's)


def _norm(n: int) -> dict:
    return {"norm_scale": np.ones(n, np.float32), "norm_bias": np.zeros(n, np.float32)}


def _stats(n: int) -> dict:
    return {"mean": np.zeros(n, np.float32), "var": np.ones(n, np.float32)}


def init_flashsac(rng: np.random.Generator, in_dim: int, widths: list[int], out_dim: int, init: str,
                  out_gain: float) -> Params:
    """One inverted residual block per entry of `widths` (all equal: the residual stream's width)."""
    width, inner = widths[0], EXPANSION * widths[0]

    def kernel(a: int, b: int, gain: float = 1.0) -> np.ndarray:
        return init_layer(rng, a, b, init, gain)["w"]

    blocks = [{"w1": kernel(width, inner), "norm1": _norm(inner), "w2": kernel(inner, width), "norm2": _norm(width)}
              for _ in widths]
    return {"input": _norm(in_dim), "embed": {"w": kernel(in_dim, width)}, "blocks": blocks,
            "head": {"rms_scale": np.ones(width, np.float32), "w": kernel(width, out_dim, out_gain),
                     "b": np.zeros(out_dim, np.float32)}}


def init_stats(in_dim: int, widths: list[int], out_dim: int) -> Params:
    width = widths[0]
    return {"input": _stats(in_dim),
            "blocks": [{"norm1": _stats(EXPANSION * width), "norm2": _stats(width)} for _ in widths]}


def rms_norm(x: jax.Array, scale: jax.Array) -> jax.Array:
    return x * jax.lax.rsqrt(jnp.mean(jnp.square(x), axis=-1, keepdims=True) + FLASHSAC_RMS_EPS) * scale


def flashsac_features(params: Params, stats: Params, x: jax.Array, activation: str, norm: Any, train: bool,
                      renorm: jax.Array | bool = False, matmul_dtype: str = "float32") -> tuple[jax.Array, Params]:
    """The output layer's input (after the RMSNorm), and the running statistics (new ones in training mode)."""
    act = ACTIVATIONS[activation]
    x, input_stats = norm(x, params["input"], stats["input"], train, renorm)
    x = matmul(x, params["embed"]["w"], matmul_dtype)
    new_blocks = []
    for block, block_stats in zip(params["blocks"], stats["blocks"]):
        h, stats1 = norm(matmul(x, block["w1"], matmul_dtype), block["norm1"], block_stats["norm1"], train, renorm)
        h, stats2 = norm(matmul(act(h), block["w2"], matmul_dtype), block["norm2"], block_stats["norm2"], train,
                         renorm)
        x = act(h) + x
        new_blocks.append({"norm1": stats1, "norm2": stats2})
    return rms_norm(x, params["head"]["rms_scale"]), {"input": input_stats, "blocks": new_blocks}


def _features(params, stats, x, activation, matmul_dtype, normalize=False, masks=None, batch_renorm=None,
              train=False, renorm=False):
    return flashsac_features(params, stats, x, activation, batch_renorm, train, renorm, matmul_dtype)


def unit_norm(params: Params, xp: Any = jnp) -> Params:
    """FlashSAC's normalize_parameters: kernels' units to unit norm (over their inputs), a batch normalisation's
    (scale, bias) and the RMSNorm's scale to norm sqrt(width); one network or a stacked ensemble, in NumPy (`xp=np`,
    at init) or JAX."""
    def kernel(w: Any) -> Any:
        return w / xp.maximum(xp.sqrt(xp.sum(xp.square(w), axis=-2, keepdims=True)), NORM_EPS)

    def bn(layer: dict) -> dict:
        scale, bias = layer["norm_scale"], layer["norm_bias"]
        factor = np.sqrt(scale.shape[-1]) / xp.sqrt(xp.sum(scale * scale + bias * bias, axis=-1, keepdims=True)
                                                    + NORM_EPS)
        return {"norm_scale": scale * factor, "norm_bias": bias * factor}

    head = params["head"]
    rms = head["rms_scale"]
    rms = rms * (np.sqrt(rms.shape[-1]) / xp.sqrt(xp.sum(rms * rms, axis=-1, keepdims=True) + NORM_EPS))
    return {"input": bn(params["input"]), "embed": {"w": kernel(params["embed"]["w"])},
            "blocks": [{"w1": kernel(b["w1"]), "norm1": bn(b["norm1"]), "w2": kernel(b["w2"]), "norm2": bn(b["norm2"])}
                       for b in params["blocks"]],
            "head": {"rms_scale": rms, "w": kernel(head["w"]), "b": head["b"]}}


def output_layer_mask(params: Params) -> Params:
    mask = jax.tree_util.tree_map(lambda _: False, params)
    mask["head"] = {k: k in ("w", "b") for k in params["head"]}
    return mask


def parameters(in_dim: int, widths: list[int], out_dim: int) -> int:
    """The input's normalisation, the embedding, the blocks (two kernels and two normalisations each), the
    RMSNorm and the output layer."""
    w, inner = widths[0], EXPANSION * widths[0]
    block = 2 * w * inner + 2 * inner + 2 * w
    return 2 * in_dim + in_dim * w + len(widths) * block + w + (w + 1) * out_dim


# ---- export (softac export; numpy_forward.flashsac_forward runs it) ------------------------------------

def _steps(layer: dict, stats: dict, eps: float, prefix: str) -> dict[str, np.ndarray]:
    """A batch normalisation in evaluation mode as BatchRenorm computes it, step by step in float32."""
    inv_std = jax.lax.rsqrt(jnp.asarray(stats["var"], np.float32) + np.float32(eps))
    return {f"{prefix}_mean": np.asarray(stats["mean"], np.float32), f"{prefix}_inv_std": np.asarray(inv_std),
            f"{prefix}_scale": np.asarray(layer["norm_scale"], np.float32),
            f"{prefix}_bias": np.asarray(layer["norm_bias"], np.float32)}


def export_arrays(actor: Params, actor_stats: Params, batch_renorm: Any, matmul_dtype: str,
                  act_dim: int) -> dict[str, np.ndarray]:
    """A FlashSAC actor as numpy_forward lays it out: the input's normalisation (in_*), the embedding's kernel,
    each block's kernels and normalisations (blockI_1_w, blockI_n1_*, blockI_2_w, blockI_n2_*), the RMSNorm's
    scale and the output layer cut to the mean action's columns; `bf16` marks, in that order of the kernels, the
    ones that multiply in bfloat16 (weights rounded)."""
    eps = batch_renorm.eps
    arrays: dict[str, np.ndarray] = {"network": np.asarray("flashsac"),
                                     **_steps(actor["input"], actor_stats["input"], eps, "in")}
    flags = []

    def put(name: str, w: Any, columns: int | None = None) -> None:
        w = np.asarray(w, np.float32)
        bf16 = compiled_in_bf16(w.shape, matmul_dtype)  # on the whole layer, as JAX decides it
        w = np.ascontiguousarray(w[:, :columns])
        arrays[name] = round_bf16(w) if bf16 else w
        flags.append(bf16)

    put("embed_w", actor["embed"]["w"])
    for i, (block, stats) in enumerate(zip(actor["blocks"], actor_stats["blocks"])):
        put(f"block{i}_1_w", block["w1"])
        arrays.update(_steps(block["norm1"], stats["norm1"], eps, f"block{i}_n1"))
        put(f"block{i}_2_w", block["w2"])
        arrays.update(_steps(block["norm2"], stats["norm2"], eps, f"block{i}_n2"))
    head = actor["head"]
    arrays["rms_scale"] = np.asarray(head["rms_scale"], np.float32)
    arrays["rms_eps"] = np.asarray(FLASHSAC_RMS_EPS, np.float32)
    put("head_w", head["w"], columns=act_dim)
    arrays["head_b"] = np.ascontiguousarray(np.asarray(head["b"], np.float32)[:act_dim])
    if any(flags):
        arrays["bf16"] = np.array(flags, np.int8)
    return arrays


def onnx_actor(g: onnx_layers.Graph, arrays: dict[str, np.ndarray], x: str) -> str:
    """numpy_forward.flashsac_forward's nodes."""
    bf16 = iter(dense_bf16_flags(arrays))
    act = str(arrays["activation"])

    def norm(x: str, prefix: str) -> str:
        x = g.op("Mul", g.op("Sub", x, g.const(f"{prefix}_mean", arrays[f"{prefix}_mean"])),
                 g.const(f"{prefix}_inv_std", arrays[f"{prefix}_inv_std"]))
        return g.op("Add", g.op("Mul", x, g.const(f"{prefix}_scale", arrays[f"{prefix}_scale"])),
                    g.const(f"{prefix}_bias", arrays[f"{prefix}_bias"]))

    x = onnx_layers.matmul(g, arrays, norm(x, "in"), "embed_w", next(bf16))
    for i in range(flashsac_block_count(arrays)):
        h = onnx_layers.activation(g, act, norm(onnx_layers.matmul(g, arrays, x, f"block{i}_1_w", next(bf16)),
                                                f"block{i}_n1"))
        h = onnx_layers.activation(g, act, norm(onnx_layers.matmul(g, arrays, h, f"block{i}_2_w", next(bf16)),
                                                f"block{i}_n2"))
        x = g.op("Add", h, x)
    mean_square = g.op("ReduceMean", g.op("Mul", x, x), axes=[-1], keepdims=1)
    inv_rms = g.op("Reciprocal", g.op("Sqrt", g.op("Add", mean_square, g.const("rms_eps", arrays["rms_eps"]))))
    x = g.op("Mul", g.op("Mul", x, inv_rms), g.const("rms_scale", arrays["rms_scale"]))
    return g.op("Add", onnx_layers.matmul(g, arrays, x, "head_w", next(bf16)), g.const("head_b", arrays["head_b"]))


# each 4x-wide block keeps its two matmuls' outputs and their normalisations' for the backward pass
FLASHSAC = Network(
    init=init_flashsac, features=_features, head=lambda params: params["head"], output_mask=output_layer_mask,
    parameters=parameters, init_stats=init_stats, unit_norm=unit_norm, activation_factor=10,
    export=ActorExport(arrays=export_arrays, onnx=onnx_actor, input_size=lambda arrays: arrays["embed_w"].shape[0]))
