"""CrossQ (Bhatt et al. 2024): batch renormalisation, the joint critic pass without target critics, the
actor's update with the critics in evaluation mode, Adam's b1, and what CrossQ keeps in the state."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softac import SAC
from softac.learner import build, losses, policy
from softac.config.sac_config import SACConfig
from softac.learner.networks.layers import BatchRenorm, init_norm_stats

from conftest import assert_clean_error, run_cli
from test_sac_losses import ACT, BATCH, OBS, batch, constant_actor, constant_critics

NORM = BatchRenorm(momentum=0.9)
POLICY = policy.Policy("relu", -20.0, 2.0, "clamp", batch_renorm=NORM)
CRITICS = losses.Critics("relu", unroll=True, batch_renorm=NORM)


def _layer(n, scale=1.0, bias=0.0):
    return {"norm_scale": np.full(n, scale, np.float32), "norm_bias": np.full(n, bias, np.float32)}


@pytest.mark.numerics
def test_training_mode_normalises_with_the_batch_and_moves_the_running_statistics():
    x = jnp.asarray(np.random.default_rng(0).normal(3.0, 2.0, size=(64, 4)), jnp.float32)
    stats = {"mean": np.zeros(4, np.float32), "var": np.ones(4, np.float32)}
    y, new = NORM(x, _layer(4, scale=2.0, bias=1.0), stats, train=True)
    z = (np.asarray(y) - 1.0) / 2.0
    # float32 batch moments over 64 rows: gamma_64 = 64 * 2^-24 ~ 4e-6 of their terms' sizes (z ~ 1, mean(x) ~ 3
    # from terms ~ 3; the variance's one pass a few times that)
    np.testing.assert_allclose(z.mean(0), 0.0, atol=1e-5)
    np.testing.assert_allclose(z.var(0), np.asarray(x).var(0) / (np.asarray(x).var(0) + NORM.eps), rtol=1e-4)
    np.testing.assert_allclose(new["mean"], 0.1 * np.asarray(x).mean(0), rtol=1e-5)
    np.testing.assert_allclose(new["var"], 0.9 + 0.1 * np.asarray(x).var(0), rtol=1e-5)


@pytest.mark.numerics
def test_evaluation_mode_uses_the_running_statistics_and_keeps_them():
    x = jnp.asarray([[1.0, 5.0], [3.0, -1.0]], jnp.float32)
    stats = {"mean": np.asarray([1.0, 2.0], np.float32), "var": np.asarray([4.0, 9.0], np.float32)}
    y, same = NORM(x, _layer(2), stats, train=False)
    expected = (np.asarray(x) - stats["mean"]) / np.sqrt(stats["var"] + NORM.eps)
    # float32: var + eps, rsqrt (a few 2^-24 on any CPU), two products: rtol 1e-6 is ~17 of them
    np.testing.assert_allclose(np.asarray(y), expected, rtol=1e-6)
    assert same is stats


@pytest.mark.numerics
def test_renormalisation_corrects_the_batch_statistics_towards_the_running_ones():
    """After the warm-up, x_hat = (x - mean_B) / std_B * r + d with r = std_B / std_run clipped to [1/3, 3]
    and d = (mean_B - mean_run) / std_run clipped to [-5, 5] (Ioffe 2017): with r and d inside their clips
    this is exactly the running statistics' normalisation; outside, the clipped correction."""
    x = jnp.asarray(np.random.default_rng(1).normal(0.5, 1.5, size=(256, 3)), jnp.float32)
    near = {"mean": np.full(3, 0.4, np.float32), "var": np.full(3, 2.0, np.float32)}
    y, _ = NORM(x, _layer(3), near, train=True, renorm=True)
    np.testing.assert_allclose(np.asarray(y), (np.asarray(x) - 0.4) / np.sqrt(2.0 + NORM.eps), rtol=1e-4, atol=1e-5)
    plain, _ = NORM(x, _layer(3), near, train=True, renorm=False)
    assert not np.allclose(np.asarray(plain), np.asarray(y), atol=1e-3)

    far = {"mean": np.full(3, -100.0, np.float32), "var": np.full(3, 1e-4, np.float32)}  # r, d both clip
    y, _ = NORM(x, _layer(3), far, train=True, renorm=True)
    xs = np.asarray(x)
    z = (xs - xs.mean(0)) / np.sqrt(xs.var(0) + NORM.eps)
    np.testing.assert_allclose(np.asarray(y), z * 3.0 + 5.0, rtol=1e-4, atol=1e-4)


