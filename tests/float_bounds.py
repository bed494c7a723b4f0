"""How far a float32 evaluation of an agent's deterministic policy can be from the exact one.

`action_bound(agent, obs)` gives the float64 reference of what agent.predict(obs, deterministic=True)
computes and a bound on how far ANY float32 evaluation of that network can be from it, per observation
and action dimension: XLA on any CPU (any summation order, FMA or not, any vector width), the exported
NumPy forward pass and onnxruntime's graph alike. Two float32 programs then differ by at most twice the
bound, whatever order their sums run in, so the export tests compare each program with the reference
instead of one CPU's result with another's through a fixed tolerance.

The model is the standard forward error analysis (Higham, Accuracy and Stability of Numerical
Algorithms, ch. 3), carried layer by layer as a vector `e` of bounds on |computed - reference|:

* a dot product of length n plus a bias, computed in float32 in any order, with or without FMA:
  |fl(x.w + b) - (x.w + b)| <= gamma_{n+1} (|x|.|w| + |b|), gamma_k = k u / (1 - k u), u = 2^-24;
  the magnitudes |x| are those of the computed inputs, |x_ref| + e;
* an input error e becomes e @ |W| after the layer; an activation f carries it on as the spread of f over
  [x_ref - e, x_ref + e] (relu, tanh, elu and clips are monotone, gelu is on either side of its minimum:
  a dead relu or a saturated tanh passes no error on) and adds its own evaluation error (bounds below);
* elementwise normalisations cost a few u of the magnitudes involved: obs_norm's (x - mean) / std, CrossQ's
  batch renormalisation (x - mean) * rsqrt(var + eps) * scale + bias; clips are 1-Lipschitz;
* bf16 layers (networks.multiplies_in_bf16) round their inputs to bfloat16 (8 significant bits) before an
  exact bf16 x bf16 product and a float32 sum. The reference rounds its own input the same way. Rounding
  is monotone, so a computed input within e of x_ref rounds to a value between round(x_ref - e) and
  round(x_ref + e): where that interval holds no rounding boundary, to the reference's own bf16 value (no
  error left), else at most one bf16 step away. Rare observations near a boundary get a bound as large as
  their true error can be, the others keep a float32-sized one;
* CrossQ's batch renormalisation: JAX evaluates it as written, before the dot; the export folds it into
  the float32 layers' weights in float64 (networks/mlp.py, _fold_batch_renorm) and rounds them once, which rounds
  differently. Each layer's rounding term is the larger of the two programs' terms, so the bound covers
  both (a bound built from the exported, folded arrays would understate JAX's error where x ~ mean).

Second-order terms (products of two rounding errors, ~1e-14 relative) are left out: first order.
Underflow: XLA may flush subnormals to zero; each layer carries an absolute 2^-126-sized term for it.
Out of scope: GPU float32 matmuls, which JAX runs in TF32 on recent NVIDIA GPUs by default (inputs
rounded to 11 bits); the tests act on the CPU.
"""

from __future__ import annotations

import numpy as np

U = 2.0**-24  # float32's unit roundoff (round to nearest)
TINY = 2.0**-126  # float32's smallest normal number: what a flush of a subnormal can cost

# The transcendentals' evaluation error, |computed - exact| <= ABS + REL * |f(x)| for a float32 input x.
# Measured once against float64 on a dense float32 grid (29 million points in [-30, 30], every 61st float32 by
# bits) with XLA's CPU kernels (default ISA, AVX2 and SSE4_2), NumPy and onnxruntime 1.32: worst relative
# errors tanh 5.9u (XLA under SSE4_2; 4.8u otherwise; onnxruntime 5.2u, NumPy 1.8u), elu 5.8u (XLA;
# onnxruntime's exp(x) - 1 is off by 1u absolute, not relative, near 0), rsqrt 2.7u; gelu (below) 3.9u |x|.
# These functions are rational or polynomial approximations evaluated in float32 (XLA's CPU tanh is one,
# clamped to +-1 beyond |x| ~ 9): a couple of u of approximation error plus about one u per arithmetic
# step of the evaluation, a property of the algorithm, not of one CPU; the bounds below take 16u, about
# three times the worst seen, for an evaluation order or FMA use that differs on another CPU.
ACT_ABS = 4 * U  # near 0 (exp(x) - 1, or a polynomial's absolute error around a zero of f)
ACT_REL = 16 * U
# gelu is x * 0.5 * (1 + tanh(z)): where tanh(z) ~ -1 the sum cancels, so its error is relative to |x|, not to
# |gelu(x)| (measured: 3.9u |x| at most, XLA and onnxruntime; 1.9u NumPy). 16u |x| covers tanh's bound (4u + 16u,
# halved by the 0.5), the rounding of z (5 operations, times |z| sech^2(z) <= 0.45) and of the products.
GELU_REL_X = 16 * U
# rsqrt(var + eps) in batch renormalisation: the computed value's relative error (2.7u measured, a Newton step
# on a 12-14-bit hardware estimate or sqrt and a division), plus the rounding of var + eps and of eps
# itself (u each, halved by the square root)
RSQRT_REL = 8 * U + U
GELU_C1, GELU_C2 = float(np.float32(np.sqrt(2.0 / np.pi))), float(np.float32(0.044715))  # float32, as computed


