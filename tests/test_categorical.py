"""Categorical critics (issue 66): C51's projection (Bellemare et al. 2017), the two-hot and HL-Gauss targets
(Farebrother et al. 2024), clipped double Q on distributions (the lowest-mean next distribution, as XQC and
FlashSAC), the cross-entropy loss and the actor's value, each on a hand computation; the return-based reward
scale (SimbaV2's, as XQC's std and FlashSAC's std_max); their composition with CrossQ and target critics; and
an exact resume.

Float bounds as in test_sac_losses: the losses run in float32, the hand computations in float64; rel=1e-5 is
~170 float32 roundings of the result for a few dozen operations on terms no larger than it; the
projections' masses, sums of a few products of numbers in [0, 1], are held to 1e-6."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import norm

from softac.config.sac_config import ConfigError, SACConfig
from softac.learner import build, losses
from softac.learner.metrics import metric_means
from softac.learner.networks import init_critics
from softac.learner.normalization import RunningReturnScale

from conftest import assert_same_training, straight_and_resumed
from test_crossq import _batches
from test_sac_losses import ACT, BATCH, OBS, POLICY, batch, constant_actor, hand_sample

SUPPORT = np.linspace(-2.0, 2.0, 5)  # atoms -2, -1, 0, 1, 2: spacing 1
K = len(SUPPORT)
CRITICS = losses.Critics("relu", unroll=True, n_atoms=K, v_min=-2.0, v_max=2.0)


def constant_categorical_critics(*logit_rows):
    """Critics whose logits are logit_rows[i] (K values) for every (s, a): zero weights, the last bias set."""
    critics = init_critics(np.random.default_rng(0), OBS, ACT, [4], "default", len(logit_rows), out_dim=K)
    critics = jax.tree_util.tree_map(np.zeros_like, critics)
    critics[-1]["b"] = np.asarray(logit_rows, np.float32)
    return critics


def softmax(logits):
    e = np.exp(np.asarray(logits, np.float64) - np.max(logits, axis=-1, keepdims=True))
    return e / e.sum(axis=-1, keepdims=True)


def hand_projection(atoms, probs):
    """C51's algorithm 1 in float64, floor and ceil: each clipped atom's probability to its two neighbours."""
    out = np.zeros((len(atoms), K))
    for row, (row_atoms, row_probs) in enumerate(zip(np.asarray(atoms, np.float64), np.asarray(probs, np.float64))):
        for a, p in zip(np.clip(row_atoms, SUPPORT[0], SUPPORT[-1]), row_probs):
            b = (a - SUPPORT[0]) / (SUPPORT[1] - SUPPORT[0])
            lo, hi = int(np.floor(b)), int(np.ceil(b))
            if lo == hi:
                out[row, lo] += p
            else:
                out[row, lo] += p * (hi - b)
                out[row, hi] += p * (b - lo)
    return out


# ---- the target distributions ------------------------------------------------------------------------------

@pytest.mark.numerics
def test_the_projection_keeps_each_rows_mass_and_splits_it_between_the_neighbouring_atoms():
    atoms = jnp.asarray([[0.25, 1.0, -7.0], [2.5, -1.5, 0.0]])  # between atoms, on one, and beyond either end
    probs = jnp.asarray([[0.5, 0.3, 0.2], [0.1, 0.6, 0.3]])
    m = np.asarray(losses.project_onto_support(atoms, probs, jnp.asarray(SUPPORT, jnp.float32)))
    np.testing.assert_allclose(m.sum(axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(m, hand_projection(atoms, probs), atol=1e-6)
    # row 0: 0.25 gives 0.75 of its 0.5 to atom 0 and 0.25 to atom 1; 1.0 all of its 0.3 to atom 1; -7 to -2
    np.testing.assert_allclose(m[0], [0.2, 0.0, 0.375, 0.125 + 0.3, 0.0], atol=1e-6)
    # row 1: 2.5 past the top end; -1.5 halfway between -2 and -1; 0.0 on an atom
    np.testing.assert_allclose(m[1], [0.3, 0.3, 0.3, 0.0, 0.1], atol=1e-6)


@pytest.mark.numerics
def test_two_hot_and_hl_gauss_spread_a_scalar_on_the_support():
    support = jnp.asarray(SUPPORT, jnp.float32)
    two = np.asarray(losses.two_hot(jnp.asarray([0.25, -5.0, 1.0]), support))
    np.testing.assert_allclose(two, [[0, 0, 0.75, 0.25, 0], [1, 0, 0, 0, 0], [0, 0, 0, 1, 0]], atol=1e-6)
    np.testing.assert_allclose(two @ SUPPORT, [0.25, -2.0, 1.0], atol=1e-6)  # the mean is the value, clipped

    values, sigma = np.asarray([0.3, 1.9]), 0.75
    gauss = np.asarray(losses.hl_gauss(jnp.asarray(values, jnp.float32), support, sigma))
    edges = np.append(SUPPORT - 0.5, SUPPORT[-1] + 0.5)
    cdf = norm.cdf((edges[None, :] - values[:, None]) / sigma)
    want = np.diff(cdf, axis=1) / (cdf[:, -1:] - cdf[:, :1])  # the bins' mass, renormalised to the support
    np.testing.assert_allclose(gauss, want, atol=1e-6)
    np.testing.assert_allclose(gauss.sum(axis=1), 1.0, atol=1e-6)
    assert abs(float(gauss[0] @ SUPPORT) - 0.3) < 0.05  # near the middle the mean is nearly the value


@pytest.mark.numerics
def test_clipped_double_q_takes_each_rows_lowest_mean_distribution_whole():
    support = jnp.asarray(SUPPORT, jnp.float32)
    wide = [0.5, 0.0, 0.0, 0.0, 0.5]  # mean 0, the lower in row 0
    high = [0.0, 0.0, 0.0, 0.9, 0.1]  # mean 1.1
    low = [0.0, 1.0, 0.0, 0.0, 0.0]  # mean -1, the lower in row 1
    next_probs = jnp.asarray([[wide, high], [high, low]], jnp.float32)  # [critic, row, atom]
    chosen = np.asarray(losses.lowest_mean_distribution(next_probs, support))
    np.testing.assert_array_equal(chosen, [wide, low])  # the distribution itself, not a min per atom


# ---- the loss and the actor's value --------------------------------------------------------------------------

@pytest.mark.numerics
@pytest.mark.parametrize("target_form", ["c51", "two_hot", "hl_gauss"])
def test_categorical_critic_loss_is_the_cross_entropy_to_the_soft_target_distribution(target_form):
    key = jax.random.PRNGKey(5)
    mean, log_std = [0.3, -0.2], [-0.5, 0.1]
    rewards, terminated, alpha, gamma = [0.5, -1.0, 0.2, 1.5], [0.0, 1.0, 0.0, 0.0], 0.1, 0.9
    online = [[0.0, 1.0, 2.0, 0.5, -1.0], [1.0, 0.0, 0.0, 0.0, 3.0]]
    target_logits = [[0.0, 0.0, 2.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0, 2.0]]  # critic 0's mean is the lower
    critics = losses.Critics("relu", unroll=True, n_atoms=K, v_min=-2.0, v_max=2.0, categorical_target=target_form)
    b = batch(rewards, terminated)

    loss, (metrics, _) = losses.soft_q_loss(
        constant_categorical_critics(*online), (), constant_categorical_critics(*target_logits),
        constant_actor(mean, log_std), (), jnp.float32(alpha), b, key, POLICY, critics, gamma)

    _, next_log_prob = hand_sample(key, mean, log_std)
    p = np.broadcast_to(softmax(target_logits[0]), (BATCH, K))
    bootstrap = gamma * (1.0 - np.asarray(terminated))
    r = np.asarray(rewards)
    if target_form == "c51":  # every atom shifted by the entropy term, then moved and projected
        target = hand_projection(r[:, None] + bootstrap[:, None] * (SUPPORT[None] - alpha * next_log_prob[:, None]), p)
    else:
        value = r + bootstrap * (p @ SUPPORT - alpha * next_log_prob)
        target = (hand_projection(value[:, None], np.ones((BATCH, 1))) if target_form == "two_hot" else
                  np.asarray(losses.hl_gauss(jnp.asarray(value, jnp.float32), jnp.asarray(SUPPORT, jnp.float32),
                                             0.75)))
    log_q = np.log(softmax(online))  # [critic, atom], the same in every row
    want = sum(float(np.mean(-(target * log_q[i]).sum(axis=1))) for i in range(2))
    assert float(loss) == pytest.approx(want, rel=1e-5)
    assert float(metrics["q1_mean"]) == pytest.approx(float(softmax(online[0]) @ SUPPORT), rel=1e-5)

    # d loss / d logit_k = mean over rows of (softmax_k - target_k): the logits of the atoms the target holds
    # more mass on than the critic go up
    grads = jax.grad(lambda c: losses.soft_q_loss(
        c, (), constant_categorical_critics(*target_logits), constant_actor(mean, log_std), (), jnp.float32(alpha),
        b, key, POLICY, critics, gamma)[0])(constant_categorical_critics(*online))
    g = np.asarray(grads[-1]["b"])
    np.testing.assert_allclose(g, softmax(online) - target.mean(axis=0)[None], rtol=1e-4, atol=1e-6)


@pytest.mark.numerics
def test_with_target_q_each_every_critic_learns_toward_its_own_target_critics_projection():
    """FastSAC's form: critic i's C51 target is target critic i's distribution moved and projected (no lowest-mean
    choice), and the loss sums the critics' cross-entropies."""
    key = jax.random.PRNGKey(5)
    mean, log_std = [0.3, -0.2], [-0.5, 0.1]
    rewards, terminated, alpha, gamma = [0.5, -1.0, 0.2, 1.5], [0.0, 1.0, 0.0, 0.0], 0.1, 0.9
    online = [[0.0, 1.0, 2.0, 0.5, -1.0], [1.0, 0.0, 0.0, 0.0, 3.0]]
    target_logits = [[0.0, 0.0, 2.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0, 2.0]]
    critics = dataclasses.replace(CRITICS, target_q="each")
    loss, _ = losses.soft_q_loss(
        constant_categorical_critics(*online), (), constant_categorical_critics(*target_logits),
        constant_actor(mean, log_std), (), jnp.float32(alpha), batch(rewards, terminated), key, POLICY, critics, gamma)
    _, next_log_prob = hand_sample(key, mean, log_std)
    bootstrap = gamma * (1.0 - np.asarray(terminated))
    atoms = np.asarray(rewards)[:, None] + bootstrap[:, None] * (SUPPORT[None] - alpha * next_log_prob[:, None])
    log_q = np.log(softmax(online))
    want = sum(float(np.mean(-(hand_projection(atoms, np.broadcast_to(softmax(target_logits[i]), (BATCH, K)))
                               * log_q[i]).sum(axis=1))) for i in range(2))
    assert float(loss) == pytest.approx(want, rel=1e-5)


