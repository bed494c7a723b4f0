"""gSDE, generalised state-dependent exploration (issue 43; Raffin et al. 2022, SB3's SAC `use_sde`): the
distribution against a hand computation, its gradients, its statistics, that training acts with each env's
exploration matrix held for sde_sample_freq steps, that its log std learns, exact resume and export.

The hand computations run in float64 and the policy in float32; bounds are float32 roundings of the terms."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import assert_clean_error, assert_same_training, run_cli, straight_and_resumed
from softac import SAC
from softac.replay.exploration import SdeNoise
from softac.learner.networks import NETWORKS, init_actor
from softac.learner.policy import SDE_CLIP_MEAN, SDE_EPSILON, Policy

OBS, ACT, HIDDEN = 3, 2, 5
POLICY = Policy("relu", -20.0, 2.0, "clamp", sde=True)


def sde_actor(seed=0, log_std_init=-1.0):
    actor = init_actor(np.random.default_rng(seed), OBS, ACT, [4, HIDDEN], "default", sde_log_std_init=log_std_init)
    actor[-1]["w"] = actor[-1]["w"] * 50.0  # means of order 1, some beyond the clip
    actor[-1]["sde_log_std"] = np.random.default_rng(seed + 1).normal(-1.0, 0.3, (HIDDEN, ACT)).astype(np.float32)
    return actor


U = 2.0**-24  # a float32 rounding


def rounding_bound(actor, obs, weights):
    """A bound on |u - u_float32|: each layer's sums round within (terms summed) * (layer width + a few) * U,
    relative to the size of the terms, not of the result; tanh and the clip are 1-Lipschitz."""
    x = np.abs(np.asarray(obs, np.float64))
    error = np.zeros_like(x)
    for layer in actor[:-1]:
        w = np.abs(np.asarray(layer["w"], np.float64))
        terms = x @ w + np.abs(layer["b"])
        error = error @ w + (w.shape[0] + 2) * U * terms
        x = terms
    head = actor[-1]
    w = np.abs(np.asarray(head["w"], np.float64)) + np.exp(np.asarray(head["sde_log_std"], np.float64)) * np.abs(weights)
    return error @ w + (w.shape[0] + 4) * U * (x @ w + np.abs(head["b"]))


def by_hand(actor, obs, weights):
    """float64: (features, clipped mean, u = mean + f @ (std * weights), log-probability of tanh(u))."""
    x = np.asarray(obs, np.float64)
    for layer in actor[:-1]:
        x = np.maximum(x @ np.asarray(layer["w"], np.float64) + layer["b"], 0.0)
    head = actor[-1]
    mean = np.clip(x @ np.asarray(head["w"], np.float64) + head["b"], -SDE_CLIP_MEAN, SDE_CLIP_MEAN)
    std = np.exp(np.asarray(head["sde_log_std"], np.float64))
    u = mean + x @ (std * weights)
    sigma = np.sqrt(x**2 @ std**2 + SDE_EPSILON)
    gaussian = -0.5 * ((u - mean) / sigma) ** 2 - np.log(sigma) - 0.5 * np.log(2 * np.pi)
    log_prob = np.sum(gaussian - np.log(1.0 - np.tanh(u) ** 2), axis=-1)
    return x, mean, u, log_prob


def test_the_actor_outputs_the_mean_and_holds_the_exploration_matrix_log_std():
    actor = init_actor(np.random.default_rng(0), OBS, ACT, [4, HIDDEN], "default", sde_log_std_init=-3.67)
    assert actor[-1]["w"].shape == (HIDDEN, ACT)  # the mean only: no log-std outputs
    np.testing.assert_array_equal(actor[-1]["sde_log_std"], np.full((HIDDEN, ACT), -3.67, np.float32))
    # AdamW's output-layer decay (CrossQ+WN) leaves the log std alone, as SB3's optimiser does
    assert NETWORKS["mlp"].output_mask(actor)[-1] == {"w": True, "b": True, "sde_log_std": False}


@pytest.mark.numerics
def test_a_sample_and_its_log_probability_match_a_hand_computation():
    actor = sde_actor()
    obs = np.random.default_rng(2).normal(0.0, 2.0, (64, OBS)).astype(np.float32)
    key = jax.random.PRNGKey(3)
    action, log_prob = POLICY.sample(actor, (), obs, key)
    weights = np.asarray(jax.random.normal(key, (HIDDEN, ACT)), np.float64)  # one matrix for the batch
    features, mean, u, expected = by_hand(actor, obs, weights)
    assert np.any(np.abs(mean) == SDE_CLIP_MEAN) and np.any(np.abs(mean) < SDE_CLIP_MEAN)  # both branches
    bound = rounding_bound(actor, obs, weights)
    assert np.all(np.abs(np.asarray(action) - np.tanh(u)) <= bound)
    # each term of the log-probability is O(10) at most here: 1e-4 is a few hundred float32 roundings
    np.testing.assert_allclose(np.asarray(log_prob), expected, rtol=1e-5, atol=1e-4)
    # the state-dependent std that mean_and_log_std reports
    _, log_std = POLICY.mean_and_log_std(actor, (), obs)
    sigma = np.sqrt(features**2 @ np.exp(2 * np.asarray(actor[-1]["sde_log_std"], np.float64)) + SDE_EPSILON)
    np.testing.assert_allclose(np.exp(np.asarray(log_std)), sigma, rtol=1e-5)
    # acting with given weights (one matrix per row) is the same function
    per_row = np.broadcast_to(weights.astype(np.float32), (64, HIDDEN, ACT))
    assert np.all(np.abs(np.asarray(POLICY.with_noise(actor, (), obs, per_row)) - np.tanh(u)) <= bound)
    assert np.all(np.abs(np.asarray(POLICY.deterministic(actor, (), obs)) - np.tanh(mean)) <= bound)


def test_the_features_learn_through_the_noise_as_in_sb3s_sac():
    """SB3's SAC makes its gSDE distribution with learn_features=True: the actor's loss reaches the hidden
    layers through the noise and the variance, not only through the mean. With the mean's weights at zero
    (a constant mean) only those paths are left, and the first layer's gradient is still not zero."""
    actor = sde_actor()
    actor[-1] = {**actor[-1], "w": np.zeros_like(actor[-1]["w"])}
    obs = np.random.default_rng(7).normal(0.0, 1.0, (32, OBS)).astype(np.float32)

    def mean_log_prob_and_action(layers):
        action, log_prob = POLICY.sample(layers, (), obs, jax.random.PRNGKey(8))
        return jnp.mean(log_prob) + jnp.mean(action)

    grads = jax.grad(mean_log_prob_and_action)(actor)
    assert float(jnp.max(jnp.abs(grads[0]["w"]))) > 1e-4
    assert float(jnp.max(jnp.abs(grads[-1]["sde_log_std"]))) > 1e-4


