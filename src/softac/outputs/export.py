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

def policy_arrays(learner: Learner, step: int) -> dict[str, np.ndarray]:
    """Everything the deterministic policy needs, as named float32 arrays (the activation's name aside), and a
    few entries for the record (`step`: the env steps it was trained for)."""
    from softac.config.names import NETWORK_NAMES
    from softac.learner.networks import NETWORKS, network_kind  # imports JAX, which the learner has loaded by now

    kind = network_kind(learner.config.network, learner.config.crossq)
    if kind.export is None:  # a kind in the registry without an export of its own
        exported = [name for name in NETWORK_NAMES if name in NETWORKS and NETWORKS[name].export is not None]
        raise SoftacError(f"export writes the networks {', '.join(exported)}; this agent's network is "
                          f"{learner.config.network}")
    arrays: dict[str, np.ndarray] = {}
    obs_norm = learner.obs_norm
    if obs_norm is not None:  # as RunningObsNorm.normalize computes them
        arrays["obs_mean"] = obs_norm.mean.astype(np.float32)
        arrays["obs_std"] = np.sqrt(obs_norm.var + EPSILON).astype(np.float32)
        arrays["obs_clip"] = np.asarray(obs_norm.clip, np.float32)
    actor, actor_stats, _ = learner.deployed_policy()
    arrays.update(kind.export.arrays(actor, actor_stats, learner.functions.policy.batch_renorm, learner.matmul_dtype,
                                     learner.spaces.act_dim))
    if learner.functions.policy.sde:
        from softac.learner.policy import SDE_CLIP_MEAN

        arrays["mean_clip"] = np.asarray(SDE_CLIP_MEAN, np.float32)
    if learner.spaces.image_shape is not None:
        arrays.update(encoder_arrays(learner))
    arrays["activation"] = np.asarray(learner.config.activation)
    if learner.functions.policy.layer_norm:  # an MLP actor's LayerNorm before (or after) each hidden activation
        from softac.learner.networks.layers import LAYER_NORM_EPS

        arrays["hidden_ln_eps"] = np.asarray(LAYER_NORM_EPS, np.float32)
        if learner.functions.policy.layer_norm == "after":
            arrays["hidden_ln_after"] = np.asarray(1, np.int8)
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

def _onnx_encoder(g: Any, arrays: dict[str, np.ndarray], images: str) -> str:
    """softac.learner.encoder.encode on uint8 frame stacks [batch, k, h, w, c]: the frames laid along the channels
    (ONNX's Conv takes [batch, channels, h, w]), the convolutions, the features flattened in JAX's [h, w,
    channels] order, the linear layer, LayerNorm as JAX computes it, tanh."""
    from softac.learner.encoder import LN_EPS  # here, not at the top: `softac export` checks its inputs before JAX loads
    from softac.learner.networks.onnx_layers import layer_norm

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
    return g.op("Tanh", layer_norm(g, arrays, h, "enc_ln", LN_EPS))


def onnx_model(arrays: dict[str, np.ndarray]) -> Any:
    """The graph of numpy_forward.policy_forward: input `obs` [batch, obs_dim] (for a dict-observing env, one
    input per key, [batch, size] each, concatenated in the flat observation's order), output `action`
    [batch, act_dim]. An image agent's input `obs` is uint8 frame stacks [batch, k, h, w, c]; for an image
    beside state values, the image key's input is those and each state key's [batch, size] float32."""
    from softac.learner.networks import NETWORKS
    from softac.learner.networks.onnx_layers import Graph

    onnx = require_onnx()
    g = Graph(onnx)
    actor = NETWORKS[str(arrays.get("network", "mlp"))].export  # files hold "network" but for an MLP
    obs_dim = actor.input_size(arrays)
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
    x = actor.onnx(g, arrays, x)
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

