"""Every preset trains: 110 steps (10 of them learning: enough env steps for every preset's critic and actor
steps, policy delay 3 included, to run) with its own networks and settings, through the CLI's main() in the
test's process (conftest.run_cli_in_process)."""

import json

import pytest
import yaml

from conftest import run_cli_in_process
from softac.config.sac_config import SACConfig
from softac.config.presets import DMC_PRESET, GENERIC_PRESETS, load_preset, preset_names
from softac.config.names import is_dmc_id
from softac.envs.robotics import ROBOTICS_PREFIXES

# a preset of an older env version trains on it as written (InvertedPendulum-v4), which Gymnasium says is out of date
pytestmark = pytest.mark.filterwarnings("ignore:.*is out of date. You should consider upgrading:DeprecationWarning")

# the env a preset that names no env of its own trains on here: `dmc` is every DeepMind Control task's
FAMILY_ENVS = {DMC_PRESET: "dmc:cartpole-balance"}  # a task with no preset of its own


def _param(name: str):
    # Gymnasium-Robotics' envs need the [robotics] extra (the test extra has it; test-min leaves them out);
    # the DeepMind Control Suite the [dmc] extra
    if name.startswith(ROBOTICS_PREFIXES):
        return pytest.param(name, marks=pytest.mark.robotics)
    if name == DMC_PRESET or is_dmc_id(str(load_preset(name).get("env_id", ""))):
        import importlib.util

        missing = importlib.util.find_spec("dm_control") is None
        return pytest.param(name, marks=[pytest.mark.dmc, pytest.mark.skipif(missing, reason="no [dmc] extra")])
    return name


ENV_PRESETS = [_param(name) for name in preset_names() if name not in GENERIC_PRESETS]


@pytest.mark.parametrize("name", ENV_PRESETS)
def test_env_preset_trains_a_few_hundred_steps(name, tmp_path):
    env = FAMILY_ENVS.get(name) or load_preset(name).get("env_id", name)  # dmc-TASK presets name their task
    preset = SACConfig.preset(name, env_id=env if name in FAMILY_ENVS else None)
    steps = 110
    run = tmp_path / "run"
    # the preset's networks, batch, rates and flags as they are; only the budget, the warm-up and the
    # buffer shrink so that the run includes learning (10 env steps of the preset's updates: what a wrong shape,
    # dtype or flag breaks fails at the first); the env's own preset, as a user who gives only --env gets it
    r = run_cli_in_process("train", "--env", env, "--steps", str(steps), "--out", str(run), "--no-progress", "--set",
                           "learning_starts=100", "buffer_size=5000", f"eval_interval={steps}", "eval_episodes=1")
    assert r.returncode == 0, r.stderr
    config = yaml.safe_load((run / "config.yaml").read_text())
    for key in ("hidden_sizes", "critic_hidden_sizes", "batch_size", "critic_lr", "gamma", "gradient_steps", "obs_norm", "crossq",
                "action_repeat"):
        assert config[key] == getattr(preset, key), key
    summary = json.loads((run / "summary.json").read_text())
    assert summary["steps"] == steps and summary["last_eval"] is not None


# drq learns from 84x84 frames with 1024-wide networks at batch 512: 50 such updates take minutes on a CPU, so its
# run here keeps its flags (pixels, frame stack, augmentation, tanh log std, delays) at a CPU test's sizes; brax-sac
# keeps everything but its envs' count (128 envs' one vector step would pass the 110-step budget); fastsac its
# networks and flags, with 2 envs and batch 256 (8192-row batches of 768-wide critics: seconds an update here)
SHRUNK = {"drq": ["pixel_size=24", "batch_size=16", "hidden_sizes=64,64", "encoder_channels=8"],
          "brax-sac": ["n_envs=2"], "fastsac": ["n_envs=2", "batch_size=256"]}


@pytest.mark.parametrize("name", GENERIC_PRESETS)
def test_generic_preset_trains_any_env_a_few_hundred_steps(name, tmp_path):
    """`--preset NAME` on an env it was not written for (a 4-value observation, 1 action; drq: its frames)."""
    run = tmp_path / "run"
    r = run_cli_in_process("train", "--env", "InvertedPendulum-v5", "--preset", name, "--steps", "110", "--out",
                           str(run), "--no-progress", "--set", "learning_starts=100", "buffer_size=5000",
                           "eval_interval=110", "eval_episodes=1", *SHRUNK.get(name, []))
    assert r.returncode == 0, r.stderr
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert config["env_id"] == "InvertedPendulum-v5"
    assert config["crossq"] == load_preset(name).get("crossq", False)  # fastsac's 4096 envs need a device env
    assert json.loads((run / "summary.json").read_text())["steps"] == 110
