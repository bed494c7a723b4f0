"""Gymnasium-Robotics' goal envs (the [robotics] extra; issue 31): every env a preset names, and the three the
goal-env guide shows, construct with the MuJoCo the extra installs, are recognised as goal envs, restore their state
exactly (the goal included) and train a few steps with HER. The next MuJoCo release that breaks them fails
here, not in a user's run."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from softac import SAC
from softac.config.sac_config import SACConfig
from softac.config.presets import load_preset, preset_names
from softac.envs.make import EnvError, get_env_state, make_env, set_env_state
from softac.envs.robotics import ROBOTICS_PREFIXES

pytestmark = pytest.mark.robotics

SHOWN = ("FetchReach-v4", "FetchPush-v4", "PointMaze_UMaze-v3")


def robotics_envs() -> list[str]:
    """The robotics env ids the presets name (as their file name or env_id), and those the goal-env guide shows."""
    named = set(SHOWN)
    for name in preset_names():
        env_id = load_preset(name).get("env_id", name)
        if str(env_id).startswith(ROBOTICS_PREFIXES):
            named.add(str(env_id))
    return sorted(named)


@pytest.mark.parametrize("env_id", robotics_envs())
def test_each_robotics_env_constructs_is_a_goal_env_and_restores_exactly(env_id):
    env = make_env(env_id)
    agent_spaces = SAC(SACConfig().replace(env_id=env_id, hidden_sizes=[32, 32], batch_size=32,
                                           learning_starts=50, buffer_size=2000, eval_interval=0)).spaces
    assert agent_spaces.goal_env and agent_spaces.layout.keys == ("achieved_goal", "desired_goal", "observation")
    env.reset(seed=1)
    actions = np.random.default_rng(0).uniform(-1, 1, (30, env.action_space.shape[0])).astype(np.float32)
    for action in actions[:10]:
        env.step(action)
    meta, physics = get_env_state(env)
    after = [env.step(a)[0] for a in actions[10:]]
    other = make_env(env_id)
    other.reset(seed=7)  # another goal and start: all of it must be overwritten
    assert set_env_state(other, meta, physics)
    for a, expected in zip(actions[10:], after):
        np.testing.assert_array_equal(other.step(a)[0], expected)
    env.close()
    other.close()


@pytest.mark.parametrize("env_id", ["FetchReach-v4", "PointMaze_UMaze-v3"])
def test_sac_with_her_trains_and_evaluates_a_robotics_env(env_id, tmp_path):
    agent = SAC(SACConfig().replace(env_id=env_id, hidden_sizes=[32, 32], batch_size=32, learning_starts=100,
                                    buffer_size=5000, eval_interval=150, eval_episodes=2))
    summary = agent.learn(300, run_dir=tmp_path / "run", progress=False)
    assert agent.collector.buffer.length[:300].max() > 0  # finished episodes, so relabelled samples
    assert summary["last_success"] is not None and 0.0 <= summary["last_success"] <= 1.0


def test_a_robotics_id_without_the_extra_names_the_extra(monkeypatch):
    import softac.envs.make as envs

    monkeypatch.setattr(envs.gym, "registry", {k: v for k, v in envs.gym.registry.items() if not k.startswith("Fetch")})
    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "gymnasium_robotics" else real_find_spec(name, *a))
    with pytest.raises(EnvError, match=r"comes from Gymnasium-Robotics, which is not installed: "
                                       r"pip install 'softac\[robotics\]'"):
        envs.resolve_env_id("FetchPush-v4")


def test_a_mujoco_the_fetch_envs_do_not_work_with_is_named_in_the_error(monkeypatch):
    import mujoco

    import softac.envs.make as envs

    def failing_make(*args, **kwargs):
        raise AssertionError  # what gymnasium-robotics 1.4.2 raises in set_joint_qpos with MuJoCo >= 3.12

    monkeypatch.setattr(mujoco, "__version__", "3.12.0")
    monkeypatch.setattr(envs.gym, "make", failing_make)
    with pytest.raises(EnvError, match=r"need MuJoCo 3\.8\.1 up to \(not including\) 3\.12\.0, and MuJoCo 3\.12\.0 "
                                       r"is installed: pip install 'softac\[robotics\]'"):
        make_env("FetchReach-v4")


def test_cli_trains_a_fetch_env_and_records_its_video(tmp_path):
    """The user's path: train FetchReach-v4 briefly, evaluate (success rate in the JSON), record a video."""
    import json

    from conftest import run_cli

    run = tmp_path / "fetch"
    result = run_cli("train", "--env", "FetchReach-v4", "--steps", "300", "--out", str(run), "--no-progress",
                     "--set", "hidden_sizes=32,32", "batch_size=32", "learning_starts=100", "eval_interval=150",
                     "eval_episodes=2")
    assert result.returncode == 0, result.stderr
    result = run_cli("eval", str(run), "--episodes", "2", "--json")
    assert result.returncode == 0 and json.loads(result.stdout)["success_rate"] is not None, result.stderr
    result = run_cli("video", str(run), "--max-steps", "20")
    assert result.returncode == 0, result.stderr
    import imageio.v2 as imageio

    [video] = (run / "videos").glob("*.mp4")
    reader = imageio.get_reader(video)
    frames = [frame for _, frame in zip(range(20), reader)]
    reader.close()
    assert len(frames) == 20 and max(f.mean() for f in frames) > 1.0
