"""The layers' ONNX twins, for a network kind's export (its `ActorExport.onnx`) and the export's own graph
(softac.outputs.export): each node computes what numpy_forward computes, in the same order. ONNX itself is
imported by the export (the `export` extra) and handed in on the graph."""

from __future__ import annotations

from typing import Any

import numpy as np

from softac.errors import SoftacError


class Graph:
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


def activation(g: Graph, name: str, x: str) -> str:
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
    if name == "silu":
        return g.op("Mul", x, g.op("Sigmoid", x))
    raise SoftacError(f"cannot export activation '{name}'")


def layer_norm(g: Graph, arrays: dict[str, np.ndarray], x: str, name: str, eps: float) -> str:
    """LayerNorm over the last axis as networks.layer_norm computes it, then the arrays NAME_scale, NAME_bias
    where `arrays` has them (none: no affine, as an MLP's hidden LayerNorm)."""
    centred = g.op("Sub", x, g.op("ReduceMean", x, axes=[-1], keepdims=1))
    variance = g.op("ReduceMean", g.op("Mul", centred, centred), axes=[-1], keepdims=1)
    inv_std = g.op("Reciprocal", g.op("Sqrt", g.op("Add", variance, g.const(f"{name}_eps", eps))))
    if f"{name}_scale" not in arrays:
        return g.op("Mul", centred, inv_std)
    return g.op("Add", g.op("Mul", g.op("Mul", centred, inv_std), g.const(f"{name}_scale", arrays[f"{name}_scale"])),
                g.const(f"{name}_bias", arrays[f"{name}_bias"]))


def dense(g: Graph, arrays: dict[str, np.ndarray], x: str, w: str, b: str, bf16: bool) -> str:
    return g.op("Add", matmul(g, arrays, x, w, bf16), g.const(b, arrays[b]))


def matmul(g: Graph, arrays: dict[str, np.ndarray], x: str, w: str, bf16: bool) -> str:
    """x @ arrays[w] (a dense layer without bias)."""
    if bf16:  # rounded to bf16 and back, as the run's bf16 matmul sees its input
        x = g.op("Cast", g.op("Cast", x, to=g.onnx.TensorProto.BFLOAT16), to=g.onnx.TensorProto.FLOAT)
    return g.op("MatMul", x, g.const(w, arrays[w]))
