"""`softac export`: a run's deterministic policy as an ONNX graph or a NumPy .npz, to act without JAX.

Both formats hold the same float32 arrays (`policy_arrays`, laid out as softac.export_numpy describes):
observation normalisation (obs_norm), the actor's layers up to the mean action, and the action bounds;
the graph computes what `softac.export_numpy.policy_forward` does, which is what
`agent.predict(obs, deterministic=True)` does. Runs trained with bfloat16 matmuls are exported in float32:
their actions differ from predict()'s by bf16 rounding of the hidden layers' inputs.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from softac import __version__
from softac.checkpoint import is_checkpoint
from softac.errors import SoftacError
from softac.export_numpy import layer_count
from softac.normalization import EPSILON
from softac.rundir import write_atomic

if TYPE_CHECKING:
    from softac.agent import SAC

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

def _fold_batch_renorm(layer: dict, stats: dict, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """(w, b) of one dense layer with its input's batch renormalisation (evaluation mode: running statistics)
    folded in: ((x - mean) / sqrt(var + eps) * scale + bias) @ w + b == x @ (s[:, None] * w) + (t @ w + b),
    with s = scale / sqrt(var + eps) and t = bias - mean * s. Folded in float64, then rounded once."""
    w, b = np.asarray(layer["w"], np.float64), np.asarray(layer["b"], np.float64)
    s = np.asarray(layer["norm_scale"], np.float64) / np.sqrt(np.asarray(stats["var"], np.float64) + eps)
    t = np.asarray(layer["norm_bias"], np.float64) - np.asarray(stats["mean"], np.float64) * s
    return (s[:, None] * w).astype(np.float32), (t @ w + b).astype(np.float32)


def _actor_layers(agent: SAC) -> list[tuple[np.ndarray, np.ndarray]]:
    """The actor's (w, b) per layer, the last cut to the mean action's columns (the log-std is not needed)."""
    actor, norm = agent.state.actor, agent.fns.policy.norm
    if norm is None:
        layers = [(np.asarray(layer["w"], np.float32), np.asarray(layer["b"], np.float32)) for layer in actor]
    else:
        layers = [_fold_batch_renorm(layer, stats, norm.eps) for layer, stats in zip(actor, agent.state.actor_stats)]
    w, b = layers[-1]
    act_dim = agent.spaces.act_dim
    layers[-1] = (np.ascontiguousarray(w[:, :act_dim]), np.ascontiguousarray(b[:act_dim]))
    return layers


def policy_arrays(agent: SAC) -> dict[str, np.ndarray]:
    """Everything the deterministic policy needs, as named float32 arrays (the activation's name aside), and a
    few entries for the record."""
    arrays: dict[str, np.ndarray] = {}
    if agent.obs_norm is not None:  # as RunningObsNorm.normalize computes them
        arrays["obs_mean"] = agent.obs_norm.mean.astype(np.float32)
        arrays["obs_std"] = np.sqrt(agent.obs_norm.var + EPSILON).astype(np.float32)
        arrays["obs_clip"] = np.asarray(agent.obs_norm.clip, np.float32)
    for i, (w, b) in enumerate(_actor_layers(agent)):
        arrays[f"w{i}"], arrays[f"b{i}"] = w, b
    arrays["activation"] = np.asarray(agent.config.activation)
    arrays["action_low"] = agent.scaler.low.astype(np.float32)
    arrays["action_high"] = agent.scaler.high.astype(np.float32)
    arrays["env_id"] = np.asarray(agent.config.env_id)
    arrays["step"] = np.asarray(agent.num_steps, np.int64)
    arrays["softac_version"] = np.asarray(__version__)
    return arrays


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

    def const(self, name: str, value: np.ndarray | float) -> str:
        if name not in self.constants:
            array = np.asarray(value, np.float32)
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


def onnx_model(arrays: dict[str, np.ndarray]) -> Any:
    """The graph of export_numpy.policy_forward: input `obs` [batch, obs_dim], output `action` [batch, act_dim]."""
    onnx = require_onnx()
    g = _Graph(onnx)
    x = "obs"
    if "obs_mean" in arrays:
        x = g.op("Div", g.op("Sub", x, g.const("obs_mean", arrays["obs_mean"])), g.const("obs_std", arrays["obs_std"]))
        clip = float(arrays["obs_clip"])
        x = g.op("Clip", x, g.const("obs_clip_low", -clip), g.const("obs_clip_high", clip))
    n_layers = layer_count(arrays)
    for i in range(n_layers):
        x = g.op("Add", g.op("MatMul", x, g.const(f"w{i}", arrays[f"w{i}"])), g.const(f"b{i}", arrays[f"b{i}"]))
        if i < n_layers - 1:
            x = _onnx_activation(g, str(arrays["activation"]), x)
    low, high = arrays["action_low"], arrays["action_high"]
    scaled = g.op("Add", g.const("action_bias", (high + low) / 2.0),
                  g.op("Mul", g.const("action_scale", (high - low) / 2.0), g.op("Tanh", x)))
    # per-dimension bounds: Clip takes only scalar bounds
    g.op("Min", g.op("Max", scaled, g.const("action_low", low)), g.const("action_high", high), output="action")

    obs_dim, act_dim = arrays["w0"].shape[0], len(low)
    graph = onnx.helper.make_graph(
        g.nodes, "softac_policy",
        [onnx.helper.make_tensor_value_info("obs", onnx.TensorProto.FLOAT, ["batch", obs_dim])],
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

def export_policy(agent_or_path: SAC | str | Path, path: str | Path | None = None, format: str = "onnx",
                  which: str | None = None) -> Path:
    """Write the deterministic policy of an agent, a run or a checkpoint directory to `path` (default for a run:
    RUN/export/policy.onnx or .npz); `which` picks a run's best or last checkpoint (default best, else last).
    Returns the path written."""
    check_format(format)
    if format == "onnx":
        require_onnx()  # before loading anything: fail fast
    if path is None:
        if not isinstance(agent_or_path, (str, Path)):
            raise SoftacError("export_policy needs a path to write to when given an agent")
        path = default_export_path(agent_or_path, format)
    path = Path(path)
    check_target(path, format)
    agent = _load(agent_or_path, which) if isinstance(agent_or_path, (str, Path)) else agent_or_path
    arrays = policy_arrays(agent)
    data = numpy_bytes(arrays) if format == "numpy" else onnx_model(arrays).SerializeToString()
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, data)
    return path


def _load(run_or_ckpt: str | Path, which: str | None) -> SAC:
    from softac.agent import SAC

    # the CPU is enough to read weights, and a GPU run then exports on a machine without one
    return SAC.load(run_or_ckpt, which=which, device="cpu")
