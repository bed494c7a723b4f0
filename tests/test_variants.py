"""The SAC family's variants (issue 42), each pinned on a hand computation where its paper differs from SAC:
TQC's truncated atoms and quantile Huber loss (Kuznetsov et al. 2020), CrossQ with target critics (CrossQ+WN,
Palenicek et al. 2025), AdamW's decay on all or only the output layers, DroQ's critic dropout (Hiraoka et al.
2022), SimBa's residual networks (Lee et al. 2024); and each resumes exactly.

Float bounds as in test_sac_losses: the losses run in float32, the hand computations in float64; rel=1e-5 is
~170 float32 roundings of the result for a few dozen operations on terms no larger than it."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softac import SAC
from softac.learner import build, losses, policy, sac
from softac.config.sac_config import ConfigError, SACConfig
from softac.learner.networks.layers import BatchRenorm, dropout, dropout_mask, init_norm_stats, unit_norm_hidden_units
from softac.learner.networks import NETWORKS, critics_apply, init_critics
from softac.learner.networks.simba import init_simba, simba
from softac.learner.metrics import metric_means

from conftest import assert_clean_error, assert_same_training, run_cli, straight_and_resumed
from test_crossq import _batches
from test_sac_losses import ACT, BATCH, OBS, POLICY, batch, constant_actor, hand_sample

M = 3  # quantiles per critic in the hand cases


def constant_quantile_critics(*rows):
    """Critics whose quantiles are rows[i] (M values) for every (s, a): zero weights, the last bias set."""
    critics = init_critics(np.random.default_rng(0), OBS, ACT, [4], "default", len(rows), out_dim=M)
    critics = jax.tree_util.tree_map(np.zeros_like, critics)
    critics[-1]["b"] = np.asarray(rows, np.float32)
    return critics


def _hand_quantile_huber(q, target):
    """The quantile Huber loss in float64: q [n, B, M], target [B, K]; mean over B, M, K, summed over n."""
    q, target = np.asarray(q, np.float64), np.asarray(target, np.float64)
    taus = (np.arange(q.shape[-1]) + 0.5) / q.shape[-1]
    delta = target[None, :, None, :] - q[..., None]
    huber = np.where(np.abs(delta) > 1, np.abs(delta) - 0.5, 0.5 * delta**2)
    return float(np.sum(np.mean(np.abs(taus[:, None] - (delta < 0)) * huber, axis=(1, 2, 3))))


# ---- TQC -------------------------------------------------------------------------------------------------

def test_tqc_pools_the_atoms_and_drops_the_largest_per_critic():
    next_q = jnp.asarray([[[5.0, 1.0, 3.0], [0.0, 7.0, 7.0]], [[2.0, 9.0, 0.5], [7.0, 1.0, 2.0]]])  # 2 critics, 2 rows
    atoms, keep = losses.truncated_target_atoms(next_q, drop_per_critic=1)
    kept = [sorted(np.asarray(atoms)[row][np.asarray(keep)[row] == 1]) for row in range(2)]
    assert kept == [[0.5, 1.0, 2.0, 3.0], [0.0, 1.0, 2.0, 7.0]]  # 6 pooled a row, the 2 largest dropped (ties too)
    atoms, keep = losses.truncated_target_atoms(next_q, 0)
    assert sorted(np.asarray(atoms)[0]) == [0.5, 1.0, 2.0, 3.0, 5.0, 9.0] and np.all(np.asarray(keep) == 1)


@pytest.mark.numerics
def test_tqc_critic_loss_is_the_quantile_huber_loss_to_the_truncated_soft_atoms():
    key = jax.random.PRNGKey(11)
    mean, log_std = [0.3, -0.2], [-0.5, 0.1]
    rewards, terminated, alpha, gamma = [1.0, -2.0, 0.5, 3.0], [0.0, 1.0, 0.0, 0.0], 0.5, 0.9
    critic = constant_quantile_critics([0.0, 1.0, 2.5], [-1.0, 0.5, 20.0])
    target_critic = constant_quantile_critics([3.0, 4.0, 6.0], [2.0, 5.0, 8.0])
    critics = losses.Critics("relu", unroll=True, n_quantiles=M, drop_per_critic=1)
    b = batch(rewards, terminated)

    loss, (metrics, _) = losses.soft_q_loss(critic, (), target_critic, constant_actor(mean, log_std), (),
                                         jnp.float32(alpha), b, key, POLICY, critics, gamma)

    _, next_log_prob = hand_sample(key, mean, log_std)
    kept = np.asarray([2.0, 3.0, 4.0, 5.0])  # pooled 2,3,4,5,6,8; the two largest dropped (1 per critic)
    target = (np.asarray(rewards)[:, None] + gamma * (1 - np.asarray(terminated))[:, None]
              * (kept[None, :] - alpha * next_log_prob[:, None]))
    rows = np.asarray([[0.0, 1.0, 2.5], [-1.0, 0.5, 20.0]])
    q = np.broadcast_to(rows[:, None, :], (2, BATCH, M))
    assert float(loss) == pytest.approx(_hand_quantile_huber(q, target), rel=1e-5)
    assert float(metrics["q1_mean"]) == pytest.approx(3.5 / 3) and float(metrics["q2_mean"]) == pytest.approx(19.5 / 3)

    # d loss / d q_i = mean over rows and atoms of -|tau_i - 1{u < 0}| * Huber'(u), u = z - q_i, over M
    grads = jax.grad(lambda c: losses.soft_q_loss(c, (), target_critic, constant_actor(mean, log_std), (),
                                               jnp.float32(alpha), b, key, POLICY, critics, gamma)[0])(critic)
    g = np.asarray(grads[-1]["b"])
    for n in range(2):
        for i in range(M):
            u = target - rows[n, i]
            tau = (i + 0.5) / M
            want = np.mean(-np.abs(tau - (u < 0)) * np.clip(u, -1.0, 1.0)) / M
            assert g[n, i] == pytest.approx(want, rel=1e-5, abs=1e-7), (n, i)
    # a quantile above every atom (critic 2's top one, 20) comes down; critic 1's top one (2.5, tau 5/6) sits
    # below most of the atoms of the three rows that bootstrap, so it goes up
    assert g[1, 2] > 0 and g[0, 2] < 0


@pytest.mark.numerics
def test_tqc_actor_climbs_the_mean_of_all_quantiles():
    key = jax.random.PRNGKey(3)
    mean, log_std, alpha = [0.3, -0.2], [-0.5, 0.1], 0.2
    critics = losses.Critics("relu", unroll=True, n_quantiles=M, drop_per_critic=1)
    obs = batch([0.0] * BATCH, [0.0] * BATCH).obs
    loss, (log_prob, _) = losses.policy_loss(constant_actor(mean, log_std), (),
                                          constant_quantile_critics([0.0, 1.0, 2.0], [-3.0, 4.0, 8.0]), (),
                                          jnp.float32(alpha), obs, key, POLICY, critics)
    _, want_log_prob = hand_sample(key, mean, log_std)
    assert float(loss) == pytest.approx(alpha * np.mean(want_log_prob) - 12.0 / 6, rel=1e-5)


# ---- CrossQ with target critics (CrossQ+WN) ----------------------------------------------------------------

def _with_norm_layers(critic):
    return [{**layer, "norm_scale": np.ones((2, layer["w"].shape[1]), np.float32),
             "norm_bias": np.zeros((2, layer["w"].shape[1]), np.float32)} for layer in critic]


@pytest.mark.numerics
def test_crossq_with_targets_bootstraps_from_the_target_critics_joint_pass():
    """The next-state value comes from the target critics (here constant 5 and 7: the target takes 5), while the
    online critics' joint pass alone moves the running statistics."""
    from test_sac_losses import constant_critics

    norm = BatchRenorm(momentum=0.9)
    crossq_policy = policy.Policy("relu", -20.0, 2.0, "clamp", batch_renorm=norm)
    critics = losses.Critics("relu", unroll=True, batch_renorm=norm, targets=True)
    actor = [{**layer, "norm_scale": np.ones(layer["w"].shape[0], np.float32),
              "norm_bias": np.zeros(layer["w"].shape[0], np.float32)} for layer in constant_actor([0.1, 0.2], [-1, -1])]
    actor_stats = init_norm_stats([OBS, 4, 2 * ACT])
    stats = jax.tree_util.tree_map(lambda *x: np.stack(x), *[init_norm_stats([OBS + ACT, 4, 1])] * 2)
    target_stats = jax.tree_util.tree_map(lambda x: x + 3.0, stats)  # apart, to see which moves
    critic, target = _with_norm_layers(constant_critics(1.0, 2.0)), _with_norm_layers(constant_critics(5.0, 7.0))
    key, alpha, gamma = jax.random.PRNGKey(4), 0.3, 0.9
    b = batch([1.0, -2.0, 0.5, 3.0], [0.0, 0.0, 1.0, 0.0])
    loss, (metrics, new_stats) = losses.soft_q_loss(critic, stats, target, actor, actor_stats, jnp.float32(alpha), b,
                                                 key, crossq_policy, critics, gamma, target_stats=target_stats)
    _, log_prob = crossq_policy.sample(actor, actor_stats, b.next_obs, key)
    y = np.asarray(b.rewards) + gamma * (1 - np.asarray(b.terminated)) * (5.0 - alpha * np.asarray(log_prob))
    assert float(loss) == pytest.approx(0.5 * (np.mean((1.0 - y) ** 2) + np.mean((2.0 - y) ** 2)), rel=1e-5)
    rows = np.concatenate([np.asarray(b.obs), np.asarray(b.next_obs)])
    np.testing.assert_allclose(np.asarray(new_stats[0]["mean"])[0, :OBS], 0.1 * rows.mean(0), rtol=1e-4, atol=1e-6)