@pytest.mark.numerics
def test_crossq_critic_loss_bootstraps_from_the_online_critics():
    """No target critics: the target takes the smaller of the online critics' Q(s', a')."""
    mean, log_std, alpha, gamma = [0.3, -0.2], [-1.0, -0.5], 0.2, 0.9
    b = batch([1.0, -2.0, 0.5, 3.0], [0.0, 0.0, 1.0, 0.0])
    actor = constant_actor(mean, log_std)
    actor = [{**layer, **_layer(layer["w"].shape[0])} for layer in actor]
    actor_stats = init_norm_stats([OBS, 4, 2 * ACT])
    critic = constant_critics(1.0, 2.0)
    critic = [{**layer, "norm_scale": np.ones((2, layer["w"].shape[1]), np.float32),
               "norm_bias": np.zeros((2, layer["w"].shape[1]), np.float32)} for layer in critic]
    critic_stats = jax.tree_util.tree_map(lambda *x: np.stack(x), *[init_norm_stats([OBS + ACT, 4, 1])] * 2)
    key = jax.random.PRNGKey(3)
    loss, (metrics, new_stats) = losses.soft_q_loss(critic, critic_stats, (), actor, actor_stats, jnp.float32(alpha),
                                                 b, key, POLICY, CRITICS, gamma)
    _, log_prob = POLICY.sample(actor, actor_stats, b.next_obs, key)
    target = np.asarray(b.rewards) + gamma * (1 - np.asarray(b.terminated)) * (1.0 - alpha * np.asarray(log_prob))
    expected = 0.5 * (np.mean((1.0 - target) ** 2) + np.mean((2.0 - target) ** 2))
    assert float(loss) == pytest.approx(expected, rel=1e-5)
    assert float(metrics["q1_mean"]) == pytest.approx(1.0) and float(metrics["q2_mean"]) == pytest.approx(2.0)
    # one pass over (s, a) and (s', a') together: the input layer's statistics are those of all 2B rows
    rows = np.concatenate([np.asarray(b.obs), np.asarray(b.next_obs)])
    # the batch mean is summed about the first row in float32: 2B + 4 roundings of terms of size |row - row_0|
    # (a mean of -0.018 from terms ~0.5 here), the momentum's 0.1 scaling them
    sizes = np.abs(rows - rows[0]).mean(0) + np.abs(rows.mean(0))
    np.testing.assert_array_less(np.abs(np.asarray(new_stats[0]["mean"])[:, :OBS] - 0.1 * rows.mean(0)),
                                 np.tile(0.1 * (2 * BATCH + 4) * 2**-24 * sizes, (2, 1)))
    # the gradient lowers Q_2 (above every target) and keeps the target fixed (stop_gradient)
    grads = jax.grad(lambda c: losses.soft_q_loss(c, critic_stats, (), actor, actor_stats, jnp.float32(alpha), b, key,
                                               POLICY, CRITICS, gamma)[0])(critic)
    assert float(grads[-1]["b"][1, 0]) == pytest.approx(np.mean(2.0 - target), rel=1e-5)


@pytest.mark.numerics
def test_crossq_actor_loss_uses_the_critics_running_statistics_and_updates_the_actors():
    actor = constant_actor([0.1, 0.1], [-1.0, -1.0])
    actor = [{**layer, **_layer(layer["w"].shape[0])} for layer in actor]
    actor_stats = init_norm_stats([OBS, 4, 2 * ACT])
    fns = build.build(SACConfig().replace(crossq=True, hidden_sizes=[8], batch_size=BATCH), OBS, ACT)
    state = fns.init(0)
    obs = jnp.asarray(np.random.default_rng(2).normal(2.0, 1.0, size=(BATCH, OBS)), jnp.float32)
    key = jax.random.PRNGKey(0)
    critics = losses.Critics("relu", unroll=True, batch_renorm=BatchRenorm())

    def loss(critic_stats):
        return losses.policy_loss(actor, actor_stats, state.critic, critic_stats, jnp.float32(0.1), obs, key, POLICY,
                               critics)

    value, (log_prob, new_actor_stats) = loss(state.variants.critic_stats)
    shifted = jax.tree_util.tree_map(lambda s: s + 1.0, state.variants.critic_stats)
    assert float(loss(shifted)[0]) != pytest.approx(float(value))  # the critics read their running statistics
    np.testing.assert_allclose(np.asarray(new_actor_stats[0]["mean"]), 0.1 * np.asarray(obs).mean(0), rtol=1e-5)
    assert log_prob.shape == (BATCH,)


