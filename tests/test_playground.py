"""MuJoCo Playground's envs through the [playground] extra, one on the host each (what evaluation, videos and
collect_on=host run; issue 67): ids, spaces, Playground's done as a termination and its episode length as a truncation, exact state mid-episode,
training, evaluation and filming from the CLI, and one-line errors for unknown ids and missing robot models."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import (assert_clean_error, assert_same_training, filmed_frames, run_cli, straight_and_resumed,
                      tiny_config)
from softac.envs.make import EnvPool, get_env_state, make_env, set_env_state
from softac.run.csv_logs import read_csv

pytest.importorskip("mujoco_playground")
pytestmark = pytest.mark.playground

ENV = "playground:CartpoleSwingup"  # the smallest of the suite's ports: the quickest compile


def test_ids_spaces_and_the_episode_length_as_a_truncation():
    env = make_env(ENV)
    assert env.spec.id == "playground/CartpoleSwingup" and env.spec.max_episode_steps == 1000
    assert make_env("playground/CartpoleSwingup").spec.id == env.spec.id
    assert env.observation_space.shape == (5,) and env.observation_space.dtype == np.float32
    assert env.action_space.shape == (1,) and (env.action_space.low, env.action_space.high) == (-1.0, 1.0)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (5,) and obs.dtype == np.float32
    steps, terminated, truncated = 0, False, False
    while not (terminated or truncated):
        _, reward, terminated, truncated, _ = env.step(np.zeros(1, np.float32))
        steps += 1
    assert (steps, terminated, truncated) == (1000, False, True)  # bootstrapped, never a termination
    assert isinstance(reward, float)


@pytest.mark.filterwarnings("ignore:.*(NaN|not within the observation space)")
def test_playgrounds_done_is_a_termination():
    """A NaN action makes the state NaN, which Playground's suite ports mark done (their only termination)."""
    env = make_env(ENV)
    env.reset(seed=0)
    _, _, terminated, truncated, _ = env.step(np.full(1, np.nan, np.float32))
    assert (terminated, truncated) == (True, False)


@pytest.mark.exact
def test_a_playground_env_restores_exactly_mid_episode_and_seeds_its_starts():
    env = make_env(ENV)
    first, _ = env.reset(seed=3)
    again, _ = make_env(ENV).reset(seed=3)
    other, _ = make_env(ENV).reset(seed=4)
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first, other)
    actions = np.random.default_rng(0).uniform(-1, 1, (40, 1)).astype(np.float32)
    for action in actions[:20]:
        env.step(action)
    meta, physics = get_env_state(env)
    assert meta["kind"] == "protocol" and meta["elapsed_steps"] == 20
    after = [env.step(a) for a in actions[20:]]
    reset_after = env.reset()[0]  # the key of the next reset is part of the state too
    restored = make_env(ENV)
    restored.reset(seed=11)
    assert set_env_state(restored, meta, physics)
    for action, (obs, reward, terminated, truncated, _) in zip(actions[20:], after):
        step = restored.step(action)
        np.testing.assert_array_equal(step[0], obs)
        assert step[1:4] == (reward, terminated, truncated)
    np.testing.assert_array_equal(restored.reset()[0], reset_after)
    with pytest.raises(ValueError, match="values where this env has"):
        restored.unwrapped.load_state(physics[:-1])


@pytest.mark.exact
def test_a_playground_agent_resumes_exactly_mid_episode(tmp_path):
    """N + M == N+M: the split at 250 falls inside the first 1000-step episode."""
    cfg = tiny_config(ENV, learning_starts=100, n_envs=1, collect_on="host")  # the host family's own resume
    straight, resumed = straight_and_resumed(cfg, tmp_path, 250, 150)
    assert_same_training(straight, resumed)


def test_the_cli_trains_evaluates_and_films_a_playground_env(tmp_path):
    run = tmp_path / "run"
    result = run_cli("train", "--env", ENV, "--steps", "300", "--out", str(run), "--no-progress", "--n-envs", "2",
                     "--set", "collect_on=host", "hidden_sizes=32,32", "batch_size=32", "learning_starts=100", "eval_interval=300",
                     "eval_episodes=1")
    assert result.returncode == 0, result.stderr
    assert [int(float(r["step"])) for r in read_csv(run / "eval.csv")] == [300]
    frames = filmed_frames(run, tmp_path / "c.mp4", (0, 19))
    assert frames[0].shape == (480, 640, 3) and frames[0].std() > 5  # softac video's size; a picture, not a blank
    assert np.abs(frames[0].astype(int) - frames[1].astype(int)).sum() > 0  # the MJX state reaches the renderer


def test_envs_of_one_name_share_one_compiled_step():
    from softac.envs import playground

    pool = EnvPool(lambda i: make_env(ENV), 3, seed=0, name="cartpole")
    try:
        pool.reset()
        pool.step(np.zeros((3, 1), np.float32), 1)
        steps = {id(env.unwrapped._step) for env in pool.envs}
        assert steps == {id(playground.load("CartpoleSwingup")[3])}
    finally:
        pool.close()


def test_unknown_envs_missing_robot_models_and_a_missing_extra_are_one_line_errors(tmp_path, monkeypatch):
    result = run_cli("train", "--env", "playground:CartpoleSwingp", "--steps", "10", "--out", str(tmp_path / "r"))
    assert_clean_error(result, "unknown MuJoCo Playground env 'CartpoleSwingp'", "playground:CartpoleSwingup")
    assert not (tmp_path / "r").exists()

    from mujoco_playground._src import mjx_env

    from softac.envs import playground
    from softac.envs.make import EnvError

    if mjx_env.MENAGERIE_PATH.exists():
        pytest.skip("MuJoCo Menagerie is installed here: the robot tasks load")

    def no_clone():  # as on a machine that cannot reach GitHub (where a clone would take minutes otherwise)
        raise __import__("subprocess").CalledProcessError(128, ["git", "clone"])

    monkeypatch.setattr(mjx_env, "ensure_menagerie_exists", no_clone)
    monkeypatch.setattr(playground, "_LOADED", {})
    with pytest.raises(EnvError, match=r"needs the robot models of MuJoCo Menagerie.*git clone https://github.com/"):
        make_env("playground:Go1JoystickFlatTerrain")

    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "mujoco_playground" else real(name, *a))
    with pytest.raises(EnvError, match=r"pip install 'softac\[playground\]'"):
        playground.resolve("playground:CheetahRun")
