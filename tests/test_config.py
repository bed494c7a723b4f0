"""SACConfig: presets, overrides, validation with the key named."""

import pytest

from softac.config.sac_config import ConfigError, SACConfig
from softac.config.presets import preset_names


def test_presets_exist_and_load():
    names = preset_names()
    for required in ("InvertedPendulum-v5", "InvertedPendulum-v4", "Pusher-v5", "sb3", "cleanrl", "default"):
        assert required in names
        SACConfig.preset(required)


def test_env_presets_set_their_env_and_generic_presets_keep_it():
    assert SACConfig.preset("Pusher-v5").env_id == "Pusher-v5"
    assert SACConfig.preset("sb3").env_id == "InvertedPendulum-v5"
    assert SACConfig.preset("sb3", env_id="Pusher-v5").env_id == "Pusher-v5"
    assert SACConfig.for_env("Swimmer-v5").env_id == "Swimmer-v5"  # no preset of its own: the default one
    assert SACConfig.for_env("Swimmer-v5").replace(env_id="x") == SACConfig.preset("default", env_id="x")
    assert SACConfig.for_env("Hopper-v5") == SACConfig.preset("Hopper-v5")  # an env's own preset


def test_a_dmc_task_gets_its_own_preset_in_either_id_form_and_the_others_get_dmc():
    own = SACConfig.preset("dmc-cheetah-run")
    assert own.env_id == "dmc:cheetah-run" and own.critic_hidden_sizes == [512, 512] and own.batch_size == 256
    for env_id in ("dmc:cheetah-run", "dm_control/cheetah-run-v0"):
        assert SACConfig.for_env(env_id) == own.replace(env_id=env_id)
    for env_id in ("dmc:walker-run", "dm_control/walker-run-v0"):
        assert SACConfig.for_env(env_id) == SACConfig.preset("dmc", env_id=env_id)
    assert SACConfig.for_env("dmc:walker-run").critic_hidden_sizes != [512, 512]


def test_every_preset_has_a_description_and_a_row_in_the_readme_and_the_presets_guide():
    from pathlib import Path

    from softac.config.presets import preset_description, preset_summary

    root = Path(__file__).resolve().parent.parent
    readme = (root / "README.md").read_text()
    short = readme.split("## Presets")[1].split("\n## ")[0]  # one line each, several names to a line
    full = (root / "docs" / "guides" / "presets.md").read_text().split("\n\n")[1]
    for name in preset_names():
        # one sentence a newcomer reads in a list (`softac presets`), the rest for `softac presets NAME`
        summary = preset_summary(name)
        assert summary and len(summary) <= 100 and summary.endswith("."), name
        assert preset_description(name), name
        assert f"`{name}`" in short, name
        assert f"| `{name}` |" in full, name


def test_cleanrl_preset_has_cleanrl_defaults():
    c = SACConfig.preset("cleanrl")
    assert (c.critic_lr, c.actor_lr, c.learning_starts, c.policy_frequency) == (1e-3, 3e-4, 5000, 2)
    assert (c.log_std_min, c.log_std_max, c.log_std_mode) == (-5.0, 2.0, "tanh")


def test_sb3_preset_has_sb3_defaults():
    c = SACConfig.preset("sb3")
    assert (c.batch_size, c.learning_starts, c.hidden_sizes, c.tau, c.buffer_size) == (256, 100, [256, 256], 0.005,
                                                                                       1_000_000)


def test_overrides_parse_types():
    c = SACConfig().with_overrides(["batch_size=64", "hidden_sizes=128,64", "gamma=0.95", "autotune_alpha=false",
                                    "target_entropy=-3", "total_steps=1e4", "device=cpu"])
    assert (c.batch_size, c.hidden_sizes, c.gamma, c.autotune_alpha) == (64, [128, 64], 0.95, False)
    assert c.target_entropy == -3.0 and c.total_steps == 10_000
    assert SACConfig().with_overrides(["hidden_sizes=[32, 32]"]).hidden_sizes == [32, 32]
    assert SACConfig().with_overrides(["hidden_sizes=256x256"]).hidden_sizes == [256, 256]


@pytest.mark.parametrize("pair,fragment", [
    ("batch_szie=3", "did you mean batch_size"),
    ("nonsense=1", "unknown config key 'nonsense'"),
    ("batch_size=abc", "batch_size"),
    ("batch_size=0", "batch_size"),
    ("gamma=1.5", "gamma"),
    ("n_step=0", "n_step"),
    ("n_step=2.5", "n_step"),
    ("tau=0", "tau"),
    ("actor_lr=-1", "actor_lr"),
    ("hidden_sizes=a,b", "hidden_sizes"),
    ("log_std_min=5", "log_std_min"),
    ("device=tpu9", "device"),
    ("gamma=nan", "gamma"),
    ("n_envs=2.5", "n_envs"),
    ("autotune_alpha=maybe", "autotune_alpha"),
    ("target_entropy=high", "target_entropy"),
    ("target_q=max", "target_q"),
    ("actor_q=median", "actor_q"),
    ("adam_b2=1", "adam_b2"),
    ("activation=swish", "silu"),
    ("novalue", "KEY=VALUE"),
])
def test_bad_overrides_name_the_key(pair, fragment):
    with pytest.raises(ConfigError, match=fragment):
        SACConfig().with_overrides([pair])