def _batches(rng, steps, size, obs_dim=3, act_dim=2):
    return losses.Batch(obs=rng.standard_normal((steps, size, obs_dim), dtype=np.float32),
                     actions=rng.uniform(-1, 1, (steps, size, act_dim)).astype(np.float32),
                     rewards=rng.standard_normal((steps, size), dtype=np.float32),
                     next_obs=rng.standard_normal((steps, size, obs_dim), dtype=np.float32),
                     terminated=np.zeros((steps, size), np.float32), steps=np.ones((steps, size), np.float32))


@pytest.mark.numerics
def test_crossq_update_keeps_no_targets_and_moves_both_networks_statistics():
    cfg = SACConfig().replace(crossq=True, hidden_sizes=[16, 16], batch_size=8, policy_delay=3)
    fns = build.build(cfg, 3, 2)
    state = fns.init(0)
    assert state.target_critic == () and len(state.variants.actor_stats) == 3 and len(state.variants.critic_stats) == 3
    state, metrics = fns.update(state, _batches(np.random.default_rng(0), 2, 8))
    assert all(np.isfinite(float(v)) for v in metrics.values())
    assert np.any(np.asarray(state.variants.critic_stats[1]["var"]) != 1.0)
    assert not np.any(np.asarray(state.variants.actor_stats[0]["mean"]))  # no actor step yet (policy_delay 3)
    state, _ = fns.update(state, _batches(np.random.default_rng(1), 1, 8))
    assert np.any(np.asarray(state.variants.actor_stats[0]["mean"]))


@pytest.mark.numerics
def test_adam_b1_sets_the_first_moment_decay():
    """After one step Adam's first moment is (1 - b1) * gradient: b1 0.5 keeps 5x what b1 0.9 keeps."""
    moments = {}
    for b1 in (0.5, 0.9):
        fns = build.build(SACConfig().replace(hidden_sizes=[16], batch_size=8, adam_b1=b1), 3, 2)
        state, _ = fns.update(fns.init(0), _batches(np.random.default_rng(0), 1, 8))
        moments[b1] = np.asarray(state.critic_opt[0].mu[0]["w"])
    np.testing.assert_allclose(moments[0.5], 5.0 * moments[0.9], rtol=1e-4, atol=1e-9)


@pytest.mark.numerics
def test_adam_b2_sets_the_second_moment_decay():
    """After one step Adam's second moment is (1 - b2) * gradient^2: b2 0.95 (FastSAC's) keeps 50x what 0.999 keeps,
    for the alpha optimiser too."""
    moments = {}
    for b2 in (0.95, 0.999):
        fns = build.build(SACConfig().replace(hidden_sizes=[16], batch_size=8, adam_b2=b2), 3, 2)
        state, _ = fns.update(fns.init(0), _batches(np.random.default_rng(0), 1, 8))
        moments[b2] = (np.asarray(state.critic_opt[0].nu[0]["w"]), np.asarray(state.alpha_opt[0].nu))
    for fast, slow in zip(moments[0.95], moments[0.999]):
        np.testing.assert_allclose(fast, 50.0 * slow, rtol=1e-4, atol=1e-12)


@pytest.mark.exact
def test_crossq_reset_renews_the_statistics(tiny):
    agent = SAC(tiny(crossq=True))
    agent.learn(400, progress=False)
    after = agent.learner.functions.reset(agent.learner.state, agent.config.seed, 1)
    assert np.any(np.asarray(agent.learner.state.variants.critic_stats[0]["mean"]))
    for leaf, fresh in zip(jax.tree_util.tree_leaves(after.variants.critic_stats),
                           jax.tree_util.tree_leaves(agent.learner.functions.init(0).variants.critic_stats), strict=True):
        np.testing.assert_array_equal(leaf, fresh)


@pytest.mark.exact
def test_a_crossq_agent_learns_and_predicts_with_its_statistics(tiny, tmp_path):
    agent = SAC(tiny(crossq=True, adam_b1=0.5, policy_delay=3, eval_interval=300))
    agent.learn(600, run_dir=tmp_path / "run", progress=False)
    obs = np.random.default_rng(0).normal(size=(8, 2)).astype(np.float32)
    loaded = SAC.load(tmp_path / "run", which="last")
    np.testing.assert_array_equal(agent.predict(obs), loaded.predict(obs))
    zeroed = agent.learner.functions.act_deterministic(agent.learner.state.actor, jax.tree_util.tree_map(jnp.zeros_like,
                                                                                   agent.learner.state.variants.actor_stats), obs)
    assert not np.allclose(np.asarray(zeroed), np.asarray(agent.learner.functions.act_deterministic(
        agent.learner.state.actor, agent.learner.state.variants.actor_stats, obs)))  # acting reads the running statistics


