"""What a network kind of the registry (softac.learner.networks.NETWORKS) provides: how its parameters are made,
run, counted, decayed and exported. A network's output is `dense(features(...), head(params))`; the actor and
the critic ensemble (softac.learner.networks) are built on these, whatever the kind."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

Params = Any


@dataclass(frozen=True)
class ActorExport:
    """How `softac export` writes a kind's deterministic actor. Its NumPy forward pass is numpy_forward's (a
    file that imports NumPy alone, so that users can copy it), chosen there by the arrays' `network` entry."""
    # (actor, actor_stats, batch_renorm (BatchRenorm or None), matmul_dtype, act_dim) -> named float32 arrays,
    # the output layer cut to the mean action's columns; among them `network`, the kind's registry name (an
    # MLP's layout leaves it out, as files from before it did)
    arrays: Callable[..., dict[str, Any]]
    # (onnx_layers.Graph, arrays, input name) -> the name of the mean action before tanh: numpy_forward's pass
    onnx: Callable[..., str]
    input_size: Callable[[dict[str, Any]], int]  # (arrays) -> the size of the observation vector it takes


@dataclass(frozen=True)
class Network:
    # (rng, in_dim, widths, out_dim, init, out_gain) -> parameters, drawn from the NumPy generator rng
    init: Callable[..., Params]
    # (params, stats, x, activation, matmul_dtype, normalize (LayerNorm), masks (dropout), batch_renorm, train, renorm)
    #   -> (the output layer's input, the running statistics: new ones in training mode where the kind has them)
    features: Callable[..., tuple[Any, Params]]
    head: Callable[[Params], dict]  # the output layer: {"w", "b", ...}
    output_mask: Callable[[Params], Params]  # True on the output layer's w and b (CrossQ+WN decays only those)
    parameters: Callable[[int, list[int], int], int]  # (in_dim, widths, out_dim) -> count, for the memory check
    # activations a hidden unit keeps for the backward pass, relative to a plain MLP's (the memory check)
    activation_factor: int = 1
    export: ActorExport | None = None  # None: `softac export` refuses the kind (one line)
    # (in_dim, widths, out_dim) -> fresh running statistics of its batch normalisations (mean 0, variance 1), for
    # a kind that normalises with batch statistics (crossq); None: it has none, and the config refuses crossq
    init_stats: Callable[[int, list[int], int], Params] | None = None
    # (params, xp) -> the parameters weight_norm keeps on the unit sphere after each optimiser step, projected
    # there (xp: np at init, jnp in the update); None: weight_norm is refused with the kind
    unit_norm: Callable[..., Params] | None = None