@pytest.mark.parametrize("values,fragment", [
    (["n_quantiles=25", "target_q=each"], "TQC's quantile critics pool"),
    (["crossq=true", "actor_layer_norm=true"], "actor_layer_norm"),
    (["network=simba", "actor_layer_norm=true"], "actor_layer_norm"),
    (["crossq=true", "weight_norm=true", "zero_actor_head=true"], "zero_actor_head"),
])
def test_combinations_that_cannot_work_are_refused(values, fragment):
    with pytest.raises(ConfigError, match=fragment):
        SACConfig().with_overrides(values)


def test_unknown_preset_suggests():
    with pytest.raises(ConfigError, match="did you mean Pusher-v5"):
        SACConfig.preset("Pusher-v4")


def test_yaml_file_roundtrip(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("env_id: Pusher-v5\nbatch_size: 64\nversions: {jax: '0'}\ncpus: 2\n")
    c = SACConfig.from_yaml(path)
    assert c.env_id == "Pusher-v5" and c.batch_size == 64
    path.write_text("batch_size: [1\n")
    with pytest.raises(ConfigError, match="cannot read config file"):
        SACConfig.from_yaml(path)
    path.write_text("bogus_key: 1\n")
    with pytest.raises(ConfigError, match="bogus_key"):
        SACConfig.from_yaml(path)


def test_every_field_is_documented():
    docs = SACConfig.field_docs()
    assert all(docs.values())
    for key in ("total_steps", "seed", "n_envs", "buffer_size", "batch_size", "learning_starts", "gamma", "tau",
                "target_update_interval", "gradient_steps", "policy_frequency", "hidden_sizes", "actor_lr",
                "critic_lr", "alpha_lr", "autotune_alpha", "alpha", "target_entropy", "log_std_min", "log_std_max",
                "n_critics", "eval_interval", "eval_episodes", "checkpoint_interval", "device"):
        assert key in docs


def test_the_configuration_reference_is_current():
    from pathlib import Path

    reference = (Path(__file__).parent.parent / "docs" / "reference" / "config.md").read_text()
    assert SACConfig.markdown_table() in reference, "docs/reference/config.md is stale: run `make docs`"
    for key in SACConfig.field_docs():
        assert f"| `{key}` |" in reference, key


def test_mujoco_env_presets_extend_crossq():
    """`extends: crossq` in a preset file: the env's preset is crossq's settings with its env id."""
    for env in ("HalfCheetah-v5", "Hopper-v5", "Walker2d-v5", "Ant-v5", "Humanoid-v5"):
        assert SACConfig.preset(env) == SACConfig.preset("crossq", env_id=env)
        assert SACConfig.for_env(env).crossq and SACConfig.for_env(env).env_id == env


def test_crossq_avg_is_crossq_deploying_a_weight_average():
    """`crossq-avg` trains as `crossq` does (every other key equal) and deploys a moving average of the actor."""
    averaged, plain = SACConfig.preset("crossq-avg"), SACConfig.preset("crossq")
    assert averaged.policy_average_tau == 0.001 and plain.policy_average_tau == 0.0
    assert averaged.replace(policy_average_tau=0.0) == plain


def test_dmc_tasks_get_the_dmc_preset_the_crossq_avg_preset_with_action_repeat_2():
    """Every DeepMind Control task without a preset of its own trains with `dmc`: crossq-avg's settings (crossq
    deploying a weight average of its actor), action repeat 2, 50k agent steps (100k frames)."""
    for env in ("dmc:walker-run", "dm_control/walker-walk-v0"):
        assert SACConfig.for_env(env) == SACConfig.preset("crossq", env_id=env).replace(
            action_repeat=2, total_steps=50_000, policy_average_tau=0.001)
        assert SACConfig.preset("dmc", env_id=env) == SACConfig.for_env(env)
    with pytest.raises(ConfigError, match="--env dmc:DOMAIN-TASK"):
        SACConfig.preset("dmc")
    with pytest.raises(ConfigError, match="for DeepMind Control tasks.*got Hopper-v5"):
        SACConfig.preset("dmc", env_id="Hopper-v5")


def test_dmc_quadruped_run_deploys_its_actor_where_the_dmc_preset_deploys_an_average():
    """quadruped-run's preset is `dmc` with wider critics, a larger batch and no weight averaging (its average
    did worse than the same trainings' actor on fresh seeds: the preset file)."""
    own, dmc = SACConfig.for_env("dmc:quadruped-run"), SACConfig.preset("dmc", env_id="dmc:quadruped-run")
    assert own.policy_average_tau == 0.0 and dmc.policy_average_tau == 0.001
    assert own == dmc.replace(critic_hidden_sizes=(512, 512), batch_size=256, policy_average_tau=0.0)


def test_a_preset_that_extends_itself_is_refused(monkeypatch, tmp_path):
    import softac.config.presets as config

    (tmp_path / "a.yaml").write_text("extends: b\n")
    (tmp_path / "b.yaml").write_text("extends: a\n")
    monkeypatch.setattr(config, "_preset_dir", lambda: tmp_path)
    with pytest.raises(ConfigError, match="extends itself"):
        config.load_preset("a")