@pytest.mark.numerics
def test_crossq_with_targets_keeps_and_averages_target_statistics():
    cfg = SACConfig().replace(crossq=True, target_critics="on", tau=0.5, hidden_sizes=[16, 16], batch_size=8,
                              policy_delay=1)
    fns = build.build(cfg, 3, 2)
    state = fns.init(0)
    assert state.target_critic != () and len(state.variants.target_critic_stats) == 3
    before = np.array(state.variants.target_critic_stats[1]["var"], copy=True)
    state, _ = fns.update(state, _batches(np.random.default_rng(0), 1, 8))
    # target statistics = 0.5 * online (after the step) + 0.5 * old target
    np.testing.assert_allclose(np.asarray(state.variants.target_critic_stats[1]["var"]),
                               0.5 * np.asarray(state.variants.critic_stats[1]["var"]) + 0.5 * before, rtol=1e-6)
    assert build.build(cfg.replace(target_critics="auto"), 3, 2).init(0).target_critic == ()  # CrossQ's default


# ---- AdamW ---------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("layers", ["all", "output"])
def test_adamw_decays_all_or_only_the_output_layers(layers):
    """With zero gradients Adam's step is zero, so one step is the decay alone: p <- p - lr * wd * p where the
    mask says, p unchanged elsewhere."""
    cfg = SACConfig().replace(weight_decay=0.1, weight_decay_layers=layers, critic_lr=0.01, hidden_sizes=[8, 8])
    params = init_critics(np.random.default_rng(0), 3, 2, [8, 8], "default", 2)
    tx = build.optimizer(cfg, cfg.critic_lr)
    updates, _ = tx.update(jax.tree_util.tree_map(jnp.zeros_like, params), tx.init(params), params)
    for i, (layer, update) in enumerate(zip(params, updates)):
        decayed = layers == "all" or i == len(params) - 1
        for name in ("w", "b"):
            want = -0.01 * 0.1 * layer[name] if decayed else np.zeros_like(layer[name])
            np.testing.assert_allclose(np.asarray(update[name]), want, rtol=1e-6, atol=1e-12)
    assert isinstance(build.optimizer(cfg.replace(weight_decay=0.0), 1e-3), type(__import__("optax").adam(1e-3)))


