"""The networks: a registry of network kinds, and the actor and the critic ensemble built on any of them.

Each kind is one module with one `Network` entry (networks/entry.py: init, features, head, output mask,
parameter count, and where it has them its batch normalisations' statistics and weight_norm's projection);
NETWORKS names them. A config's `network` (mlp, simba, bn_mlp, flashsac) picks the kind, CrossQ's batch
renormalisation (`crossq`) turning an MLP into a batch_renorm_mlp (`network_kind`). The critic ensemble holds
every critic's parameters stacked on a leading axis and is evaluated with one `jax.vmap` (or critic by critic,
`unroll`), so n critics cost one batched matmul per layer.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from softac.learner.networks.batch_renorm_mlp import BATCH_RENORM_MLP
from softac.learner.networks.bn_mlp import BN_MLP
from softac.learner.networks.flashsac import FLASHSAC
from softac.learner.networks.entry import Network, Params
from softac.learner.networks.layers import BatchRenorm, dense, dropout_mask, each_critic, stack
from softac.learner.networks.mlp import MLP
from softac.learner.networks.simba import SIMBA

NETWORKS: dict[str, Network] = {"mlp": MLP, "batch_renorm_mlp": BATCH_RENORM_MLP, "simba": SIMBA, "bn_mlp": BN_MLP,
                                "flashsac": FLASHSAC}


def network_kind(network: str, batch_renorm: bool) -> Network:
    """The registry's entry for a config's `network`: with CrossQ's batch renormalisation an MLP normalises each
    layer's input (batch_renorm_mlp; the config refuses it with other kinds)."""
    return NETWORKS["batch_renorm_mlp" if batch_renorm and network == "mlp" else network]


def init_actor(rng: np.random.Generator, obs_dim: int, act_dim: int, hidden: list[int], init: str,
               norm: bool = False, network: str = "mlp", sde_log_std_init: float | None = None) -> Params:
    """The actor outputs [mean, log_std] for each action dimension. With gSDE (`sde_log_std_init` given) it
    outputs the mean only, and its output layer also holds `sde_log_std`, the log std of each weight of the
    exploration matrix (output layer's input features x action dims), all at `sde_log_std_init`."""
    out_dim = act_dim if sde_log_std_init is not None else 2 * act_dim
    kind = network_kind(network, norm)
    # with orthogonal init a small last layer starts the policy near zero mean (Andrychowicz et al. 2021)
    actor = kind.init(rng, obs_dim, hidden, out_dim, init, 0.01)
    if sde_log_std_init is not None:
        kind.head(actor)["sde_log_std"] = np.full((hidden[-1], act_dim), sde_log_std_init, np.float32)
    return actor


def init_critics(rng: np.random.Generator, obs_dim: int, act_dim: int, hidden: list[int], init: str,
                 n: int, norm: bool = False, network: str = "mlp", out_dim: int = 1) -> Params:
    """n critics Q(s, a) (each with `out_dim` outputs: TQC's quantiles), parameters stacked on a leading axis
    of size n."""
    kind = network_kind(network, norm)
    return stack([kind.init(rng, obs_dim + act_dim, hidden, out_dim, init, 1.0) for _ in range(n)])


def critics_apply(params: Params, obs: jax.Array, actions: jax.Array, activation: str,
                  matmul_dtype: str = "float32", normalize: bool | str = False, unroll: bool = False,
                  network: str = "mlp", dropout_rate: float = 0.0, key: jax.Array | None = None,
                  quantiles: bool = False, stats: Params = (), batch_renorm: BatchRenorm | None = None,
                  train: bool = False, renorm: jax.Array | bool = False) -> tuple[jax.Array, Params]:
    """Q-values of every critic, shape [n_critics, batch], or with `quantiles` [n_critics, batch, outputs]
    (TQC's quantile critics, one output a quantile), and the running statistics (each critic its own; new ones
    in training mode with batch renormalisation, else `stats` as given). With `dropout_rate`, each critic and row
    drops its own hidden units (masks drawn from `key`; MLP critics). `normalize`: LayerNorm before each hidden
    activation (True or "before") or after it ("after"; MLP critics).

    The parameters are one stacked ensemble either way. `unroll` evaluates it critic by critic as
    plain 2-D matmuls, which XLA's CPU backend runs faster than the batched matmuls of `vmap`
    (sb3-preset update: 4.6 ms vs 5.6 ms, medians of 6 interleaved runs; docs/performance.md).
    """
    x = jnp.concatenate([obs, actions], axis=-1)
    kind = network_kind(network, batch_renorm is not None)

    def one(p: Params, s: Params, masks: list[jax.Array] | None) -> tuple[jax.Array, Params]:
        features, s = kind.features(p, s, x, activation, matmul_dtype, normalize, masks, batch_renorm, train,
                                    renorm)
        return dense(features, kind.head(p), matmul_dtype), s

    n = jax.tree_util.tree_leaves(params)[0].shape[0]
    masks = None
    if dropout_rate > 0:  # every critic's masks in one draw per layer: vmapped or unrolled, the same masks
        widths = [layer["w"].shape[-1] for layer in params[:-1]]
        masks = [dropout_mask(k, dropout_rate, (n, x.shape[0], w))
                 for k, w in zip(jax.random.split(key, len(widths)), widths)]
    if unroll:
        outs = [one(each_critic(params, i), each_critic(stats, i), None if masks is None else [m[i] for m in masks])
                for i in range(n)]
        q = jnp.stack([out for out, _ in outs])
        new_stats = jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *[s for _, s in outs])
    else:
        q, new_stats = jax.vmap(one)(params, stats, masks)
    return (q if quantiles else q[..., 0]), new_stats
