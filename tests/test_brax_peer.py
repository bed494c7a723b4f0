"""Brax's own SAC trainer as a peer (issue 67): a softac config's settings as Brax's keywords, what Brax cannot take
refused in one line, and the sweep's trial command training it on a MuJoCo Playground env into a softac-style
run directory (config.yaml, progress.csv, eval.csv, summary.json) with the JAX this venv has (brax 0.14.2 needs
jax.device_put_replicated, which JAX 0.10 removed: softac.peers.brax_sac puts it back)."""

from __future__ import annotations

import json
import math
import subprocess

import pytest
import yaml

from conftest import assert_clean_error, child_env, run_cli
from softac import sweep
from softac.config.sac_config import SACConfig
from softac.run.csv_logs import read_csv

pytestmark = pytest.mark.playground
ENV = "playground:CartpoleSwingup"


@pytest.fixture(scope="module", autouse=True)
def _brax():
    pytest.importorskip("mujoco_playground")
    pytest.importorskip("brax.training.agents.sac")


def test_the_brax_sac_presets_settings_become_braxs_keywords():
    from softac.peers.settings import brax_sac_settings

    settings = brax_sac_settings(SACConfig.preset("brax-sac", env_id=ENV), act_dim=1)
    assert settings == {
        "num_envs": 128, "learning_rate": 1e-3, "discounting": 0.99, "batch_size": 512, "normalize_observations": True,
        "tau": 0.005, "min_replay_size": 8192, "max_replay_size": 4194304, "grad_updates_per_step": 8,
        "deterministic_eval": True,
        "network": {"hidden_layer_sizes": [256, 256], "activation": "relu", "q_network_layer_norm": True,
                    "policy_network_layer_norm": False}}


@pytest.mark.parametrize("change, fragment", [
    ({"actor_lr": 3e-4}, "actor_lr != critic_lr"),
    ({"alpha": 0.1}, "initial alpha != 1"),
    ({"n_atoms": 11}, "n_atoms"),
    ({"target_entropy_scale": 1.0}, "target entropy other than -|A|/2"),
    ({"critic_hidden_sizes": [64, 64]}, "actor and critic widths differ"),
    ({"warmup_actions": "uniform"}, "warmup_actions other than policy"),
    ({"log_std_mode": "clamp", "log_std_min": -20.0}, "log_std other than softplus with floor 0.001"),
    ({"layer_norm_position": "before"}, "layer_norm_position other than after"),
    ({"init": "default"}, "init other than lecun_uniform"),
])
def test_settings_brax_cannot_take_are_refused_by_name(change, fragment):
    from softac.peers.settings import brax_sac_settings

    with pytest.raises(ValueError, match=r"settings Brax's SAC cannot take: .*" + fragment.replace("|", r"\|")):
        brax_sac_settings(SACConfig.preset("brax-sac", env_id=ENV, overrides=change), act_dim=1)


def test_a_brax_sac_sweep_off_playground_is_one_line(tmp_path):
    r = run_cli("sweep", "--framework", "brax-sac", "--env", "Pendulum-v1", "--preset", "brax-sac",
                "--set", "n_envs=2", "--out", str(tmp_path / "s"), timeout=120)
    assert_clean_error(r, "--framework brax-sac trains MuJoCo Playground's envs (--env playground:NAME), not Pendulum-v1")


@pytest.mark.slow  # ~100 s on one Xeon core, mostly Brax compiling its prefill, epoch and evaluator
def test_the_sweeps_trial_trains_brax_sac_into_a_softac_run_directory(tmp_path):
    """The command a `softac sweep --framework brax-sac` trial runs, at a test's size: 4 envs, 100-step episodes
    (action repeat 10), 600 agent steps, Brax's evaluations every ~300 (after its replay's prefill)."""
    spec = sweep.SweepSpec(env_id=ENV, steps=600, seeds=[0], framework="brax-sac", preset="brax-sac",
                           overrides=["n_envs=4", "action_repeat=10", "batch_size=32", "hidden_sizes=16,16",
                                      "learning_starts=100", "buffer_size=2000", "gradient_steps=2",
                                      "eval_interval=300", "eval_episodes=3", "log_interval=100"])
    trial, run = sweep.grid_trials(spec)[0], tmp_path / "seed=0"
    command = sweep.trial_command(spec, spec.base_config(), trial, run)
    assert command[1:5] == ["-m", "softac.peers", "run", "brax-sac"]
    r = subprocess.run(command, capture_output=True, text=True, timeout=600, env=child_env())
    assert r.returncode == 0, r.stderr[-2000:]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["steps"] >= 600 and summary["framework"] == "brax-sac" and math.isfinite(summary["last_eval"])
    evals = read_csv(run / "eval.csv")
    assert [row["step"] for row in evals][0] == "0" and len(evals) == 3 and {row["episodes"] for row in evals} == {"3"}
    assert int(evals[-1]["step"]) == summary["steps"]
    assert float(evals[-1]["mean_return"]) == pytest.approx(summary["last_eval"], rel=1e-5)
    progress = read_csv(run / "progress.csv")
    assert progress and all(math.isfinite(float(row["critic_loss"])) and float(row["fps"]) > 0 for row in progress)
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert config["framework"] == "brax-sac" and config["brax"]["num_envs"] == 4
    assert config["brax"]["action_repeat"] == 10 and config["versions"]["brax-sac"] != "unknown"
