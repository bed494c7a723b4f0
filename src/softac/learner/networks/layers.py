"""The layers and pieces every network kind is made of: initialisers, the dense layer (float32, or bf16 on the
hidden-to-hidden layers), LayerNorm, CrossQ's batch renormalisation, dropout, CrossQ+WN's unit-norm projection,
and the critic ensemble's stacking. Parameters are plain JAX pytrees; initialisation runs in NumPy."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

Params = Any

ACTIVATIONS: dict[str, Callable[[jax.Array], jax.Array]] = {
    "relu": jax.nn.relu,
    "tanh": jnp.tanh,
    "elu": jax.nn.elu,
    "gelu": jax.nn.gelu,
    "silu": jax.nn.silu,
}


def init_layer(rng: np.random.Generator, fan_in: int, fan_out: int, init: str, gain: float) -> dict:
    # NumPy, not jitted JAX: initialising this way costs microseconds where compiling an init costs seconds
    if init == "orthogonal":  # Saxe et al. 2014, as torch.nn.init.orthogonal_
        a = rng.standard_normal((max(fan_in, fan_out), min(fan_in, fan_out)))
        q, r = np.linalg.qr(a)
        q *= np.sign(np.diag(r))
        w = gain * (q if fan_in >= fan_out else q.T)
        b = np.zeros(fan_out)
    elif init == "xavier_uniform":  # Glorot & Bengio 2010, as RLPD's networks: U(+-sqrt(6 / (fan_in + fan_out))), zero biases
        bound = math.sqrt(6.0 / (fan_in + fan_out))
        w = rng.uniform(-bound, bound, (fan_in, fan_out))
        b = np.zeros(fan_out)
    elif init == "lecun_uniform":  # Brax's networks (jax.nn.initializers.lecun_uniform): U(+-sqrt(3 / fan_in)), zero biases
        bound = math.sqrt(3.0 / fan_in)
        w = rng.uniform(-bound, bound, (fan_in, fan_out))
        b = np.zeros(fan_out)
    else:  # PyTorch nn.Linear's default: U(-1/sqrt(fan_in), 1/sqrt(fan_in)) for weights and biases
        bound = 1.0 / math.sqrt(fan_in)
        w = rng.uniform(-bound, bound, (fan_in, fan_out))
        b = rng.uniform(-bound, bound, fan_out)
    return {"w": w.astype(np.float32), "b": b.astype(np.float32)}


def he_normal(rng: np.random.Generator, fan_in: int, fan_out: int) -> np.ndarray:
    """He-normal as jax.nn.initializers.he_normal: a normal truncated at 2 std, scaled to variance 2/fan_in."""
    z = rng.standard_normal((fan_in, fan_out))
    while np.any(outside := np.abs(z) > 2.0):
        z[outside] = rng.standard_normal(int(outside.sum()))
    return (z * math.sqrt(2.0 / fan_in) / 0.87962566103423978).astype(np.float32)


def orthogonal(rng: np.random.Generator, fan_in: int, fan_out: int, gain: float) -> np.ndarray:
    return init_layer(rng, fan_in, fan_out, "orthogonal", gain)["w"]


def unit_norm_hidden_units(params: Params, xp: Any = jnp) -> Params:
    """Each hidden unit's incoming weights and bias, as one vector, scaled to unit length; the output layer
    as it is (CrossQ+WN, Palenicek et al. 2025). With batch renormalisation after the activation, a ReLU
    unit's output scales with that vector and the next normalisation divides the scale out, so the network
    computes the same function while the effective learning rate stays put. Works on one MLP or a stacked
    ensemble (leading critic axis), in NumPy (`xp=np`, at init) or JAX."""
    def project(layer: dict) -> dict:
        norm = xp.sqrt(xp.sum(xp.square(layer["w"]), axis=-2) + xp.square(layer["b"]))
        return {**layer, "w": layer["w"] / norm[..., None, :], "b": layer["b"] / norm}

    return [project(layer) for layer in params[:-1]] + [params[-1]]


def init_norm_stats(sizes: list[int]) -> Params:
    """Running mean and variance of each layer's input (mean 0, variance 1 to start)."""
    return [{"mean": np.zeros(n, np.float32), "var": np.ones(n, np.float32)} for n in sizes[:-1]]


@jax.custom_vjp
def bf16_matmul(x: jax.Array, w: jax.Array) -> jax.Array:
    """x @ w with bf16 inputs and f32 accumulation, in the forward and in both backward matmuls.

    Plain autodiff of a bf16 dot would run the two backward dots in f32 (the cotangent is f32),
    losing most of the gain: 256^3 runs at ~320 GFLOP/s in bf16 vs ~130 in f32 on this AMX CPU.
    """
    return jnp.dot(x.astype(jnp.bfloat16), w.astype(jnp.bfloat16), preferred_element_type=jnp.float32)


