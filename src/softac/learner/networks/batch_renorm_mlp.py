"""CrossQ's networks (Bhatt et al. 2024): an MLP whose every layer normalises its input first with batch
renormalisation (the observation, then each hidden activation). Parameters: an MLP's layers, each also with
"norm_scale" and "norm_bias"; the running statistics are kept apart (`init_norm_stats`), so the optimisers
never see them."""

from __future__ import annotations

import jax

from softac.learner.networks import mlp
from softac.learner.networks.entry import Network, Params
from softac.learner.networks.layers import (ACTIVATIONS, BatchRenorm, dense, init_norm_stats,
                                            unit_norm_hidden_units)


def batch_renorm_mlp(params: Params, stats: Params, x: jax.Array, activation: str, norm: BatchRenorm,
                   train: bool, renorm: jax.Array | bool = False,
                   matmul_dtype: str = "float32") -> tuple[jax.Array, Params]:
    """An MLP whose every layer normalises its input first (CrossQ's networks: the observation, then each
    hidden activation); returns the output and the new running statistics."""
    features, new_stats = batch_renorm_mlp_features(params, stats, x, activation, norm, train, renorm, matmul_dtype)
    return dense(features, params[-1], matmul_dtype), new_stats


def batch_renorm_mlp_features(params: Params, stats: Params, x: jax.Array, activation: str, norm: BatchRenorm,
                              train: bool, renorm: jax.Array | bool = False,
                              matmul_dtype: str = "float32") -> tuple[jax.Array, Params]:
    """`batch_renorm_mlp` up to the output layer's input (normalised): (those features, the new statistics)."""
    act = ACTIVATIONS[activation]
    new_stats = []
    for i, (layer, layer_stats) in enumerate(zip(params, stats)):
        x, layer_stats = norm(x, layer, layer_stats, train, renorm)
        new_stats.append(layer_stats)
        if i < len(params) - 1:
            x = act(dense(x, layer, matmul_dtype))
    return x, new_stats


def _features(params, stats, x, activation, matmul_dtype, normalize=False, masks=None, batch_renorm=None,
              train=False, renorm=False):
    return batch_renorm_mlp_features(params, stats, x, activation, batch_renorm, train, renorm, matmul_dtype)


BATCH_RENORM_MLP = Network(
    init=lambda rng, in_dim, widths, out_dim, init, out_gain: mlp.init_mlp(rng, [in_dim, *widths, out_dim], init,
                                                                           out_gain, norm=True),
    features=_features, head=lambda params: params[-1], output_mask=mlp.output_layer_mask, parameters=mlp.parameters,
    init_stats=lambda in_dim, widths, out_dim: init_norm_stats([in_dim, *widths, out_dim]),
    # the export folds its batch renormalisation into the weights, or keeps it apart where a layer is bf16
    unit_norm=unit_norm_hidden_units, export=mlp.MLP_EXPORT)