def gamma(n: int) -> float:
    """gamma_n = n u / (1 - n u): the relative bound of an n-term float32 sum of products."""
    return n * U / (1.0 - n * U)


def round_bf16(x: np.ndarray) -> np.ndarray:
    """float64 values rounded to bfloat16's 8 significant bits, to nearest, ties to even (exact in float64)."""
    mantissa, exponent = np.frexp(np.asarray(x, np.float64))  # |mantissa| in [0.5, 1)
    return np.ldexp(np.round(mantissa * 256.0), exponent - 8)  # np.round: ties to even


def _activation(name: str, x: np.ndarray) -> np.ndarray:
    if name == "relu":
        return np.maximum(x, 0.0)
    if name == "tanh":
        return np.tanh(x)
    if name == "elu":
        return np.where(x > 0, x, np.expm1(np.minimum(x, 0.0)))
    if name == "gelu":  # jax.nn.gelu's default tanh form, with the float32 constants the programs multiply by
        return x * 0.5 * (1.0 + np.tanh(GELU_C1 * (x + GELU_C2 * x**3)))
    if name == "silu":  # x * sigmoid(x)
        return x * 0.5 * (1.0 + np.tanh(0.5 * x))
    raise ValueError(name)


def _minimum(name: str, lo: float, hi: float) -> float:
    """Where gelu's tanh form (x ~ -0.75) or silu (x ~ -1.28) turns, their minimum: bisection on the sign of the
    slope, in float64."""
    slope = lambda x: (_activation(name, x + 1e-7) - _activation(name, x - 1e-7))
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if slope(mid) < 0 else (lo, mid)
    return 0.5 * (lo + hi)