def _bf16_matmul_fwd(x: jax.Array, w: jax.Array):
    x16, w16 = x.astype(jnp.bfloat16), w.astype(jnp.bfloat16)
    return jnp.dot(x16, w16, preferred_element_type=jnp.float32), (x16, w16)


def _materialised_transpose(x: jax.Array) -> jax.Array:
    """x.T as a gather: XLA folds a plain transpose into the consuming dot (contracting the batch axis),
    which its CPU backend then runs in f32 on converted copies; a gathered copy cannot be folded."""
    if jax.default_backend() != "cpu":  # GPUs run transposed bf16 dots natively
        return x.T
    rows, cols = x.shape
    return x[jnp.arange(rows)[None, :], jnp.arange(cols)[:, None]]


def _bf16_matmul_bwd(residuals, g: jax.Array):
    x16, w16 = residuals
    g16 = g.astype(jnp.bfloat16)
    # XLA's CPU backend keeps a bf16 dot in bf16 only in plain (row-major, untransposed) form or as
    # one dot_general contracting both last axes; `jnp.dot(g16, w16.T)` and `jnp.dot(x16.T, g16)` ran
    # in f32 (docs/performance.md: sb3 update 4.22 -> 3.67 -> 3.44 ms with the two changes).
    dx = jax.lax.dot_general(g16, w16, (((1,), (1,)), ((), ())), preferred_element_type=jnp.float32)
    dw = jnp.dot(_materialised_transpose(x16), g16, preferred_element_type=jnp.float32)
    return dx, dw


bf16_matmul.defvjp(_bf16_matmul_fwd, _bf16_matmul_bwd)


def multiplies_in_bf16(weight_shape: tuple[int, ...], matmul_dtype: str) -> bool:
    # mixed precision only where the FLOPs are: hidden-to-hidden layers. The input and output
    # layers are thin (a few columns), cost little, and keep full precision for obs and Q-values.
    return matmul_dtype != "float32" and min(weight_shape[-2:]) >= 16


@functools.cache
def jit_keeps_bf16_rounding() -> bool:
    """Whether this JAX's compiled bf16 layer rounds its inputs to bf16, as current JAX does. JAX 0.4.30's CPU
    backend drops the float32 -> bf16 -> float32 round trip as excess precision (XLA's
    xla_allow_excess_precision) and multiplies in float32: there a bf16 layer computes the float32 layer, so
    the export (which must act as predict() does) writes it as float32. Probed once on a layer whose two
    results differ by ~1e-2."""
    from softac.learner.numpy_forward import round_bf16  # the export's own rounding: the one it would reproduce

    rng = np.random.default_rng(0)
    x, w = rng.normal(size=(8, 32)).astype(np.float32), rng.normal(size=(32, 8)).astype(np.float32)
    # an op before the matmul, as in a network (one correctly rounded float32 add: NumPy's is XLA's to the bit)
    compiled = np.asarray(jax.jit(lambda x, w: bf16_matmul(x + 1.0, w))(x, w), np.float64)
    shifted = x + np.float32(1.0)
    rounded = round_bf16(shifted).astype(np.float64) @ round_bf16(w).astype(np.float64)
    unrounded = shifted.astype(np.float64) @ w.astype(np.float64)
    return bool(np.abs(compiled - rounded).max() < np.abs(compiled - unrounded).max())


def compiled_in_bf16(weight_shape: tuple[int, ...], matmul_dtype: str) -> bool:
    """Whether a layer's compiled matmul really rounds its inputs to bf16 (`multiplies_in_bf16`, where this JAX
    keeps the rounding): what the export reproduces, so that it acts as predict() does."""
    return multiplies_in_bf16(weight_shape, matmul_dtype) and jit_keeps_bf16_rounding()


def dense(x: jax.Array, layer: dict, matmul_dtype: str) -> jax.Array:
    return matmul(x, layer["w"], matmul_dtype) + layer["b"]


def matmul(x: jax.Array, w: jax.Array, matmul_dtype: str) -> jax.Array:
    """x @ w, in bf16 where `multiplies_in_bf16` (a dense layer without its bias)."""
    return bf16_matmul(x, w) if multiplies_in_bf16(w.shape, matmul_dtype) else x @ w


LAYER_NORM_EPS = 1e-5  # torch.nn.LayerNorm's