def test_output_layer_mask_of_mlp_and_simba():
    mlp_mask = NETWORKS["mlp"].output_mask([{"w": 0, "b": 0, "norm_scale": 0}, {"w": 0, "b": 0, "norm_scale": 0}])
    assert mlp_mask == [{"w": False, "b": False, "norm_scale": False}, {"w": True, "b": True, "norm_scale": False}]
    assert NETWORKS["batch_renorm_mlp"].output_mask is NETWORKS["mlp"].output_mask
    mask = NETWORKS["simba"].output_mask(init_simba(np.random.default_rng(0), 3, [8], 1))
    assert mask["head"] == {"ln_scale": False, "ln_bias": False, "w": True, "b": True}
    assert not any(jax.tree_util.tree_leaves(mask["blocks"])) and not any(jax.tree_util.tree_leaves(mask["embed"]))


# ---- DroQ ---------------------------------------------------------------------------------------------------

def test_dropout_zeroes_units_at_the_rate_and_keeps_the_mean():
    x = jnp.ones((200, 500))
    y = np.asarray(dropout(x, 0.1, jax.random.PRNGKey(0)))
    zero = np.mean(y == 0.0)
    # 100,000 Bernoulli(0.1) draws: the share's std is ~0.00095; 5 std either side
    assert abs(zero - 0.1) < 0.005
    np.testing.assert_allclose(y[y != 0], 1 / 0.9, rtol=1e-6)


