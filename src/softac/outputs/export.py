"""`softac export`: a run's deterministic policy as an ONNX graph or a NumPy .npz, to act without JAX.

Both formats hold the same float32 arrays (`policy_arrays`, laid out as softac.learner.numpy_forward describes):
observation normalisation (obs_norm), an image agent's encoder, the actor's layers up to the mean action,
and the action bounds;
the graph computes what `softac.learner.numpy_forward.policy_forward` does, which is what
`agent.predict(obs, deterministic=True)` does, bf16 matmuls included: an agent whose hidden layers multiply
in bfloat16 (matmul_dtype bfloat16, or auto where it picks bf16) is exported with those layers' weights
rounded to bf16 and their inputs rounded to bf16 in the forward pass, so its actions match predict()'s
rather than a float32 network's, which differ by up to a few hundredths (where this JAX's compiled layers
round at all: JAX 0.4.30's CPU backend multiplies them in float32, and there the export is float32 too:
networks.jit_keeps_bf16_rounding).
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from softac.version import __version__
from softac.run.checkpoint import is_checkpoint
from softac.errors import SoftacError
from softac.learner.numpy_forward import dense_bf16_flags, is_simba, round_bf16, simba_block_count
from softac.learner.normalization import EPSILON
from softac.run.run_dir import write_atomic
from softac.run.checkpoint_contents import load_learner

if TYPE_CHECKING:
    from softac.envs.goals import DictLayout
    from softac.learner.learner import Learner

FILE_NAMES = {"onnx": "policy.onnx", "numpy": "policy.npz"}
ONNX_OPSET = 17
ONNX_IR_VERSION = 8  # the IR version opset 17 shipped with: older onnxruntimes refuse newer ones


def check_format(format: str) -> None:
    if format not in FILE_NAMES:
        raise SoftacError(f"unknown export format '{format}' (choose from {', '.join(FILE_NAMES)})")


def require_onnx() -> Any:
    try:
        import onnx
    except ImportError:
        raise SoftacError("exporting to ONNX needs the onnx package: pip install 'softac[export]'") from None
    return onnx


def default_export_path(run_or_ckpt: str | Path, format: str) -> Path:
    """RUN/export/policy.onnx|npz, also for a checkpoint inside RUN; CKPT/export/... for a lone checkpoint."""
    base = Path(run_or_ckpt)
    if is_checkpoint(base) and base.parent.name == "checkpoints":
        base = base.parent.parent
    return base / "export" / FILE_NAMES[format]


def check_target(path: Path, format: str) -> None:
    suffix = Path(FILE_NAMES[format]).suffix
    if path.suffix != suffix:
        raise SoftacError(f"the {format} format writes a {suffix} file, not {path}")
    if is_checkpoint(path.parent):
        raise SoftacError(f"{path} is inside the checkpoint {path.parent}; write the export elsewhere")


# ---- the arrays -------------------------------------------------------------------

def _batch_renorm_steps(layer: dict, stats: dict, eps: float) -> dict[str, np.ndarray]:
    """A layer input's batch renormalisation as networks.BatchRenorm computes it in evaluation mode, step by
    step in float32 ((x - mean) * inv_std * scale + bias, inv_std from JAX's own rsqrt): the values a bf16
    layer then rounds are JAX's to the last bit, so the rounding is too."""
    import jax  # here, not at the top: `softac export` checks its inputs before JAX loads

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


def _actor_layers(learner: Learner) -> list[dict[str, np.ndarray]]:
    """The actor's layers as numpy_forward lays them out (w, b; norm, the input's batch renormalisation of a
    CrossQ layer that multiplies in bf16; bf16: whether it does), the last cut to the mean action's columns
    (the log-std is not needed)."""
    from softac.learner.networks.layers import compiled_in_bf16  # imports JAX, which the learner has loaded by now

    (actor, actor_stats, _), norm = learner.deployed_policy(), learner.functions.policy.batch_renorm
    stats = actor_stats if norm is not None else [None] * len(actor)
    layers = []
    for layer, layer_stats in zip(actor, stats):
        bf16 = compiled_in_bf16(np.shape(layer["w"]), learner.matmul_dtype)
        entry = {"w": np.asarray(layer["w"], np.float32), "b": np.asarray(layer["b"], np.float32), "bf16": bf16}
        if norm is not None and bf16:  # folded, the weights would be rounded after scaling: not what JAX does
            entry["norm"] = _batch_renorm_steps(layer, layer_stats, norm.eps)
        elif norm is not None:
            entry["w"], entry["b"] = _fold_batch_renorm(layer, layer_stats, norm.eps)
        if bf16:
            entry["w"] = round_bf16(entry["w"])
        layers.append(entry)
    act_dim = learner.spaces.act_dim
    layers[-1]["w"] = np.ascontiguousarray(layers[-1]["w"][:, :act_dim])
    layers[-1]["b"] = np.ascontiguousarray(layers[-1]["b"][:act_dim])
    return layers


def simba_actor_arrays(learner: Learner) -> dict[str, np.ndarray]:
    """A SimBa actor (networks.simba) as numpy_forward lays it out: the embedding, each residual block's
    LayerNorm and two layers, the final LayerNorm and the output layer cut to the mean action's columns;
    `bf16` marks, in that order of the dense layers, the ones that multiply in bfloat16 (weights rounded)."""
    from softac.learner.networks.simba import SIMBA_LN_EPS  # imports JAX, loaded by the learner by now
    from softac.learner.networks.layers import compiled_in_bf16

    actor, matmul_dtype = learner.deployed_policy()[0], learner.matmul_dtype
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
    put_dense("head", head["w"], head["b"], columns=learner.spaces.act_dim)
    if any(bf16_flags):
        arrays["bf16"] = np.array(bf16_flags, np.int8)
    return arrays


# the network kinds (config.network; crossq's batch-renormalised MLP among mlp's) whose layers the export lays
# out for numpy_forward and builds in ONNX
EXPORTED_NETWORKS = ("mlp", "simba")


def policy_arrays(learner: Learner, step: int) -> dict[str, np.ndarray]:
    """Everything the deterministic policy needs, as named float32 arrays (the activation's name aside), and a
    few entries for the record (`step`: the env steps it was trained for)."""
    if learner.config.network not in EXPORTED_NETWORKS:  # a kind added to the registry without its export here
        raise SoftacError(f"export writes the networks {', '.join(EXPORTED_NETWORKS)}; this agent's network is "
                          f"{learner.config.network}")
    arrays: dict[str, np.ndarray] = {}
    obs_norm = learner.obs_norm
    if obs_norm is not None:  # as RunningObsNorm.normalize computes them
        arrays["obs_mean"] = obs_norm.mean.astype(np.float32)
        arrays["obs_std"] = np.sqrt(obs_norm.var + EPSILON).astype(np.float32)
        arrays["obs_clip"] = np.asarray(obs_norm.clip, np.float32)
    if learner.config.network == "simba":
        arrays.update(simba_actor_arrays(learner))
    else:
        layers = _actor_layers(learner)
        for i, layer in enumerate(layers):
            arrays[f"w{i}"], arrays[f"b{i}"] = layer["w"], layer["b"]
            for key, value in layer.get("norm", {}).items():
                arrays[f"n{i}_{key}"] = value
        if any(layer["bf16"] for layer in layers):
            arrays["bf16"] = np.array([layer["bf16"] for layer in layers], np.int8)
    if learner.functions.policy.sde:
        from softac.learner.policy import SDE_CLIP_MEAN

        arrays["mean_clip"] = np.asarray(SDE_CLIP_MEAN, np.float32)
    if learner.spaces.image_shape is not None:
        arrays.update(encoder_arrays(learner))
    arrays["activation"] = np.asarray(learner.config.activation)
    arrays["action_low"] = learner.scaler.low.astype(np.float32)
    arrays["action_high"] = learner.scaler.high.astype(np.float32)
    if learner.spaces.layout is not None:  # a dict-observing env: the policy takes the dict, flattened in this order
        arrays.update(dict_layout_arrays(learner.spaces.layout))
    arrays["env_id"] = np.asarray(learner.config.env_id)
    arrays["step"] = np.asarray(step, np.int64)
    arrays["softac_version"] = np.asarray(__version__)
    return arrays


def encoder_arrays(learner: Learner) -> dict[str, np.ndarray]:
    """An image agent's encoder (softac.learner.encoder, float32 as it computes), the shape of the frame stacks it takes
    ([k, h, w, c], the images alone) and, for an image beside state values, the keys the state comes from."""
    from softac.learner.encoder import CONV_STRIDES, image_only_shape

    encoder, state_dim = learner.deployed_policy()[2], learner.spaces.image_state_dim
    arrays = {"image_shape": np.asarray(image_only_shape(learner.spaces.image_shape, state_dim), np.int64),
              "conv_strides": np.asarray(CONV_STRIDES, np.int64),
              "pixel_offset": np.asarray(learner.config.pixel_offset, np.float32)}
    for i, layer in enumerate(encoder["convs"]):
        arrays[f"conv{i}_w"], arrays[f"conv{i}_b"] = (np.asarray(layer[k], np.float32) for k in ("w", "b"))
    for key, value in encoder["head"].items():
        arrays[f"enc_{key}"] = np.asarray(value, np.float32)
    layout = learner.spaces.image_state
    if layout is not None:
        arrays["image_key"] = np.asarray(layout.image_key)
        arrays.update(dict_layout_arrays(layout.state))
    return arrays


def dict_layout_arrays(layout: DictLayout) -> dict[str, np.ndarray]:
    """A dict observation's keys in the order the flat vector concatenates them, and each one's size."""
    return {"obs_keys": np.asarray(list(layout.keys)),
            "obs_key_sizes": np.asarray([layout.slices[k].stop - layout.slices[k].start for k in layout.keys],
                                        np.int64)}


def numpy_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


# ---- the ONNX graph -----------------------------------------------------------------

class _Graph:
    """Nodes and constants of an ONNX graph, each node's output named after it."""

    def __init__(self, onnx: Any):
        self.onnx = onnx
        self.nodes: list[Any] = []
        self.constants: dict[str, Any] = {}

    def const(self, name: str, value: np.ndarray | float, dtype: Any = np.float32) -> str:
        if name not in self.constants:
            array = np.asarray(value, dtype)
            self.constants[name] = self.onnx.numpy_helper.from_array(array, name)
        return name

    def op(self, op_type: str, *inputs: str, output: str | None = None, **attributes: Any) -> str:
        output = output or f"{op_type.lower()}_{len(self.nodes)}"
        self.nodes.append(self.onnx.helper.make_node(op_type, list(inputs), [output], **attributes))
        return output


def _onnx_activation(g: _Graph, name: str, x: str) -> str:
    if name == "relu":
        return g.op("Relu", x)
    if name == "tanh":
        return g.op("Tanh", x)
    if name == "elu":
        return g.op("Elu", x, alpha=1.0)
    if name == "gelu":  # the tanh approximation, as jax.nn.gelu (opset 17 has no Gelu op)
        cube = g.op("Mul", g.op("Mul", x, x), x)
        inner = g.op("Add", x, g.op("Mul", g.const("gelu_c", 0.044715), cube))
        tanh = g.op("Tanh", g.op("Mul", g.const("sqrt_2_over_pi", np.sqrt(2.0 / np.pi)), inner))
        cdf = g.op("Mul", g.const("half", 0.5), g.op("Add", g.const("one", 1.0), tanh))
        return g.op("Mul", x, cdf)
    raise SoftacError(f"cannot export activation '{name}'")


def _onnx_encoder(g: _Graph, arrays: dict[str, np.ndarray], images: str) -> str:
    """softac.learner.encoder.encode on uint8 frame stacks [batch, k, h, w, c]: the frames laid along the channels
    (ONNX's Conv takes [batch, channels, h, w]), the convolutions, the features flattened in JAX's [h, w,
    channels] order, the linear layer, LayerNorm as JAX computes it, tanh."""
    from softac.learner.encoder import LN_EPS  # here, not at the top: `softac export` checks its inputs before JAX loads

    onnx = g.onnx
    k, height, width, channels = (int(n) for n in arrays["image_shape"])
    x = g.op("Sub", g.op("Div", g.op("Cast", images, to=onnx.TensorProto.FLOAT), g.const("pixel_scale", 255.0)),
             g.const("pixel_offset", float(arrays["pixel_offset"])))
    x = g.op("Reshape", g.op("Transpose", x, perm=[0, 1, 4, 2, 3]),
             g.const("stacked_shape", [-1, k * channels, height, width], np.int64))
    for i, stride in enumerate(int(n) for n in arrays["conv_strides"]):
        w = np.ascontiguousarray(np.transpose(arrays[f"conv{i}_w"], (3, 2, 0, 1)))  # HWIO -> OIHW
        x = g.op("Relu", g.op("Conv", x, g.const(f"conv{i}_w", w), g.const(f"conv{i}_b", arrays[f"conv{i}_b"]),
                              strides=[stride, stride]))
    x = g.op("Reshape", g.op("Transpose", x, perm=[0, 2, 3, 1]), g.const("flat_shape", [0, -1], np.int64))
    h = g.op("Add", g.op("MatMul", x, g.const("enc_w", arrays["enc_w"])), g.const("enc_b", arrays["enc_b"]))
    return g.op("Tanh", _onnx_layer_norm(g, arrays, h, "enc_ln", LN_EPS))


def _onnx_layer_norm(g: _Graph, arrays: dict[str, np.ndarray], x: str, name: str, eps: float) -> str:
    """LayerNorm over the last axis as networks.layer_norm computes it, then the arrays NAME_scale, NAME_bias."""
    centred = g.op("Sub", x, g.op("ReduceMean", x, axes=[-1], keepdims=1))
    variance = g.op("ReduceMean", g.op("Mul", centred, centred), axes=[-1], keepdims=1)
    inv_std = g.op("Reciprocal", g.op("Sqrt", g.op("Add", variance, g.const(f"{name}_eps", eps))))
    return g.op("Add", g.op("Mul", g.op("Mul", centred, inv_std), g.const(f"{name}_scale", arrays[f"{name}_scale"])),
                g.const(f"{name}_bias", arrays[f"{name}_bias"]))


def _onnx_dense(g: _Graph, arrays: dict[str, np.ndarray], x: str, w: str, b: str, bf16: bool) -> str:
    if bf16:  # rounded to bf16 and back, as the run's bf16 matmul sees its input
        x = g.op("Cast", g.op("Cast", x, to=g.onnx.TensorProto.BFLOAT16), to=g.onnx.TensorProto.FLOAT)
    return g.op("Add", g.op("MatMul", x, g.const(w, arrays[w])), g.const(b, arrays[b]))


def _onnx_mlp_actor(g: _Graph, arrays: dict[str, np.ndarray], x: str) -> str:
    bf16 = dense_bf16_flags(arrays)
    for i in range(len(bf16)):
        if f"n{i}_mean" in arrays:
            x = g.op("Mul", g.op("Sub", x, g.const(f"n{i}_mean", arrays[f"n{i}_mean"])),
                     g.const(f"n{i}_inv_std", arrays[f"n{i}_inv_std"]))
            x = g.op("Add", g.op("Mul", x, g.const(f"n{i}_scale", arrays[f"n{i}_scale"])),
                     g.const(f"n{i}_bias", arrays[f"n{i}_bias"]))
        x = _onnx_dense(g, arrays, x, f"w{i}", f"b{i}", bf16[i])
        if i < len(bf16) - 1:
            x = _onnx_activation(g, str(arrays["activation"]), x)
    return x


def _onnx_simba_actor(g: _Graph, arrays: dict[str, np.ndarray], x: str) -> str:
    """numpy_forward.simba_forward: the embedding, the residual blocks, the final LayerNorm, the output layer."""
    eps, n_blocks = float(arrays["ln_eps"]), simba_block_count(arrays)
    bf16 = iter(dense_bf16_flags(arrays))
    x = _onnx_dense(g, arrays, x, "embed_w", "embed_b", next(bf16))
    for i in range(n_blocks):
        h = _onnx_layer_norm(g, arrays, x, f"block{i}_ln", eps)
        h = _onnx_activation(g, str(arrays["activation"]),
                             _onnx_dense(g, arrays, h, f"block{i}_1_w", f"block{i}_1_b", next(bf16)))
        x = g.op("Add", x, _onnx_dense(g, arrays, h, f"block{i}_2_w", f"block{i}_2_b", next(bf16)))
    return _onnx_dense(g, arrays, _onnx_layer_norm(g, arrays, x, "head_ln", eps), "head_w", "head_b", next(bf16))


def onnx_model(arrays: dict[str, np.ndarray]) -> Any:
    """The graph of numpy_forward.policy_forward: input `obs` [batch, obs_dim] (for a dict-observing env, one
    input per key, [batch, size] each, concatenated in the flat observation's order), output `action`
    [batch, act_dim]. An image agent's input `obs` is uint8 frame stacks [batch, k, h, w, c]; for an image
    beside state values, the image key's input is those and each state key's [batch, size] float32."""
    onnx = require_onnx()
    g = _Graph(onnx)
    obs_dim = arrays["embed_w" if is_simba(arrays) else "w0"].shape[0]
    if "image_shape" in arrays:
        image_input = str(arrays.get("image_key", "obs"))
        stack = ["batch", *(int(n) for n in arrays["image_shape"])]
        inputs = [onnx.helper.make_tensor_value_info(image_input, onnx.TensorProto.UINT8, stack)]
        x = _onnx_encoder(g, arrays, image_input)
        if "obs_keys" in arrays:
            keys = [str(k) for k in arrays["obs_keys"]]
            inputs += [onnx.helper.make_tensor_value_info(k, onnx.TensorProto.FLOAT, ["batch", int(n)])
                       for k, n in zip(keys, arrays["obs_key_sizes"])]
            x = g.op("Concat", x, *keys, axis=1)
    elif "obs_keys" in arrays:
        keys = [str(k) for k in arrays["obs_keys"]]
        inputs = [onnx.helper.make_tensor_value_info(k, onnx.TensorProto.FLOAT, ["batch", int(n)])
                  for k, n in zip(keys, arrays["obs_key_sizes"])]
        x = g.op("Concat", *keys, axis=1)
    else:
        inputs = [onnx.helper.make_tensor_value_info("obs", onnx.TensorProto.FLOAT, ["batch", obs_dim])]
        x = "obs"
    if "obs_mean" in arrays:
        x = g.op("Div", g.op("Sub", x, g.const("obs_mean", arrays["obs_mean"])), g.const("obs_std", arrays["obs_std"]))
        clip = float(arrays["obs_clip"])
        x = g.op("Clip", x, g.const("obs_clip_low", -clip), g.const("obs_clip_high", clip))
    x = (_onnx_simba_actor if is_simba(arrays) else _onnx_mlp_actor)(g, arrays, x)
    if "mean_clip" in arrays:
        clip = float(arrays["mean_clip"])
        x = g.op("Clip", x, g.const("mean_clip_low", -clip), g.const("mean_clip_high", clip))
    low, high = arrays["action_low"], arrays["action_high"]
    scaled = g.op("Add", g.const("action_bias", (high + low) / 2.0),
                  g.op("Mul", g.const("action_scale", (high - low) / 2.0), g.op("Tanh", x)))
    # per-dimension bounds: Clip takes only scalar bounds
    g.op("Min", g.op("Max", scaled, g.const("action_low", low)), g.const("action_high", high), output="action")

    act_dim = len(low)
    graph = onnx.helper.make_graph(
        g.nodes, "softac_policy", inputs,
        [onnx.helper.make_tensor_value_info("action", onnx.TensorProto.FLOAT, ["batch", act_dim])],
        initializer=list(g.constants.values()))
    model = onnx.helper.make_model(graph, opset_imports=[onnx.helper.make_opsetid("", ONNX_OPSET)],
                                   producer_name="softac", producer_version=__version__,
                                   doc_string="deterministic SAC policy: action = bounds-scaled tanh(actor mean)")
    model.ir_version = ONNX_IR_VERSION
    onnx.helper.set_model_props(model, {key: str(arrays[key]) for key in ("env_id", "step", "softac_version")})
    onnx.checker.check_model(model)
    return model


# ---- the API ----------------------------------------------------------------------

def export_policy(agent_or_path: Any, path: str | Path | None = None, format: str = "onnx",
                  which: str | None = None, allow_new_bounds: bool = False) -> Path:
    """Write the deterministic policy of an agent (softac.SAC), a run or a checkpoint directory to `path`
    (default for a run: RUN/export/policy.onnx or .npz); `which` picks a run's best or last checkpoint
    (default best, else last); `allow_new_bounds` as in SAC.load. Returns the path written."""
    check_format(format)
    if format == "onnx":
        require_onnx()  # before loading anything: fail fast
    if path is None:
        if not isinstance(agent_or_path, (str, Path)):
            raise SoftacError("export_policy needs a path to write to when given an agent")
        path = default_export_path(agent_or_path, format)
    path = Path(path)
    check_target(path, format)
    if isinstance(agent_or_path, (str, Path)):
        # the CPU is enough to read weights, and a GPU run then exports on a machine without one
        learner, step = load_learner(agent_or_path, which, device="cpu", allow_new_bounds=allow_new_bounds)
    else:
        learner, step = agent_or_path.learner, agent_or_path.num_steps
    arrays = policy_arrays(learner, step)
    data = numpy_bytes(arrays) if format == "numpy" else onnx_model(arrays).SerializeToString()
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, data)
    return path