def test_the_noise_has_the_state_dependent_variance_and_is_smooth_in_the_state():
    actor = sde_actor()
    obs = np.random.default_rng(4).normal(0.0, 1.0, (1, OBS)).astype(np.float32)
    keys = jax.random.split(jax.random.PRNGKey(5), 20_000)
    u = jax.vmap(lambda k: jnp.arctanh(jnp.clip(POLICY.sample(actor, (), obs, k)[0], -1 + 1e-7, 1 - 1e-7)))(keys)
    mean, log_std = POLICY.mean_and_log_std(actor, (), obs)
    # over 20,000 matrices the noise's variance is f^2 @ std^2 (standard error of a variance: 1%)
    np.testing.assert_allclose(np.var(np.asarray(u)[:, 0, :], axis=0), np.exp(2 * np.asarray(log_std[0])), rtol=0.05)
    # one matrix: the noise is a function of the state, so nearby states get nearby noise (white noise would
    # differ by its whole scale)
    weights = np.random.default_rng(6).standard_normal((1, HIDDEN, ACT)).astype(np.float32)
    near = obs + 1e-3
    a, b = (np.asarray(POLICY.with_noise(actor, (), x, weights)) for x in (obs, near))
    assert np.max(np.abs(a - b)) < 0.05 * float(np.min(np.exp(log_std)))


def test_the_exploration_matrix_is_held_for_sde_sample_freq_steps_of_each_env():
    noise = SdeNoise(sample_freq=3, n_envs=2, n_features=4, act_dim=2, seed=0)
    draws = [noise.next().copy() for _ in range(7)]
    assert draws[0].shape == (2, 4, 2)
    for t in (1, 2, 4, 5):
        np.testing.assert_array_equal(draws[t], draws[t - 1])
    for t in (3, 6):
        assert not np.any(draws[t] == draws[t - 1])
    assert not np.any(draws[0][0] == draws[0][1])  # each env its own matrix
    noise.episode_ended(0)  # an episode's end keeps the matrix, as SB3's does
    np.testing.assert_array_equal(noise.next(), draws[6])