def test_droq_critics_drop_units_in_every_pass_with_their_own_keys():
    params = init_critics(np.random.default_rng(0), OBS, ACT, [64, 64], "default", 2)
    obs, act = jnp.ones((5, OBS)), jnp.zeros((5, ACT))
    plain = np.asarray(critics_apply(params, obs, act, "relu", normalize=True)[0])
    one = np.asarray(critics_apply(params, obs, act, "relu", normalize=True, dropout_rate=0.2, key=jax.random.PRNGKey(1))[0])
    again = np.asarray(critics_apply(params, obs, act, "relu", normalize=True, dropout_rate=0.2,
                                     key=jax.random.PRNGKey(1), unroll=True)[0])
    other = np.asarray(critics_apply(params, obs, act, "relu", normalize=True, dropout_rate=0.2,
                                     key=jax.random.PRNGKey(2))[0])
    assert not np.allclose(one, plain) and not np.allclose(one, other)
    np.testing.assert_allclose(one, again, rtol=1e-5)  # vmapped and unrolled draw the same masks
    # the same input rows in one call get different masks (each unit, each row)
    assert not np.allclose(one[:, 0], one[:, 1])
    # the critic loss and the actor loss both see dropout: two keys, two losses
    critics = losses.Critics("relu", unroll=True, layer_norm=True, dropout=0.2)
    b = batch([1.0, -2.0, 0.5, 3.0], [0.0] * BATCH)
    actor = constant_actor([0.1, 0.2], [-1.0, -1.0])
    values = {float(losses.critic_loss(params, params, actor, jnp.float32(0.1), b, jax.random.PRNGKey(k), POLICY,
                                    critics, 0.9)[0]) for k in range(3)}
    assert len(values) == 3