def _propagated(name: str, x_ref: np.ndarray, e: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A bound on |f(x) - f(x_ref)| for every |x - x_ref| <= e: relu, tanh, elu and clips are monotone, so f(x) lies
    between f(x_ref - e) and f(x_ref + e) (exact: an inactive relu or a saturated tanh passes no error on);
    gelu and silu are monotone on either side of their minimum, which joins the candidates where the interval
    holds it. (float64's own rounding of these values, 2^-52 relative, is covered by the 2^-50 term.)"""
    lo, hi = _activation(name, x_ref - e), _activation(name, x_ref + e)
    spread = np.maximum(np.abs(hi - y), np.abs(y - lo))
    if name in MINIMUM_AT:
        at = MINIMUM_AT[name]
        inside = (x_ref - e <= at) & (at <= x_ref + e)
        spread = np.where(inside, np.maximum(spread, np.abs(y - _activation(name, at))), spread)
    return spread + 2.0**-50 * (np.abs(y) + np.abs(lo) + np.abs(hi))


def _activation_error(name: str, x_ref: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the activation of the reference, a bound on the error of the computed activation): the input's error
    carried through, plus the activation's own evaluation error at the computed input."""
    y = _activation(name, x_ref)
    propagated = _propagated(name, x_ref, e, y)
    if name == "relu":  # exact
        return y, propagated
    if name == "gelu":
        return y, propagated + ACT_ABS + GELU_REL_X * (np.abs(x_ref) + e) + ACT_REL * (np.abs(y) + propagated)
    return y, propagated + ACT_ABS + ACT_REL * (np.abs(y) + propagated)


MINIMUM_AT = {"gelu": _minimum("gelu", -1.5, -0.25), "silu": _minimum("silu", -2.0, -0.5)}


def _bf16_inputs(x_ref: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the reference's bf16-rounded input, a bound on |round(x) - round(x_ref)| for any |x - x_ref| <= e)."""
    r = round_bf16(x_ref)
    error = np.maximum(round_bf16(x_ref + e) - r, r - round_bf16(x_ref - e))
    return r, error + TINY * (e > 0)  # (a subnormal input flushed to zero)


def _dense(x_ref, e, w, b, bf16: bool):
    """One dense layer x @ w + b: (its reference, the propagated error, the magnitudes its rounding scales).
    A bf16 layer rounds x and w to bf16 first, the reference too."""
    if bf16:
        x_ref, e = _bf16_inputs(x_ref, e)
        w = round_bf16(w)
    z = x_ref @ w + b
    return z, e @ np.abs(w), (np.abs(x_ref) + e) @ np.abs(w) + np.abs(b)


def _weights(layer: dict) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(layer["w"], np.float64), np.asarray(layer["b"], np.float64)


def _rounded_dense(x: np.ndarray, e: np.ndarray, w: np.ndarray, b: np.ndarray, bf16: bool) -> tuple[np.ndarray, np.ndarray]:
    """(reference, bound) of a dense layer computed in float32: the propagated error, the sum's rounding and
    the flush of subnormals."""
    n = w.shape[0]
    z, e, magnitude = _dense(x, e, w, b, bf16)
    return z, e + gamma(n + 1) * magnitude + TINY * (n + 1) * (1.0 + np.abs(w).max())


def network_bound(layers: list, x: np.ndarray, e: np.ndarray, activation: str, matmul_dtype: str = "float32",
                  norm=None, stats: list | None = None, out_columns: int | None = None,
                  layer_norm: bool | str = False) -> tuple[np.ndarray, np.ndarray]:
    """(reference, bound) of an MLP's outputs (networks.mlp, or networks.batch_renorm_mlp in evaluation mode with
    `norm` and its running `stats`) for inputs within `e` of the float64 `x`; `out_columns`: the first ones only;
    `layer_norm`: a LayerNorm without scale or bias before each hidden activation (actor_layer_norm), or after it
    ("after": layer_norm_position after)."""
    from softac.learner.networks.layers import LAYER_NORM_EPS

    from softac.learner.networks.layers import multiplies_in_bf16

    stats = stats if stats is not None else [None] * len(layers)
    for i, (layer, layer_stats) in enumerate(zip(layers, stats)):
        w, b = _weights(layer)
        bf16 = multiplies_in_bf16(w.shape, matmul_dtype)
        if i == len(layers) - 1 and out_columns is not None:
            w, b = w[:, :out_columns], b[:out_columns]
        n = w.shape[0]
        folded_rounding = 0.0
        if norm is not None:
            var = np.asarray(layer_stats["var"], np.float32).astype(np.float64)
            mean = np.asarray(layer_stats["mean"], np.float64)
            scale, bias = np.asarray(layer["norm_scale"], np.float64), np.asarray(layer["norm_bias"], np.float64)
            s = scale / np.sqrt(var + norm.eps)  # exact: the reference's inv_std * scale
            if not bf16:
                # the export's program: x @ fl(s w) + fl(t @ w + b), t = bias - mean s, folded in float64: the
                # weights' and the bias's roundings join the sum's (gamma_{n+2}), plus float64's own (2^-50 n)
                folded_w, t = s[:, None] * w, bias - mean * s
                folded_rounding = (gamma(n + 2) * ((np.abs(x) + e) @ np.abs(folded_w) + np.abs(t @ w + b))
                                   + 2.0**-50 * (n + 1) * (np.abs(t) @ np.abs(w) + np.abs(b)))
            x, e = _batch_norm(x, e, layer, layer_stats, norm.eps)
        z, e, magnitude = _dense(x, e, w, b, bf16)
        rounding = np.maximum(gamma(n + 1) * magnitude, folded_rounding)
        e = e + rounding + TINY * (n + 1) * (1.0 + np.abs(w).max())
        x = z
        affine = (np.asarray(layer.get("ln_scale", np.ones(x.shape[-1])), np.float64),
                  np.asarray(layer.get("ln_bias", np.zeros(x.shape[-1])), np.float64))
        if i < len(layers) - 1 and layer_norm and layer_norm != "after":
            x, e = _layer_norm(x, e, *affine, LAYER_NORM_EPS)
        if i < len(layers) - 1:
            x, e = _activation_error(activation, x, e)
        if i < len(layers) - 1 and layer_norm == "after":
            x, e = _layer_norm(x, e, *affine, LAYER_NORM_EPS)
    return x, e


def _batch_norm(x: np.ndarray, e: np.ndarray, layer: dict, stats: dict, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """(reference, bound) of a batch normalisation in evaluation mode, as JAX (and the exports' kept-apart steps)
    compute it: ((x - mean) * inv_std) * scale + bias: the subtraction, two products (u each) and inv_std's own
    error scale |x - mean| |s|, the sum |x_hat|."""
    var = np.asarray(stats["var"], np.float32).astype(np.float64)
    mean = np.asarray(stats["mean"], np.float64)
    scale, bias = np.asarray(layer["norm_scale"], np.float64), np.asarray(layer["norm_bias"], np.float64)
    s = scale / np.sqrt(var + eps)  # exact: the reference's inv_std * scale
    centred = np.abs(x - mean) + e
    x = (x - mean) * s + bias
    return x, e * np.abs(s) + (3 * U + RSQRT_REL) * centred * np.abs(s) + U * (np.abs(x) + e * np.abs(s))


def bn_mlp_bound(actor: dict, stats: dict, x: np.ndarray, e: np.ndarray, activation: str, eps: float,
                 matmul_dtype: str = "float32", out_columns: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(reference, bound) of XQC's network (networks.bn_mlp in evaluation mode): the input's batch normalisation;
    per hidden layer a matmul without bias, its batch normalisation and the activation; the output layer
    (`out_columns`: its first ones only)."""
    from softac.learner.networks.layers import multiplies_in_bf16

    x, e = _batch_norm(x, e, actor["input"], stats["input"], eps)
    for layer, layer_stats in zip(actor["layers"], stats["layers"]):
        w = np.asarray(layer["w"], np.float64)
        x, e = _rounded_dense(x, e, w, np.zeros(w.shape[1]), multiplies_in_bf16(w.shape, matmul_dtype))
        x, e = _activation_error(activation, *_batch_norm(x, e, layer, layer_stats, eps))
    w, b = _weights(actor["head"])
    return _rounded_dense(x, e, w[:, :out_columns], b[:out_columns], multiplies_in_bf16(w.shape, matmul_dtype))


def flashsac_bound(actor: dict, stats: dict, x: np.ndarray, e: np.ndarray, activation: str, eps: float,
                   matmul_dtype: str = "float32", out_columns: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(reference, bound) of FlashSAC's network (networks.flashsac in evaluation mode): the input's batch
    normalisation and the embedding; per block two matmuls, each followed by its batch normalisation and the
    activation, and the residual sum (one rounding); the RMSNorm and the output layer."""
    from softac.learner.networks.layers import multiplies_in_bf16
    from softac.learner.numpy_forward import FLASHSAC_RMS_EPS

    def matmul(x, e, w):
        w = np.asarray(w, np.float64)
        return _rounded_dense(x, e, w, np.zeros(w.shape[1]), multiplies_in_bf16(w.shape, matmul_dtype))

    x, e = matmul(*_batch_norm(x, e, actor["input"], stats["input"], eps), actor["embed"]["w"])
    for block, block_stats in zip(actor["blocks"], stats["blocks"]):
        h, e_h = _activation_error(activation, *_batch_norm(*matmul(x, e, block["w1"]), block["norm1"],
                                                            block_stats["norm1"], eps))
        h, e_h = _activation_error(activation, *_batch_norm(*matmul(h, e_h, block["w2"]), block["norm2"],
                                                            block_stats["norm2"], eps))
        x, e = x + h, e + e_h + U * (np.abs(x + h) + e + e_h)
    head = actor["head"]
    x, e = _rms_norm(x, e, np.asarray(head["rms_scale"], np.float64), FLASHSAC_RMS_EPS)
    w, b = _weights(head)
    return _rounded_dense(x, e, w[:, :out_columns], b[:out_columns], multiplies_in_bf16(w.shape, matmul_dtype))


def _rms_norm(h: np.ndarray, e: np.ndarray, scale: np.ndarray, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """(reference, bound) of RMSNorm over the last axis, h / sqrt(mean(h^2) + eps) * scale, for inputs within e of
    h, computed in float32 in any order: _layer_norm's analysis without the centring."""
    n = h.shape[-1]
    ms = (h * h).mean(axis=-1, keepdims=True)
    e_ms = (2 * np.abs(h) * e + e**2).mean(axis=-1, keepdims=True) \
        + gamma(n + 2) * ((np.abs(h) + e) ** 2).mean(axis=-1, keepdims=True)
    total = ms + eps
    e_total = e_ms + U * (total + e_ms) + U * eps
    r = 1.0 / np.sqrt(total)
    change = 0.5 * np.maximum(total - e_total, eps / 2) ** -1.5 * e_total
    e_r = change + RSQRT_REL * (r + change)
    y = h * r * scale
    m = (np.abs(h) + e) * (r + e_r) * np.abs(scale)
    return y, (e * r + (np.abs(h) + e) * e_r) * np.abs(scale) + 2 * U * m


def simba_bound(actor: dict, x: np.ndarray, e: np.ndarray, activation: str, matmul_dtype: str = "float32",
                out_columns: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(reference, bound) of a SimBa network's outputs (networks.simba) for inputs within `e` of the float64 `x`:
    the embedding; per block the LayerNorm, two dense layers with the activation between, and the residual sum
    (one rounding of the sum); the final LayerNorm and the output layer (`out_columns`: its first ones only)."""
    from softac.learner.networks.simba import SIMBA_LN_EPS
    from softac.learner.networks.layers import multiplies_in_bf16

    def dense(x, e, w, b, columns=None):
        w, b = np.asarray(w, np.float64), np.asarray(b, np.float64)
        bf16 = multiplies_in_bf16(w.shape, matmul_dtype)
        return _rounded_dense(x, e, w[:, :columns], b[:columns], bf16)

    def norm(x, e, scale, bias):
        return _layer_norm(x, e, np.asarray(scale, np.float64), np.asarray(bias, np.float64), SIMBA_LN_EPS)

    x, e = dense(x, e, actor["embed"]["w"], actor["embed"]["b"])
    for block in actor["blocks"]:
        h, e_h = norm(x, e, block["ln_scale"], block["ln_bias"])
        h, e_h = _activation_error(activation, *dense(h, e_h, block["w1"], block["b1"]))
        h, e_h = dense(h, e_h, block["w2"], block["b2"])
        x, e = x + h, e + e_h + U * (np.abs(x + h) + e + e_h)
    head = actor["head"]
    return dense(*norm(x, e, head["ln_scale"], head["ln_bias"]), head["w"], head["b"], out_columns)


def mlp_bound(layers: list, x: np.ndarray, activation: str) -> tuple[np.ndarray, np.ndarray]:
    """(reference, bound) of a float32 MLP's outputs (networks.mlp with float32 matmuls and no layer norm) for
    float32 inputs x."""
    x = np.asarray(x, np.float32).astype(np.float64)
    return network_bound(layers, x, np.zeros_like(x), activation)


def _conv(x: np.ndarray, w: np.ndarray, stride: int) -> np.ndarray:
    """A VALID convolution of [batch, h, w, c] with HWIO weights, in float64."""
    windows = np.lib.stride_tricks.sliding_window_view(x, w.shape[:2], axis=(1, 2))[:, ::stride, ::stride]
    return np.tensordot(windows, w, axes=([3, 4, 5], [2, 0, 1]))


def _layer_norm(h: np.ndarray, e: np.ndarray, scale: np.ndarray, bias: np.ndarray,
                eps: float) -> tuple[np.ndarray, np.ndarray]:
    """(reference, bound) of LayerNorm over the last axis, (h - mean) / sqrt(var + eps) * scale + bias, for inputs
    within e of h, computed in float32 in any order (mean and variance as sums divided by n, or times 1/n;
    1/sqrt as rsqrt, or a square root and a division): first order, each step's rounding carried through."""
    n = h.shape[-1]
    mean = h.mean(axis=-1, keepdims=True)
    e_mean = e.mean(axis=-1, keepdims=True) + gamma(n + 2) * (np.abs(h) + e).mean(axis=-1, keepdims=True)
    c = h - mean
    e_c = e + e_mean + U * (np.abs(c) + e + e_mean)
    var = (c * c).mean(axis=-1, keepdims=True)
    e_var = (2 * np.abs(c) * e_c + e_c**2).mean(axis=-1, keepdims=True) \
        + gamma(n + 2) * ((np.abs(c) + e_c) ** 2).mean(axis=-1, keepdims=True)
    total = var + eps
    e_total = e_var + U * (total + e_var) + U * eps  # the sum, and eps's own float32 rounding
    r = 1.0 / np.sqrt(total)
    # |d r / d total| = r^3 / 2, largest at the smallest total the error allows (eps keeps it positive); the
    # computed rsqrt's own relative error applies to the r of the computed total, at most r + that change
    change = 0.5 * np.maximum(total - e_total, eps / 2) ** -1.5 * e_total
    e_r = change + RSQRT_REL * (r + change)
    y = c * r * scale + bias
    m = (np.abs(c) + e_c) * (r + e_r) * np.abs(scale)
    return y, (e_c * r + (np.abs(c) + e_c) * e_r) * np.abs(scale) + 2 * U * m + U * (m + np.abs(bias))


def image_input_bound(agent, stacks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(reference, bound) of what an image agent's actor reads for uint8 frame stacks [batch, k, h, w, c]: the
    encoder's features (softac.learner.encoder.encode: pixels / 255 - the pixel offset, the convolutions, each output a sum of 9 c_in
    products as a dense layer's, the linear layer, LayerNorm, tanh), then the state values packed beside the
    images (exact: their float32 bytes)."""
    from softac.learner.encoder import CONV_STRIDES, LN_EPS, image_only_shape, stack_channels
    from softac.envs.pixels import state_rows

    state_dim = agent.spaces.image_state_dim
    k, height, width, channels = image_only_shape(agent.spaces.image_shape, state_dim)
    stacks = np.asarray(stacks, np.uint8).reshape(-1, *agent.spaces.image_shape)
    images = np.asarray(stack_channels(stacks[:, :, :height])).astype(np.float64)
    scaled = images / 255.0
    offset = agent.config.pixel_offset
    x = scaled - offset
    e = 3 * U * scaled + (U * np.abs(x) if offset else 0.0)  # the division (or a product by 1/255), the subtraction
    encoder = agent.learner.deployed_policy()[2]
    for layer, stride in zip(encoder["convs"], CONV_STRIDES):
        w, b = _weights(layer)
        n = w.shape[0] * w.shape[1] * w.shape[2]
        z = _conv(x, w, stride) + b
        e = _conv(e, np.abs(w), stride) + gamma(n + 1) * (_conv(np.abs(x) + e, np.abs(w), stride) + np.abs(b)) \
            + TINY * (n + 1) * (1.0 + np.abs(w).max())
        x, e = _activation_error("relu", z, e)
    head = encoder["head"]
    z, e = _rounded_dense(x.reshape(len(x), -1), e.reshape(len(e), -1), *_weights(head), False)
    z, e = _layer_norm(z, e, np.asarray(head["ln_scale"], np.float64), np.asarray(head["ln_bias"], np.float64),
                       LN_EPS)
    features, e = _activation_error("tanh", z, e)
    if state_dim == 0:
        return features, e
    rows = state_rows(state_dim, width, channels)
    raw = np.ascontiguousarray(stacks[:, -1, -rows:]).reshape(len(stacks), -1)[:, : 4 * state_dim]
    state = raw.copy().view("<f4").astype(np.float64)
    return np.concatenate([features, state], axis=1), np.concatenate([e, np.zeros_like(state)], axis=1)


def action_bound(agent, obs: np.ndarray, matmul_dtype: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(reference, bound), both float64 [batch, act_dim]: the exact deterministic actions of `agent` for the
    float32 observations `obs` [batch, obs_dim], and a bound on |a - reference| for the actions `a` of any
    float32 evaluation of the same network (agent.predict on any CPU, the ONNX and NumPy exports).

    `matmul_dtype`: how the program multiplies, if not as the agent's config says (agent.learner.functions.matmul_dtype):
    "float32" for a program that skips the bf16 roundings, as JAX 0.4.30's jitted bf16 layers do."""
    from softac.learner.normalization import EPSILON

    if agent.spaces.image_shape is not None:
        x, e = image_input_bound(agent, obs)
    else:
        x = np.asarray(obs, np.float32).reshape(-1, agent.spaces.obs_dim).astype(np.float64)
        e = np.zeros_like(x)
    if agent.learner.obs_norm is not None:
        # clip((obs - mean) / std) with the float32 mean and std that predict() and the export use: a
        # subtraction and a division, u each (4u: also a division done as a multiplication by 1/std)
        mean = agent.learner.obs_norm.mean.astype(np.float32).astype(np.float64)
        std = np.sqrt(agent.learner.obs_norm.var + EPSILON).astype(np.float32).astype(np.float64)
        clip = agent.learner.obs_norm.clip
        q = (x - mean) / std
        e = 4 * U * np.abs(q)
        x = np.clip(q, -clip, clip)  # monotone: a value beyond the clip by more than its error has none left
        e = np.maximum(np.clip(q + e, -clip, clip) - x, x - np.clip(q - e, -clip, clip))

    norm, matmul_dtype = agent.learner.functions.policy.batch_renorm, matmul_dtype or agent.learner.functions.matmul_dtype
    actor, actor_stats, _ = agent.learner.deployed_policy()  # the averaged actor with policy_average_tau
    if agent.config.network == "simba":
        x, e = simba_bound(actor, x, e, agent.config.activation, matmul_dtype, out_columns=agent.spaces.act_dim)
    elif agent.config.network == "flashsac":
        x, e = flashsac_bound(actor, actor_stats, x, e, agent.config.activation, norm.eps, matmul_dtype,
                              out_columns=agent.spaces.act_dim)
    elif agent.config.network == "bn_mlp":
        x, e = bn_mlp_bound(actor, actor_stats, x, e, agent.config.activation, norm.eps, matmul_dtype,
                            out_columns=agent.spaces.act_dim)
    else:
        x, e = network_bound(actor, x, e, agent.config.activation, matmul_dtype, norm,
                             actor_stats if norm is not None else None,
                             out_columns=agent.spaces.act_dim,  # only the mean action's columns (not the log-std)
                             layer_norm=agent.learner.functions.policy.layer_norm)
    if agent.learner.functions.policy.sde:  # gSDE's mean clip: monotone and 1-Lipschitz, as the obs clip above
        from softac.learner.policy import SDE_CLIP_MEAN

        clipped = np.clip(x, -SDE_CLIP_MEAN, SDE_CLIP_MEAN)
        e = np.maximum(np.clip(x + e, -SDE_CLIP_MEAN, SDE_CLIP_MEAN) - clipped,
                       clipped - np.clip(x - e, -SDE_CLIP_MEAN, SDE_CLIP_MEAN))
        x = clipped

    # action = clip(mid + half * tanh(x), low, high): tanh carries the error through as above and adds its own,
    # the product and the sum round (u each), the clip is 1-Lipschitz
    low, high = agent.learner.scaler.low.astype(np.float64), agent.learner.scaler.high.astype(np.float64)
    mid, half = agent.learner.scaler.bias.astype(np.float64), agent.learner.scaler.scale.astype(np.float64)
    t, e = _activation_error("tanh", x, e)
    reference = np.clip(mid + half * t, low, high)
    bound = half * e + U * half * (np.abs(t) + e) + U * (np.abs(mid + half * t) + half * e)
    return reference, bound


def assert_within_bound(actions: np.ndarray, reference: np.ndarray, bound: np.ndarray, what: str = "") -> None:
    actions = np.asarray(actions, np.float64).reshape(reference.shape)
    excess = np.abs(actions - reference) / bound
    if not np.all(excess <= 1.0):
        i = np.unravel_index(np.argmax(excess), excess.shape)
        raise AssertionError(f"{what}: {np.sum(excess > 1.0)} of {excess.size} actions outside the float32 bound; "
                             f"worst at {tuple(map(int, i))}: {actions[i]!r} vs reference {reference[i]!r}, "
                             f"off by {abs(actions[i] - reference[i]):.3g} = {excess[i]:.3g} x its bound "
                             f"{bound[i]:.3g}")