def layer_norm(x: jax.Array, eps: float = LAYER_NORM_EPS) -> jax.Array:
    mean = jnp.mean(x, axis=-1, keepdims=True)
    var = jnp.mean(jnp.square(x - mean), axis=-1, keepdims=True)
    return (x - mean) * jax.lax.rsqrt(var + eps)


@dataclass(frozen=True)
class BatchRenorm:
    """Batch renormalisation (Ioffe 2017) with the settings CrossQ uses (Bhatt et al. 2024): plain batch
    normalisation until `renorm` is switched on, then the batch statistics corrected towards the running
    ones by r in [1/r_max, r_max] and d in [-d_max, d_max], so that training and acting see the same
    normalisation. Evaluation mode (acting, and the critics inside the actor's loss) uses the running ones."""
    momentum: float = 0.99
    eps: float = 1e-3
    r_max: float = 3.0
    d_max: float = 5.0

    def __call__(self, x: jax.Array, layer: dict, stats: dict, train: bool,
                 renorm: jax.Array | bool = False) -> tuple[jax.Array, dict]:
        """(the normalised x, the new running statistics); the statistics change only in training mode."""
        if not train:
            x_hat = (x - stats["mean"]) * jax.lax.rsqrt(stats["var"] + self.eps)
            return x_hat * layer["norm_scale"] + layer["norm_bias"], stats
        # both moments in one pass over x (one fused reduction instead of two in a row; with the critics
        # vmapped, CrossQ's update at HalfCheetah's sizes, batch 128, bf16: 1.71 -> 1.59 ms on CPU), taken
        # about the batch's first row so that a large mean cannot cancel the variance
        shifted = x - jax.lax.stop_gradient(x[0])
        shift_mean = jnp.mean(shifted, axis=0)
        var = jnp.maximum(jnp.mean(jnp.square(shifted), axis=0) - jnp.square(shift_mean), 0.0)
        mean = shift_mean + jax.lax.stop_gradient(x[0])
        inv_std = jax.lax.rsqrt(var + self.eps)
        running_inv_std = jax.lax.rsqrt(stats["var"] + self.eps)
        r = jax.lax.stop_gradient(jnp.clip((var + self.eps) * inv_std * running_inv_std, 1.0 / self.r_max, self.r_max))
        d = jax.lax.stop_gradient(jnp.clip((mean - stats["mean"]) * running_inv_std, -self.d_max, self.d_max))
        r, d = jnp.where(renorm, r, 1.0), jnp.where(renorm, d, 0.0)
        scale = layer["norm_scale"] * inv_std * r  # x_hat * scale + bias with x_hat = (x - mean) / std * r + d
        y = (shifted - shift_mean) * scale + (layer["norm_scale"] * d + layer["norm_bias"])
        m = self.momentum
        new_stats = {"mean": m * stats["mean"] + (1.0 - m) * jax.lax.stop_gradient(mean),
                     "var": m * stats["var"] + (1.0 - m) * jax.lax.stop_gradient(var)}
        return y, new_stats


def dropout_mask(key: jax.Array, rate: float, shape: tuple[int, ...]) -> jax.Array:
    """Inverted dropout's multiplier: 0 with probability `rate`, else 1 / (1 - rate). The bits come from XLA's
    RngBitGenerator (threefry), which a CPU runs ~2.5x faster than jax.random's threefry (2.4 against 6.3 ms for
    2^19 draws here): DroQ draws one for every hidden unit of every critic pass, up to 60 passes per env step."""
    key4 = jnp.concatenate([key, jax.random.fold_in(key, 1)])
    bits = jax.lax.rng_bit_generator(key4, shape, dtype=jnp.uint32, algorithm=jax.lax.RandomAlgorithm.RNG_THREE_FRY)[1]
    threshold = jnp.uint32(min(round(rate * 2.0**32), 2**32 - 1))
    return jnp.where(bits >= threshold, jnp.float32(1.0 / (1.0 - rate)), jnp.float32(0.0))


def dropout(x: jax.Array, rate: float, key: jax.Array) -> jax.Array:
    """Inverted dropout: each unit zeroed with probability `rate`, the rest scaled by 1/(1 - rate)."""
    return x * dropout_mask(key, rate, x.shape)


def stack(trees: list[Params]) -> Params:
    """Trees of the same shape stacked leaf by leaf on a new leading axis (the critic ensemble's layout)."""
    return jax.tree_util.tree_map(lambda *leaves: np.stack(leaves), *trees)


def each_critic(params: Params, i: int) -> Params:
    return jax.tree_util.tree_map(lambda p: p[i], params)