@pytest.mark.numerics
def test_droq_critic_loss_is_sacs_on_the_critics_with_their_drawn_masks():
    """One hidden layer of 6 units, Q_i = w2 . relu(LN(dropout(W1 x + b1))) + b2, computed by hand in float64 with
    the masks that the online and the target pass draw (losses.dropout_keys, one key per critic, networks.dropout);
    the target is the smaller target critic's value."""
    rng = np.random.default_rng(3)
    rate, alpha, gamma = 0.3, 0.2, 0.9
    critic = init_critics(rng, OBS, ACT, [6], "default", 2)
    target = init_critics(rng, OBS, ACT, [6], "default", 2)
    critics = losses.Critics("relu", unroll=True, layer_norm=True, dropout=rate)
    actor = constant_actor([0.3, -0.2], [-0.5, 0.1])
    b = batch([1.0, -2.0, 0.5, 3.0], [0.0, 1.0, 0.0, 0.0])
    key = jax.random.PRNGKey(9)
    loss, _ = losses.critic_loss(critic, target, actor, jnp.float32(alpha), b, key, POLICY, critics, gamma)

    online_key, next_key = losses.dropout_keys(key, critics)
    next_u, next_log_prob = hand_sample(key, [0.3, -0.2], [-0.5, 0.1])

    def hand_q(params, obs, actions, pass_key):
        x = np.concatenate([np.asarray(obs, np.float64), np.asarray(actions, np.float64)], -1)
        # networks.critics_apply: one key per hidden layer, one draw for every critic and row of it
        masks = np.asarray(dropout_mask(jax.random.split(pass_key, 1)[0], rate, (2, BATCH, 6)), np.float64)
        assert set(np.unique(masks)) <= {0.0, np.float32(1 / (1 - rate))}
        out = []
        for i in range(2):
            h = x @ np.asarray(params[0]["w"][i], np.float64) + np.asarray(params[0]["b"][i], np.float64)
            h = h * masks[i]
            h = (h - h.mean(-1, keepdims=True)) / np.sqrt(h.var(-1, keepdims=True) + 1e-5)
            out.append(np.maximum(h, 0) @ np.asarray(params[1]["w"][i], np.float64)[:, 0] + float(params[1]["b"][i][0]))
        return np.stack(out)

    q = hand_q(critic, b.obs, b.actions, online_key)
    next_q = hand_q(target, b.next_obs, np.tanh(next_u), next_key).min(0)
    y = np.asarray(b.rewards) + gamma * (1 - np.asarray(b.terminated)) * (next_q - alpha * next_log_prob)
    # the mask's 1/(1 - rate) is a float32 value: a few float32 roundings of the pre-activations (~1), amplified by
    # the loss's squares of terms ~1-10
    assert float(loss) == pytest.approx(0.5 * np.sum(np.mean((q - y) ** 2, axis=1)), rel=1e-4)
    # the gradient lowers each critic's output bias by the mean of (q - y)
    grads = jax.grad(lambda c: losses.critic_loss(c, target, actor, jnp.float32(alpha), b, key, POLICY, critics,
                                               gamma)[0])(critic)
    np.testing.assert_allclose(np.asarray(grads[-1]["b"])[:, 0], np.mean(q - y, axis=1), rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("keys", [
    dict(crossq=True, n_quantiles=5, top_quantiles_to_drop_per_net=1),
    dict(n_quantiles=1, top_quantiles_to_drop_per_net=0),
    dict(crossq=True, target_critics="on", weight_norm=True, n_quantiles=5),
    dict(network="simba", hidden_sizes=[16], n_quantiles=5, n_critics=3),
    dict(critic_dropout=0.05, critic_layer_norm=True, n_quantiles=5, gradient_steps=2),
    dict(target_critics="off", weight_decay=0.01),
    # FastSAC's parts (issue 67): C51 critics each toward its own target, the actor on their mean, LayerNorm and
    # SiLU in both networks, a zero actor head, AdamW with b2 0.95, two actor steps in eight critic steps
    dict(n_atoms=11, v_min=-20.0, v_max=20.0, target_q="each", actor_q="mean", critic_layer_norm=True,
         actor_layer_norm=True, activation="silu", zero_actor_head=True, adam_b2=0.95, weight_decay=0.001,
         gradient_steps=8, policy_delay=4, log_std_mode="tanh", log_std_min=-5.0, log_std_max=0.0),
    dict(crossq=True, target_q="each", actor_q="mean"),
    # RLPD's (issue 68): REDQ's subset target over an ensemble of LayerNorm critics, the actor on their mean; with
    # CrossQ's joint pass and target critics too
    dict(n_critics=5, target_q="subset", target_q_subset=2, actor_q="mean", critic_layer_norm=True,
         init="xavier_uniform", gradient_steps=4, policy_delay=4),
    dict(crossq=True, target_critics="on", n_critics=4, target_q="subset", target_q_subset=2),
])
def test_variants_compose_where_the_maths_allows(keys):
    """TQC's quantile critics with CrossQ (with and without target critics), with SimBa networks and with DroQ's
    dropout; SAC without target critics with AdamW; FastSAC's parts; RLPD's: each builds and updates to finite
    values."""
    cfg = SACConfig().replace(**{"hidden_sizes": [16, 16], "batch_size": 8, **keys})
    fns = build.build(cfg, 3, 2)
    state, totals = fns.update(fns.init(0), _batches(np.random.default_rng(0), cfg.gradient_steps, 8))
    means = metric_means(totals)
    assert set(means) >= {"critic_loss", "actor_loss", "q1_mean"} and all(np.isfinite(v) for v in means.values())
    leaf = jax.tree_util.tree_leaves(state.critic)[-1]
    assert leaf.shape[-1] == (cfg.n_quantiles or cfg.n_atoms or 1) and leaf.shape[0] == cfg.n_critics


@pytest.mark.numerics
def test_a_zero_actor_head_starts_every_state_at_the_mean_action_zero_and_one_log_std():
    """FastSAC's init (zero_actor_head): the output layer's weights and biases are 0, so the mean before tanh is 0
    and the log std is the middle of its tanh-squashed range, -2.5 in [-5, 0], whatever the observation."""
    cfg = SACConfig().replace(hidden_sizes=[16, 16], zero_actor_head=True, actor_layer_norm=True, activation="silu",
                              log_std_mode="tanh", log_std_min=-5.0, log_std_max=0.0)
    fns = build.build(cfg, 3, 2)
    state = fns.init(0)
    obs = jnp.asarray(np.random.default_rng(1).normal(scale=3.0, size=(6, 3)), jnp.float32)
    mean, log_std = fns.policy.mean_and_log_std(state.actor, (), obs)
    np.testing.assert_array_equal(np.asarray(mean), 0.0)
    np.testing.assert_allclose(np.asarray(log_std), -2.5, rtol=1e-6)
    hidden = np.asarray(state.actor[0]["w"])
    assert np.abs(hidden).max() > 0  # the hidden layers keep their usual init


@pytest.mark.numerics
def test_braxs_networks_lecun_uniform_weights_and_layer_norm_after_each_activation():
    """init lecun_uniform: weights U(+-sqrt(3 / fan_in)) (variance 1 / fan_in), biases 0; layer_norm_position after:
    each hidden layer is LayerNorm(relu(x W + b)) * scale + bias, as Brax's MLP with layer_norm (Flax's LayerNorm
    learns the scale and bias: layer_norm_affine), the critics' and the actor's."""
    cfg = SACConfig().replace(hidden_sizes=[64, 64], init="lecun_uniform", critic_layer_norm=True,
                              actor_layer_norm=True, layer_norm_position="after", layer_norm_affine=True)
    fns = build.build(cfg, 5, 2)
    state = fns.init(0)
    assert np.all(np.asarray(state.actor[0]["ln_scale"]) == 1.0) and state.critic[1]["ln_bias"].shape == (2, 64)
    moved = np.random.default_rng(3)  # the affine as training leaves it: away from 1 and 0

    def move(layers):
        return [{**layer, **({k: jnp.asarray(layer[k] + moved.normal(scale=0.3, size=np.shape(layer[k])), jnp.float32)
                              for k in ("ln_scale", "ln_bias")} if "ln_scale" in layer else {})} for layer in layers]

    state = state._replace(actor=move(state.actor), critic=move(state.critic))
    w = np.asarray(state.critic[1]["w"])  # [critic, 64, 64]
    assert np.abs(w).max() <= np.sqrt(3.0 / 64) and np.var(w) == pytest.approx(1.0 / 64, rel=0.1)
    assert not np.any(np.asarray(state.critic[0]["b"])) and not np.any(np.asarray(state.actor[-1]["b"]))

    def hand(layers, x):  # float64
        for layer in layers[:-1]:
            h = np.maximum(x @ np.asarray(layer["w"], np.float64) + np.asarray(layer["b"], np.float64), 0.0)
            x = (h - h.mean(-1, keepdims=True)) / np.sqrt(h.var(-1, keepdims=True) + 1e-5)
            x = x * np.asarray(layer["ln_scale"], np.float64) + np.asarray(layer["ln_bias"], np.float64)
        return x @ np.asarray(layers[-1]["w"], np.float64) + np.asarray(layers[-1]["b"], np.float64)

    rng = np.random.default_rng(2)
    obs, act = rng.normal(size=(7, 5)).astype(np.float32), rng.uniform(-1, 1, (7, 2)).astype(np.float32)
    q = fns.settings.critics.q_values(state.critic, (), jnp.asarray(obs), jnp.asarray(act))
    first = jax.tree_util.tree_map(lambda a: np.asarray(a)[0], state.critic)
    np.testing.assert_allclose(np.asarray(q)[0], hand(first, np.concatenate([obs, act], -1))[:, 0], rtol=1e-4,
                               atol=1e-4)
    mean, _ = fns.policy.mean_and_log_std(state.actor, (), jnp.asarray(obs))
    np.testing.assert_allclose(np.asarray(mean), hand(state.actor, obs)[:, :2], rtol=1e-4, atol=1e-4)


# ---- SimBa ---------------------------------------------------------------------------------------------------

def _hand_simba(params, x, eps=1e-6):
    """SimBa's forward in float64: embedding, x + W2 relu(W1 LN(x)) per block, LN, head."""
    p = jax.tree_util.tree_map(lambda a: np.asarray(a, np.float64), params)

    def ln(h, scale, bias):
        mu = h.mean(-1, keepdims=True)
        return (h - mu) / np.sqrt(((h - mu) ** 2).mean(-1, keepdims=True) + eps) * scale + bias

    h = x @ p["embed"]["w"] + p["embed"]["b"]
    for blk in p["blocks"]:
        h = h + np.maximum(ln(h, blk["ln_scale"], blk["ln_bias"]) @ blk["w1"] + blk["b1"], 0) @ blk["w2"] + blk["b2"]
    return ln(h, p["head"]["ln_scale"], p["head"]["ln_bias"]) @ p["head"]["w"] + p["head"]["b"]


@pytest.mark.numerics
def test_simba_network_is_pre_layer_norm_residual_blocks_and_a_final_layer_norm():
    rng = np.random.default_rng(0)
    params = init_simba(rng, 5, [16, 16], 3)
    assert params["blocks"][0]["w1"].shape == (16, 64) and params["blocks"][0]["w2"].shape == (64, 16)
    # perturb the LayerNorms' affine parts so that they take part in the check
    for blk in params["blocks"]:
        blk["ln_scale"] = rng.uniform(0.5, 1.5, 16).astype(np.float32)
        blk["ln_bias"] = rng.normal(0, 0.1, 16).astype(np.float32)
    x = rng.normal(size=(7, 5)).astype(np.float32)
    got = np.asarray(simba(params, jnp.asarray(x), "relu"))
    want = _hand_simba(params, x.astype(np.float64))
    # float32 through two residual blocks and three LayerNorms of 16 units: each output ~1, a few hundred
    # roundings of terms of size ~1-10
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)