def test_crossq_with_layer_norm_critics_is_refused_in_one_line(tmp_path):
    r = run_cli("train", "--steps", "10", "--out", str(tmp_path / "run"), "--set", "crossq=true",
                "critic_layer_norm=true")
    assert_clean_error(r, "critic_layer_norm", "crossq")
    assert not (tmp_path / "run").exists()
    r = run_cli("train", "--steps", "10", "--out", str(tmp_path / "run"), "--set", "adam_b1=1")
    assert_clean_error(r, "adam_b1")
    r = run_cli("train", "--steps", "10", "--out", str(tmp_path / "run"), "--set", "weight_norm=true")
    assert_clean_error(r, "weight_norm", "needs crossq")
    assert not (tmp_path / "run").exists()


def _hidden_unit_norms(layers):
    """The length of each hidden unit's (weights, bias) vector, per hidden layer."""
    return [np.sqrt(np.sum(np.square(np.asarray(layer["w"], np.float64)), axis=-2) +
                    np.square(np.asarray(layer["b"], np.float64))) for layer in layers[:-1]]


@pytest.mark.numerics
def test_weight_norm_keeps_every_hidden_unit_on_the_unit_sphere_and_the_output_layers_free():
    """CrossQ+WN (Palenicek et al. 2025): after init and after every optimiser step of the critics and of the
    actor, each hidden unit's incoming (weights, bias) has length 1; the output layers are left as they are."""
    cfg = SACConfig().replace(crossq=True, weight_norm=True, hidden_sizes=[16, 16], batch_size=8, policy_delay=1)
    fns = build.build(cfg, 3, 2)
    state = fns.init(0)
    plain = build.build(cfg.replace(weight_norm=False), 3, 2).init(0)
    for before in (state.actor, state.critic):
        for norms in _hidden_unit_norms(before):
            np.testing.assert_allclose(norms, 1.0, rtol=1e-6)  # float32 division: a few ulps
    # the same draws as without weight_norm, scaled; the output layers untouched
    np.testing.assert_array_equal(state.critic[-1]["w"], plain.critic[-1]["w"])
    w, w0 = np.asarray(state.actor[0]["w"]), np.asarray(plain.actor[0]["w"])
    np.testing.assert_allclose(w / np.linalg.norm(w, axis=0), w0 / np.linalg.norm(w0, axis=0), rtol=1e-5)
    for seed in range(3):
        new, metrics = fns.update(state, _batches(np.random.default_rng(seed), 2, 8))
        assert all(np.isfinite(float(v)) for v in metrics.values())
        for networks in ((new.actor, state.actor), (new.critic, state.critic)):
            for norms in _hidden_unit_norms(networks[0]):
                np.testing.assert_allclose(norms, 1.0, rtol=1e-6)
            assert not np.array_equal(networks[0][0]["w"], networks[1][0]["w"])  # they learn, on the sphere
        output = new.critic[-1]
        output_norms = np.sqrt(np.sum(np.square(output["w"]), axis=-2) + np.square(output["b"]))
        assert np.all(np.abs(output_norms - 1.0) > 1e-3)  # the output layer keeps its own scale
        state = new


@pytest.mark.numerics
def test_weight_norm_changes_nothing_for_a_network_whose_units_are_already_unit_length():
    from softac.learner.networks.layers import unit_norm_hidden_units

    rng = np.random.default_rng(0)
    layers = [{"w": rng.normal(size=(2, 4, 5)), "b": rng.normal(size=(2, 5))} for _ in range(2)]
    once = unit_norm_hidden_units(layers, np)
    twice = unit_norm_hidden_units(once, np)
    np.testing.assert_allclose(twice[0]["w"], once[0]["w"], rtol=1e-12)
    assert once[1] is layers[1]  # the output layer is the same object
    # a stacked ensemble: each critic's units normalised on their own
    np.testing.assert_allclose(_hidden_unit_norms(once)[0], np.ones((2, 5)), rtol=1e-12)
    ratio = once[0]["w"] / layers[0]["w"]
    np.testing.assert_allclose(ratio, np.broadcast_to(ratio[:, :1, :], ratio.shape), rtol=1e-12)  # one scale per unit


@pytest.mark.exact
def test_a_crossq_wn_agent_resumes_exactly(tiny, tmp_path):
    agent = SAC(tiny(crossq=True, weight_norm=True, eval_interval=300))
    agent.learn(300, run_dir=tmp_path / "run", progress=False)
    resumed = SAC.load(tmp_path / "run", which="last")
    agent.learn(200, progress=False)
    resumed.learn(200, progress=False)
    for a, b in zip(jax.tree_util.tree_leaves(agent.learner.state), jax.tree_util.tree_leaves(resumed.learner.state),
                    strict=True):
        np.testing.assert_array_equal(a, b)