@pytest.mark.numerics
@pytest.mark.parametrize("actor_q, pick", [("min", min), ("mean", np.mean)])
def test_the_actor_climbs_the_smallest_or_the_mean_of_the_critics_distributions_means(actor_q, pick):
    """actor_q=min (XQC's, FlashSAC's): the smallest of the critics' distribution means; actor_q=mean (FastSAC's):
    their mean. (Was two tests, one per form.)"""
    key = jax.random.PRNGKey(3)
    mean, log_std, alpha = [0.3, -0.2], [-0.5, 0.1], 0.2
    logits = [[0.0, 0.0, 0.0, 3.0, 0.0], [1.0, 0.0, 0.0, 0.0, 0.0]]
    obs = batch([0.0] * BATCH, [0.0] * BATCH).obs
    loss, _ = losses.policy_loss(constant_actor(mean, log_std), (), constant_categorical_critics(*logits), (),
                                 jnp.float32(alpha), obs, key, POLICY, dataclasses.replace(CRITICS, actor_q=actor_q))
    _, want_log_prob = hand_sample(key, mean, log_std)
    climbed = pick([float(softmax(row) @ SUPPORT) for row in logits])
    assert float(loss) == pytest.approx(alpha * np.mean(want_log_prob) - climbed, rel=1e-5)


