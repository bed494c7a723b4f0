"""obs_norm: running observation statistics, applied wherever the actor acts, saved in every checkpoint."""

import json

import numpy as np
import pytest

from conftest import assert_clean_error, run_cli
from softac import SAC, evaluate
from softac.run import checkpoint as ckpt
from softac.run.checkpoint import CheckpointError
from softac.learner.normalization import EPSILON, RunningObsNorm


@pytest.mark.numerics
def test_running_statistics_equal_those_of_all_observations_at_once():
    rng = np.random.default_rng(0)
    data = rng.normal(loc=[5.0, -300.0, 0.0], scale=[1.0, 50.0, 1e-3], size=(1000, 3))
    data[:, 2] = 7.0  # a constant feature
    norm = RunningObsNorm(3, clip=4.0)
    np.testing.assert_array_equal(norm.var, np.ones(3))  # before any data: the identity, not a division by 0
    for chunk in np.array_split(data, [1, 2, 10, 333, 700]):
        norm.update(chunk)
    assert norm.count == 1000
    np.testing.assert_allclose(norm.mean, data.mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(norm.var, data.var(axis=0), rtol=1e-9, atol=1e-20)
    out = norm.normalize(data)
    assert out.dtype == np.float32
    std = np.sqrt(data.var(axis=0) + EPSILON)
    expected = np.clip((data - data.mean(axis=0)) / std, -4.0, 4.0)
    # float32: the observation and the mean rounded (2^-24 of their sizes, over std), the subtraction, the std
    # rounded and the division (2^-24 of the result each): 4x that
    np.testing.assert_array_less(np.abs(out - expected),
                                 4 * 2**-24 * ((np.abs(data) + np.abs(data.mean(axis=0))) / std + np.abs(expected)))
    assert np.all(out[:, 2] == 0.0)  # a constant feature maps to 0
    hand = RunningObsNorm(1)  # by hand: [1, 3] then [5]: mean 3, var ((1-3)^2 + 0 + (5-3)^2) / 3 = 8/3
    hand.update(np.array([[1.0], [3.0]]))
    hand.update(np.array([[5.0]]))
    assert hand.mean[0] == 3.0 and hand.var[0] == pytest.approx(8.0 / 3.0)
    assert np.abs(norm.normalize(np.array([1e6, 1e6, 1e6]))).max() == 4.0  # clipped


@pytest.mark.exact
def test_predict_eval_and_every_checkpoint_use_the_statistics(tiny, tmp_path):
    agent = SAC(tiny(obs_norm=True, eval_interval=200))
    agent.learn(600, run_dir=tmp_path / "run", progress=False)
    assert agent.learner.obs_norm.count == 600 and agent.learner.obs_norm.var[1] > 1.0  # the step count in Drift's observation
    obs = np.random.default_rng(1).normal(size=(32, 2)).astype(np.float32) * [0.1, 10.0]
    by_hand = agent.learner.scaler.to_env(np.asarray(agent.learner.functions.act_deterministic(agent.learner.state.actor, (),
                                                                        agent.learner.obs_norm.normalize(obs))))
    np.testing.assert_array_equal(agent.predict(obs), by_hand)
    raw = agent.learner.scaler.to_env(np.asarray(agent.learner.functions.act_deterministic(agent.learner.state.actor, (), obs)))
    assert not np.allclose(raw, by_hand)  # the statistics matter for this agent

    for which in ("best", "last"):
        loaded = SAC.load(tmp_path / "run", which=which)
        assert loaded.learner.obs_norm is not None and loaded.learner.obs_norm.count > 0
    loaded = SAC.load(tmp_path / "run", which="last")
    np.testing.assert_array_equal(loaded.learner.obs_norm.mean, agent.learner.obs_norm.mean)
    np.testing.assert_array_equal(loaded.predict(obs), agent.predict(obs))
    assert evaluate(loaded, episodes=3)["returns"] == evaluate(agent, episodes=3)["returns"]
    count = loaded.learner.obs_norm.count
    evaluate(loaded, episodes=2)
    loaded.predict(obs)
    assert loaded.learner.obs_norm.count == count  # frozen outside training

    r = run_cli("eval", str(tmp_path / "run"), "--checkpoint", "last", "--episodes", "3", "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["returns"] == evaluate(agent, episodes=3)["returns"]


def test_a_checkpoint_without_the_statistics_is_refused_in_one_line(tiny, tmp_path):
    agent = SAC(tiny(obs_norm=True))
    agent.learn(300, progress=False)
    agent.save(tmp_path / "agent")
    meta, arrays = ckpt.load(tmp_path / "agent")
    ckpt.save(tmp_path / "broken", meta, {k: v for k, v in arrays.items() if not k.startswith("obs_norm/")})
    with pytest.raises(CheckpointError, match="no observation statistics"):
        SAC.load(tmp_path / "broken")
    assert_clean_error(run_cli("eval", str(tmp_path / "broken")), "no observation statistics")


def test_obs_norm_is_set_from_the_command_line(tmp_path):
    run = tmp_path / "run"
    r = run_cli("train", "--env", "softac_test_envs:Drift-v0", "--steps", "300", "--out", str(run), "--no-progress",
                "--set", "obs_norm=true", "obs_norm_clip=5", "hidden_sizes=16,16", "batch_size=32",
                "learning_starts=100", "eval_interval=0")
    assert r.returncode == 0, r.stderr
    assert "obs_norm: true" in (run / "config.yaml").read_text()
    assert SAC.load(run).learner.obs_norm.clip == 5.0
    assert_clean_error(run_cli("train", "--set", "obs_norm_clip=0", "--out", str(tmp_path / "x")), "obs_norm_clip")