def test_simba_init_follows_the_authors_code():
    params = init_simba(np.random.default_rng(1), 30, [256], 4)
    w1 = params["blocks"][0]["w1"]  # He normal: variance 2 / fan_in, truncated at 2 std
    assert np.var(w1) == pytest.approx(2.0 / 256, rel=0.05)
    embed = params["embed"]["w"]  # orthogonal, gain 1: orthonormal rows (30 <= 256)
    np.testing.assert_allclose(embed @ embed.T, np.eye(30), atol=1e-5)
    assert not np.any(params["blocks"][0]["b1"]) and not np.any(params["head"]["b"])


def test_simba_agent_acts_and_its_update_learns(tiny):
    # the resume test's SimBa config (VARIANTS below): one update program for both, compiled once (issue 64)
    cfg = tiny(**VARIANTS["simba"])
    agent = SAC(cfg)
    assert list(agent.learner.state.critic) == ["blocks", "embed", "head"]
    assert agent.learner.state.critic["blocks"][1]["w1"].shape == (2, 32, 128)  # two critics stacked
    assert agent.learner.state.actor["embed"]["w"].shape[1] == 16
    agent.learn(300, progress=False)
    assert np.all(np.isfinite(agent.predict(np.zeros(agent.learner.spaces.obs_dim))))