@pytest.mark.parametrize("keys", [
    dict(),
    dict(crossq=True),  # CrossQ's joint pass, no target critics
    dict(crossq=True, target_critics="on", weight_norm=True, categorical_target="hl_gauss"),
    dict(network="simba", hidden_sizes=[16], categorical_target="two_hot", reward_scale="std"),
    dict(target_critics="off", n_critics=3, critic_layer_norm=True),
])
def test_categorical_critics_compose_with_the_other_variants(keys):
    cfg = SACConfig().replace(**{"hidden_sizes": [16, 16], "batch_size": 8, "n_atoms": 11, **keys})
    fns = build.build(cfg, 3, 2)
    state, totals = fns.update(fns.init(0), _batches(np.random.default_rng(0), 2, 8))
    means = metric_means(totals)
    assert all(np.isfinite(v) for v in means.values())
    assert -5.0 <= means["q1_mean"] <= 5.0  # a distribution's mean lies on its support
    leaf = jax.tree_util.tree_leaves(state.critic)[-1]
    assert leaf.shape[-1] == 11 and leaf.shape[0] == cfg.n_critics


# ---- the reward scale -------------------------------------------------------------------------------------

@pytest.mark.numerics
def test_the_reward_scale_is_the_running_returns_spread():
    gamma, rewards = 0.5, np.asarray([[1.0, 2.0], [3.0, -1.0], [2.0, 0.0]])
    dones = np.asarray([[0, 0], [0, 1], [0, 0]])
    std, std_max = RunningReturnScale(2, gamma, "std", 1.0), RunningReturnScale(2, gamma, "std_max", 1.0)
    assert std.scale == 1.0  # before any step
    returns, seen = np.zeros(2), []
    for r, d in zip(rewards, dones):
        returns = gamma * (1 - d) * returns + r  # as SimbaV2's normaliser: the done step's G is its reward alone
        seen.extend(returns)
        std.update(r, d)
        std_max.update(r, d)
    assert std.scale == pytest.approx(np.std(seen) + 1e-8, rel=1e-12)
    assert std_max.scale == pytest.approx(max(np.sqrt(np.var(seen) + 1e-8), np.max(np.abs(seen)) / 1.0), rel=1e-12)
    np.testing.assert_allclose(std.scale_rewards(np.asarray([2.0])), 2.0 / std.scale, rtol=1e-7)

    restored = RunningReturnScale(2, gamma, "std", 1.0)
    restored.load_state_dict(std.state_dict())
    restored.update(rewards[0], dones[0])
    std.update(rewards[0], dones[0])
    assert restored.scale == std.scale


