"""The classic set users try first (issue 43): Gymnasium's classic control and, with the [box2d] extra, its
Box2D envs train through softac; classic control resumes exactly (its NumPy `state`), Box2D (whose world
cannot be saved) resumes into fresh episodes and says so."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from conftest import assert_same_training, straight_and_resumed, tiny_config
from softac import SAC


@pytest.mark.parametrize("env_id", ["Pendulum-v1", "MountainCarContinuous-v0"])
def test_classic_control_envs_resume_exactly(env_id, tmp_path):
    straight, resumed = straight_and_resumed(tiny_config(env_id, learning_starts=100), tmp_path, 250, 150)
    assert_same_training(straight, resumed)


@pytest.mark.parametrize("env_id", ["LunarLanderContinuous-v3", "BipedalWalker-v3"])
def test_box2d_envs_train_and_resume_into_fresh_episodes(env_id, tmp_path):
    pytest.importorskip("Box2D")
    agent = SAC(tiny_config(env_id, learning_starts=100))
    agent.learn(200, run_dir=tmp_path / "run", progress=False)
    assert agent.num_steps == 200
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        resumed = SAC.load(tmp_path / "run", which="last")
    assert any("starts fresh episodes" in str(w.message) for w in caught)
    resumed.learn(50, run_dir=tmp_path / "run", progress=False)
    assert resumed.num_steps == 250 and np.all(np.isfinite(resumed.predict(np.zeros(agent.spaces.obs_dim))))