# ---- weight averaging of the deployed policy --------------------------------------------------------------------

def _numpy_tree(tree):
    return jax.tree_util.tree_map(lambda a: np.array(a, np.float64), tree)


@pytest.mark.numerics
@pytest.mark.parametrize("keys", [dict(), dict(crossq=True), dict(crossq=True, weight_norm=True)])
def test_policy_average_moves_toward_the_actor_at_its_rate_after_each_actor_step(keys):
    """After an actor step the deployed policy is (1 - tau) x what it was + tau x the new actor, running statistics
    too (Nikishin et al. 2018); under weight_norm put back on the unit sphere; a step without an actor step
    (policy_delay) leaves it. Float bound: a few float32 roundings of terms ~|w| (and a norm's sqrt and division)."""
    tau = 0.25
    cfg = SACConfig().replace(hidden_sizes=[16, 16], batch_size=8, policy_average_tau=tau, policy_delay=2, **keys)
    fns = build.build(cfg, 3, 2)
    state = fns.init(0)
    start = _numpy_tree((state.actor, state.variants.actor_stats))

    def leaves(tree):
        return jax.tree_util.tree_leaves(_numpy_tree(tree))

    assert all(np.array_equal(a, b) for a, b in zip(leaves(sac.deployed(state)[:2]), leaves(start)))
    rng = np.random.default_rng(0)
    state, _ = fns.update(state, _batches(rng, 1, 8))  # gradient step 1 of a policy_delay of 2: no actor step
    assert all(np.array_equal(a, b) for a, b in zip(leaves(state.variants.policy_average[:2]), leaves(start)))
    state, totals = fns.update(state, _batches(rng, 1, 8))  # step 2: an actor step
    assert float(totals["actor_steps"]) == 1.0
    actor, stats = _numpy_tree((state.actor, state.variants.actor_stats))
    want_actor, want_stats = jax.tree_util.tree_map(lambda old, new: (1 - tau) * old + tau * new, start, (actor, stats))
    if cfg.weight_norm:
        want_actor = unit_norm_hidden_units(want_actor, np)
        norms = [np.sqrt(np.sum(np.asarray(l["w"]) ** 2, axis=0) + np.asarray(l["b"]) ** 2)
                 for l in state.variants.policy_average[0][:-1]]
        np.testing.assert_allclose(np.concatenate(norms), 1.0, rtol=1e-5)
    got_actor, got_stats = _numpy_tree(state.variants.policy_average[:2])
    for got, want in zip(leaves((got_actor, got_stats)), leaves((want_actor, want_stats))):
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    assert not np.allclose(leaves(got_actor)[0], leaves(actor)[0])  # the average is not the actor


def test_without_policy_average_the_actor_is_deployed_and_checkpoints_are_as_before(tiny):
    agent = SAC(tiny())
    state = agent.learner.state
    assert state.variants.policy_average == () and sac.deployed(state)[0] is state.actor
    assert not any("policy_average" in name for name in agent.learner.arrays())
    averaged = SAC(tiny(policy_average_tau=0.1)).learner.arrays()
    assert any(name.startswith("state.variants.policy_average") for name in averaged)


@pytest.mark.users_xla  # two programs, one with the average, compared bit for bit (tests/fast_compile.py)
def test_policy_average_changes_what_is_deployed_and_nothing_the_agent_trains(tiny):
    """Averaging only picks the deployed policy: with crossq and policy delay 3, two runs of one seed, one
    averaging, hold the same actor, critics, optimiser states and replay buffer bit for bit (exploration acts
    with the actor), while the average they would evaluate is another network."""
    plain, averaged = (SAC(tiny(crossq=True, policy_delay=3, seed=3, policy_average_tau=t)) for t in (0.0, 0.05))
    for agent in (plain, averaged):
        agent.learn(400, progress=False)
    assert len(averaged.collector.buffer) == 400
    assert_same_training(plain, averaged, skip=("policy_average",))
    deployed = jax.tree_util.tree_leaves(sac.deployed(averaged.learner.state)[0])
    assert not np.allclose(np.asarray(deployed[0]), np.asarray(jax.tree_util.tree_leaves(averaged.learner.state.actor)[0]))