@pytest.mark.parametrize("values,fragment", [
    ({"n_atoms": 11, "n_quantiles": 5}, "n_atoms"),
    ({"n_atoms": 1}, "n_atoms"),
    ({"n_atoms": 11, "categorical_target": "gauss"}, "categorical_target"),
    ({"v_min": 5.0, "v_max": 5.0}, "v_min"),
    ({"reward_scale": "max"}, "reward_scale"),
    ({"reward_scale": "std_max", "v_max": -1.0, "v_min": -2.0}, "reward_scale"),
    ({"hl_gauss_sigma": 0.0}, "hl_gauss_sigma"),
])
def test_categorical_settings_that_cannot_work_are_refused(values, fragment):
    with pytest.raises(ConfigError, match=fragment):
        SACConfig().replace(**values)


@pytest.mark.exact
def test_categorical_critics_with_reward_scale_resume_exactly(tiny, tmp_path):
    cfg = tiny(n_envs=2, eval_interval=300, n_atoms=11, reward_scale="std_max", crossq=True, target_critics="on")
    straight, resumed = straight_and_resumed(cfg, tmp_path, 300, 200)
    assert_same_training(straight, resumed)
    assert (tmp_path / "straight" / "eval.csv").read_text() == (tmp_path / "split" / "eval.csv").read_text()
