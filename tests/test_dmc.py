"""The DeepMind Control Suite through the [dmc] extra (issue 43): ids, the flat observation's key order, the
time limit as a truncation, action repeat, exact resume mid-episode, rendering."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import (assert_clean_error, assert_same_training, filmed_frames, run_cli, straight_and_resumed,
                      tiny_config)
from softac.envs.make import ActionRepeat, EnvPool, get_env_state, make_env, set_env_state, with_action_repeat
from softac.run.csv_logs import read_csv

pytest.importorskip("dm_control")
pytest.importorskip("shimmy")
pytestmark = pytest.mark.dmc

# the tasks the DMC presets and the published tables name
TASKS = ("cheetah-run", "walker-walk", "walker-run", "hopper-hop", "finger-spin", "quadruped-run", "reacher-hard",
         "cartpole-swingup")


def dm_control_env(task: str, seed: int):
    from softac.envs import dmc

    domain, name = task.split("-", 1)
    return dmc.suite().load(domain, name, task_kwargs={"random": seed})


@pytest.mark.parametrize("task", TASKS)
def test_each_task_is_flat_in_the_tasks_key_order_and_restores_exactly_mid_episode(task):
    env = make_env(f"dmc:{task}")
    assert env.spec.id == f"dm_control/{task}-v0"
    obs, _ = env.reset(seed=3)
    # the same start as dm_control's own env seeded alike, flattened as dm_control flattens (the spec's order)
    reference = dm_control_env(task, 3)
    first = reference.reset().observation
    assert [key for key, _ in env.unwrapped.observation_keys] == list(reference.observation_spec())
    np.testing.assert_array_equal(obs, np.concatenate([np.asarray(v, np.float64).ravel() for v in first.values()]))
    assert env.observation_space.shape == obs.shape

    actions = np.random.default_rng(0).uniform(-1, 1, (60, env.action_space.shape[0]))
    for action in actions[:20]:
        env.step(action)
    meta, physics = get_env_state(env)
    after = [env.step(a) for a in actions[20:]]
    other = make_env(f"dm_control/{task}-v0")
    other.reset(seed=11)  # another start (reacher's target, finger's damping...): all of it is overwritten
    assert set_env_state(other, meta, physics)
    for action, (obs, reward, terminated, truncated, _) in zip(actions[20:], after):
        again = other.step(action)
        np.testing.assert_array_equal(again[0], obs)
        assert again[1:4] == (reward, terminated, truncated)
    env.close()
    other.close()


def test_the_time_limit_truncates_and_action_repeat_counts_agent_steps():
    for repeat, length in ((1, 1000), (2, 500), (3, 334)):
        env = make_env(with_action_repeat("dmc:cartpole-swingup", repeat))
        env.reset(seed=0)
        steps, terminated, truncated = 0, False, False
        while not (terminated or truncated):
            _, _, terminated, truncated, _ = env.step(np.zeros(1))
            steps += 1
        assert (steps, terminated, truncated) == (length, False, True)  # bootstrapped, never a termination
        env.close()


def test_action_repeat_sums_the_rewards_and_stops_where_the_episode_ends():
    inner, repeated = make_env("softac_test_envs:Drift-v0"), ActionRepeat(make_env("softac_test_envs:Drift-v0"), 3)
    inner.reset(seed=5)
    repeated.reset(seed=5)
    action = np.array([1.2], np.float32)
    rewards, ends = [], []
    for _ in range(30):
        _, reward, terminated, truncated, _ = inner.step(action)
        rewards.append(reward)
        if terminated or truncated:
            ends.append(len(rewards))
            break
    total, steps, done = 0.0, 0, False
    while not done:
        _, reward, terminated, truncated, _ = repeated.step(action)
        total, steps, done = total + reward, steps + 1, terminated or truncated
    assert steps == -(-ends[0] // 3) and total == pytest.approx(sum(rewards), rel=1e-12)


def test_a_dmc_agent_with_action_repeat_resumes_exactly_mid_episode(tmp_path):
    """N + M == N+M on walker-walk with action repeat 2 (500 agent steps an episode): the split at 250 falls
    inside the first episode, so the physics, the task's RNG and the step counter all carry over."""
    cfg = tiny_config("dmc:walker-walk", action_repeat=2, learning_starts=100, n_envs=1)
    straight, resumed = straight_and_resumed(cfg, tmp_path, 250, 150)
    assert_same_training(straight, resumed)
    assert read_csv(tmp_path / "split" / "episodes.csv") == []  # the first episode still running at the end


def test_dmc_envs_in_env_workers_are_the_in_process_envs():
    pool = EnvPool(lambda i: make_env(with_action_repeat("dmc:cheetah-run", 2)), 2, seed=4, name="cheetah")
    from softac.envs.workers import WorkerEnvPool

    workers = WorkerEnvPool(with_action_repeat("dmc:cheetah-run", 2), 2, 4, "cheetah", 1)
    try:
        np.testing.assert_array_equal(pool.reset(), workers.reset())
        actions = np.random.default_rng(1).uniform(-1, 1, (2, 6)).astype(np.float32)
        a, b = pool.step(actions, 1), workers.step(actions, 1)
        np.testing.assert_array_equal(a.next_obs, b.next_obs)
        np.testing.assert_array_equal(a.rewards, b.rewards)
    finally:
        workers.close()
        pool.close()


def test_the_cli_trains_a_dmc_task_and_films_it_with_the_domains_camera(tmp_path):
    run = tmp_path / "run"
    result = run_cli("train", "--env", "dmc:quadruped-run", "--steps", "200", "--out", str(run), "--no-progress",
                     "--set", "hidden_sizes=32,32", "batch_size=32", "learning_starts=100", "eval_interval=200",
                     "eval_episodes=1", "action_repeat=4")
    assert result.returncode == 0, result.stderr
    assert [int(float(r["step"])) for r in read_csv(run / "eval.csv")] == [200]
    (frame,) = filmed_frames(run, tmp_path / "q.mp4")
    assert frame.shape == (480, 640, 3) and frame.std() > 5  # softac video's size; a picture, not a blank
    assert make_env("dmc:quadruped-run", render_mode="rgb_array").unwrapped.render_kwargs["camera_id"] == 2
    assert make_env("dmc:walker-run", render_mode="rgb_array").unwrapped.render_kwargs["camera_id"] == 0


def test_unknown_tasks_and_a_missing_extra_are_one_line_errors(tmp_path, monkeypatch):
    result = run_cli("train", "--env", "dmc:cheetah-fly", "--steps", "10", "--out", str(tmp_path / "r"))
    assert_clean_error(result, "dm_control/cheetah-fly-v0", "cheetah-run")
    import importlib.util

    from softac.envs import dmc
    from softac.envs.make import EnvError

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "shimmy" else real(name, *a))
    with pytest.raises(EnvError, match=r"pip install 'softac\[dmc\]'"):
        dmc.suite_tasks()