def test_an_averaging_runs_last_checkpoint_gives_its_final_evaluation_again_and_either_policy(tiny, tmp_path):
    """evaluate() seeds as training's evaluations do, so the `last` checkpoint of a finished run repeats the final
    row of eval.csv; with averaging one training holds two policies and `policy` (SAC.predict, evaluate,
    `softac eval --policy`) picks one. Without averaging "average" is a one-line error, "actor" the deployed."""
    from softac.errors import SoftacError
    from softac.run.evaluation import evaluate

    run = tmp_path / "run"
    # the resume test's averaging config (VARIANTS below): their update program is compiled once (issue 64)
    SAC(tiny(**{**VARIANTS["policy-average"], "eval_interval": 400})).learn(400, run_dir=run, progress=False)
    final = float((run / "eval.csv").read_text().splitlines()[-1].split(",")[1])
    agent = SAC.load(run, which="last")
    deployed, average, actor = (evaluate(agent, episodes=2, policy=p) for p in ("deployed", "average", "actor"))
    assert deployed["mean_return"] == pytest.approx(final, rel=1e-5, abs=1e-5)  # eval.csv keeps 6 digits
    assert average["returns"] == deployed["returns"] and average["policy"] == "average"
    assert actor["returns"] != deployed["returns"] and actor["policy"] == "actor"
    r = run_cli("eval", str(run), "--checkpoint", "last", "--episodes", "2", "--policy", "actor", "--json")
    assert r.returncode == 0 and json.loads(r.stdout)["returns"] == actor["returns"], r.stderr

    plain = SAC(tiny(seed=1))
    assert evaluate(plain, episodes=2, policy="actor")["returns"] == evaluate(plain, episodes=2)["returns"]
    with pytest.raises(SoftacError, match="no weight average of its actor"):
        evaluate(plain, episodes=2, policy="average")
    with pytest.raises(SoftacError, match="policy must be one of deployed, actor, average"):
        plain.predict(np.zeros(2, np.float32), policy="best")


# ---- the config and target entropy ------------------------------------------------------------------------

def test_target_entropy_scale():
    assert build.build(SACConfig().replace(hidden_sizes=[8], target_entropy_scale=0.5), 3, 6).target_entropy == -3.0
    assert build.build(SACConfig().replace(hidden_sizes=[8], target_entropy=-1.5), 3, 6).target_entropy == -1.5


@pytest.mark.parametrize("values,fragment", [
    ({"network": "simba", "crossq": True}, "network"),
    ({"network": "simba", "hidden_sizes": [256, 128]}, "hidden_sizes"),
    ({"n_quantiles": 5, "top_quantiles_to_drop_per_net": 5}, "top_quantiles_to_drop_per_net"),
    ({"crossq": True, "critic_dropout": 0.01}, "critic_dropout"),
    ({"weight_decay_layers": "hidden"}, "weight_decay_layers"),
    ({"target_critics": "maybe"}, "target_critics"),
    ({"policy_average_tau": 1.5}, "policy_average_tau"),
])
def test_variant_settings_that_do_not_compose_are_refused(values, fragment):
    with pytest.raises(ConfigError, match=fragment):
        SACConfig().replace(**values)


def test_a_refused_combination_is_one_line_on_the_command_line(tmp_path):
    r = run_cli("train", "--steps", "10", "--out", str(tmp_path / "run"), "--set", "network=simba", "crossq=true")
    assert_clean_error(r, "network=", "simba cannot be combined with crossq")
    assert not (tmp_path / "run").exists()


# ---- exact resume ------------------------------------------------------------------------------------------

VARIANTS = {
    "tqc": dict(n_quantiles=5, top_quantiles_to_drop_per_net=1, n_critics=3),
    "crossq-targets-adamw": dict(crossq=True, target_critics="on", weight_norm=True, weight_decay=0.01,
                                 weight_decay_layers="output", batch_renorm_warmup=400),
    "droq": dict(critic_dropout=0.01, critic_layer_norm=True, gradient_steps=3, policy_delay=3),
    "simba": dict(network="simba", hidden_sizes=[16], critic_hidden_sizes=[32, 32], obs_norm=True, weight_decay=0.01,
                  target_entropy_scale=0.5),
    # evaluations run the averaged actor: eval.csv alike means the average resumed exactly too
    "policy-average": dict(crossq=True, policy_average_tau=0.05, policy_delay=3),
}


@pytest.mark.exact
@pytest.mark.parametrize("variant", list(VARIANTS))
def test_each_variant_resumes_exactly(tiny, tmp_path, variant):
    cfg = tiny(n_envs=2, eval_interval=300, **VARIANTS[variant])
    straight, resumed = straight_and_resumed(cfg, tmp_path, 300, 200)
    assert_same_training(straight, resumed)
    assert (tmp_path / "straight" / "eval.csv").read_text() == (tmp_path / "split" / "eval.csv").read_text()