def test_one_kind_of_noise_state_is_refused_to_the_other_in_one_line():
    """A checkpoint's noise state restored into a run with the other kind names the mismatch (SoftacError),
    whichever way round."""
    from softac import SoftacError
    from softac.replay.exploration import ColoredNoise

    pink, sde = ColoredNoise(1.0, 2, 1, 50, 0), SdeNoise(8, 2, 4, 1, 0)
    for into, source, words in ((pink, sde, "is not pink noise"), (sde, pink, "not this run's gSDE")):
        meta, arrays = source.checkpoint_parts()
        with pytest.raises(SoftacError, match=words):
            into.restore(meta, arrays)


def test_training_acts_with_each_envs_exploration_matrix(tiny):
    """With the policy held fixed (no gradient steps), each training action is the policy's action for the
    weights SdeNoise gives at that step, across Pendulum's episode end at 200."""
    cfg = tiny("Pendulum-v1", n_envs=2, learning_starts=0, gradient_steps=0, exploration_noise="gsde",
               sde_sample_freq=16, sde_log_std_init=-0.5, buffer_size=1000)
    agent = SAC(cfg)
    agent.learn(440, progress=False)
    buffer = agent.collector.buffer
    replay = SdeNoise(16, 2, cfg.hidden_sizes[-1], 1, cfg.seed)
    for t in range(220):
        rows = slice(2 * t, 2 * t + 2)
        expected, _ = agent.learner.act_with_noise(buffer.obs[rows], replay.next())
        np.testing.assert_array_equal(buffer.actions[rows], expected)


def test_the_exploration_matrix_log_std_learns(tiny):
    cfg = tiny("Pendulum-v1", learning_starts=50, exploration_noise="gsde", sde_log_std_init=-2.0)
    agent = SAC(cfg)
    agent.learn(150, progress=False)
    log_std = np.asarray(agent.learner.state.actor[-1]["sde_log_std"])
    assert np.all(np.isfinite(log_std)) and np.any(log_std != np.float32(-2.0))


@pytest.mark.exact
@pytest.mark.parametrize("crossq", [False, True], ids=["sac", "crossq"])
def test_a_run_with_gsde_resumes_exactly(tiny, tmp_path, crossq):
    cfg = tiny(n_envs=2, exploration_noise="gsde", sde_sample_freq=7, crossq=crossq)
    straight, resumed = straight_and_resumed(cfg, tmp_path, 430, 270)  # 215 steps of each env: mid-matrix
    assert_same_training(straight, resumed)  # the weights, their random stream and the steps since the draw too


def test_an_exported_gsde_policy_clips_its_mean_as_predict_does(tiny, tmp_path):
    """test_export runs a trained gSDE agent through the ONNX and NumPy checks; here its means are pushed past
    the clip, where an export without it would act differently."""
    from float_bounds import action_bound, assert_within_bound
    from softac.outputs.export import export_policy
    from softac.learner.numpy_forward import policy_forward

    agent = SAC(tiny("Pendulum-v1", exploration_noise="gsde", learning_starts=50))
    agent.learn(100, progress=False)
    state = agent.learner.state
    head = {**state.actor[-1], "w": state.actor[-1]["w"] * 400.0}
    agent.learner.state = state._replace(actor=[*state.actor[:-1], head])
    obs = np.random.default_rng(0).uniform(-1, 1, (256, 3)).astype(np.float32)
    reference, bound = action_bound(agent, obs)
    assert np.sum(np.isclose(np.abs(reference), 2.0 * np.tanh(SDE_CLIP_MEAN))) > 10  # clipped ones
    assert np.sum(np.abs(reference) < 1.9) > 10  # and others
    with np.load(export_policy(agent, tmp_path / "policy.npz", format="numpy")) as npz:
        params = dict(npz)
    assert_within_bound(policy_forward(params, obs), reference, bound, "numpy")
    assert_within_bound(agent.predict(obs, deterministic=True), reference, bound, "predict")


def test_bad_gsde_settings_are_one_line_errors(tmp_path):
    for setting, words in (("exploration_noise=brownian", "must be gaussian, pink, gsde or repeat"),
                           ("sde_sample_freq=0", "sde_sample_freq"), ("sde_log_std_init=5", "sde_log_std_init")):
        result = run_cli("train", "--env", "Pendulum-v1", "--steps", "10", "--out", str(tmp_path / "r"),
                         "--set", "exploration_noise=gsde", setting)
        assert_clean_error(result, words)
