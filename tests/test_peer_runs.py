"""The run directories of softac and of its peers (`softac sweep --framework sb3|sbx`) give their shared columns
one meaning, so tables and plots compare like with like: progress.csv's `return_mean` is the mean return of
the last 20 training episodes (the peers used 100), `fps` is env steps per second since the previous row
(the peers gave the cumulative rate), `time_s` the run's seconds so far. The peer is a stand-in
(tests/fake_peers) driven through softac's real adapter (softac.peers.peer_run)."""

import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import TESTS, child_env, run_cli, signal_when
from softac.run.csv_logs import RECENT_EPISODES, read_csv

DRIFT = "softac_test_envs:Drift-v0"  # 25-step episodes
FAKE_PEERS = TESTS / "fake_peers"


def assert_progress_columns_mean_what_softac_means(run, min_interval_s: float = 0.0) -> None:
    episodes = [(int(r["step"]), float(r["return"])) for r in read_csv(run / "episodes.csv")]
    rows = read_csv(run / "progress.csv")
    assert len(rows) >= 3 and len(episodes) > RECENT_EPISODES  # the window is exercised
    previous = None
    for row in rows:
        step = int(row["step"])
        finished = [ret for at, ret in episodes if at <= step]
        assert int(row["episodes"]) == len(finished)
        # %.6g in the CSV: a relative rounding of at most 5e-6 on each side
        assert float(row["return_mean"]) == pytest.approx(np.mean(finished[-RECENT_EPISODES:]), rel=1e-5, abs=1e-9)
        if previous is not None:
            steps, seconds = step - int(previous["step"]), float(row["time_s"]) - float(previous["time_s"])
            assert seconds >= min_interval_s
            # fps = steps / the interval's seconds, rounded to 0.1; each time_s is rounded to 1 ms, so the
            # interval read back is off by at most 1 ms (plus the microseconds between the two clocks' reads)
            rounding = 0.05 / float(row["fps"]) + 0.0011 / seconds
            assert float(row["fps"]) == pytest.approx(steps / seconds, rel=rounding), (row, previous)
        previous = row


def test_a_peer_run_writes_the_columns_as_softac_does(tmp_path):
    run, temp = tmp_path / "peer", tmp_path / "temp"
    temp.mkdir()
    r = subprocess.run([sys.executable, "-m", "softac.peers", "run", "sbx", "--env", DRIFT, "--seed", "0", "--steps",
                        "700", "--out", str(run), "--eval-interval", "200", "--eval-episodes", "2", "--log-interval",
                        "100"], capture_output=True, text=True, timeout=300,
                       env=child_env(FAKE_PEERS, TMPDIR=str(temp)))
    assert r.returncode == 0, r.stderr
    # SB3's learn() leaves an empty SB3-<time> directory in the temp dir unless given a logger (the stand-in does too)
    assert not [p.name for p in temp.iterdir() if p.name.startswith("SB3-")]
    # each 100-step interval takes >= 0.1 s in the stand-in, and those with an evaluation >= 0.05 s more: a
    # cumulative rate (what the peers wrote before) is off from theirs by far more than the rounding allows
    assert_progress_columns_mean_what_softac_means(run, min_interval_s=0.1)
    assert [int(row["step"]) for row in read_csv(run / "eval.csv")] == [200, 400, 600, 700]
    assert (run / ".lock").exists()  # written under the run lock, as softac's runs are


def test_a_peer_run_stops_at_its_target_return(tmp_path):
    """`--target-return`: the peer stops after the first evaluation that reaches it, as softac train does, and its
    summary says so (a sweep then counts the trial as finished)."""
    run = tmp_path / "peer"
    r = subprocess.run([sys.executable, "-m", "softac.peers", "run", "sbx", "--env", DRIFT, "--seed", "0", "--steps",
                        "700", "--out", str(run), "--eval-interval", "200", "--eval-episodes", "2",
                        "--target-return=-1e9"], capture_output=True, text=True, timeout=300, env=child_env(FAKE_PEERS))
    assert r.returncode == 0, r.stderr
    assert [int(row["step"]) for row in read_csv(run / "eval.csv")] == [200]
    summary = json.loads((run / "summary.json").read_text())
    assert (summary["steps"], summary["stopped_early"], summary["stop_reason"]) == (200, True, "target_return")
    from softac.sweep import trial_state

    assert trial_state(run, 700) == "done"


def test_a_softac_run_writes_the_same_columns(tmp_path):
    run = tmp_path / "softac"
    r = run_cli("train", "--env", "softac_test_envs:Slow-v0", "--steps", "700", "--out", str(run), "--no-progress",
                "--set", "hidden_sizes=16,16", "batch_size=16", "learning_starts=100", "eval_interval=200",
                "eval_episodes=2", "log_interval=100")
    assert r.returncode == 0, r.stderr
    assert_progress_columns_mean_what_softac_means(run, min_interval_s=0.1)  # Slow-v0: >= 2 ms a step


@pytest.mark.parametrize("framework", ["sbx-crossq", "sbx-crossq-softac"])
def test_sbx_crossq_runs_at_its_defaults_or_at_the_crossq_presets_settings(tmp_path, framework):
    import yaml

    from softac.config.sac_config import SACConfig

    run = tmp_path / framework
    r = subprocess.run([sys.executable, "-m", "softac.peers", "run", framework, "--env", DRIFT, "--seed", "1",
                        "--steps", "300", "--out", str(run), "--eval-interval", "100", "--eval-episodes", "2",
                        "--log-interval", "100"], capture_output=True, text=True, timeout=300,
                       env=child_env(FAKE_PEERS))
    assert r.returncode == 0, r.stderr
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert (config["framework"], config["algorithm"]) == (framework, "CrossQ")
    assert [int(row["step"]) for row in read_csv(run / "eval.csv")] == [100, 200, 300]
    preset = SACConfig.preset("crossq")
    if framework == "sbx-crossq":  # nothing passed: the stand-in's SBX defaults stay
        assert (config["settings"], config["batch_size"], config["learning_starts"]) == ("defaults", 256, 100)
        assert config["policy_kwargs"] == "{}"
    else:
        assert config["settings"] == "crossq"
        assert (config["batch_size"], config["learning_starts"], config["policy_delay"], config["learning_rate"],
                config["qf_learning_rate"]) == (preset.batch_size, preset.learning_starts, preset.policy_delay,
                                                preset.actor_lr, preset.critic_lr)
        for expected in ("'pi': [256, 256]", "'qf': [256, 256]", "'b1': 0.5", "'renorm_warmup_steps': 100000"):
            assert expected in config["policy_kwargs"]


def test_the_crossq_settings_carry_every_setting_or_refuse():
    from softac.config.sac_config import SACConfig
    from softac.peers import crossq_settings

    preset = SACConfig.preset("crossq")
    settings = crossq_settings(preset)
    assert settings["policy_kwargs"]["net_arch"] == {"pi": preset.hidden_sizes, "qf": preset.hidden_sizes}
    assert settings["policy_kwargs"]["optimizer_kwargs"] == {"b1": preset.adam_b1, "b2": preset.adam_b2}
    assert crossq_settings(preset.replace(hidden_sizes=[64, 64], batch_size=32))["batch_size"] == 32
    for change in ({"n_step": 3}, {"obs_norm": True}, {"critic_layer_norm": True}, {"crossq": False},
                   {"activation": "tanh"}, {"alpha_lr": 3e-4}, {"gradient_steps": 2}):
        with pytest.raises(ValueError, match=next(iter(change)).split("_")[0]):
            crossq_settings(preset.replace(**change))


def test_sbx_tqc_runs_at_the_sweeps_own_settings(tmp_path):
    """`sbx-tqc-softac` takes the sweep's --preset and --set: SBX's TQC made with those settings, recorded."""
    import yaml

    run = tmp_path / "tqc"
    r = subprocess.run([sys.executable, "-m", "softac.peers", "run", "sbx-tqc-softac", "--env", DRIFT, "--seed", "1",
                        "--steps", "300", "--out", str(run), "--eval-interval", "100", "--eval-episodes", "2",
                        "--log-interval", "100", "--preset", "tqc", "--set", "n_critics=2",
                        "critic_hidden_sizes=64,64", "target_entropy_scale=0.5"], capture_output=True, text=True,
                       timeout=300, env=child_env(FAKE_PEERS))
    assert r.returncode == 0, r.stderr
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert (config["framework"], config["algorithm"], config["settings"]) == ("sbx-tqc-softac", "TQC", "sweep")
    assert config["softac_settings"] == {"preset": "tqc", "overrides": ["n_critics=2", "critic_hidden_sizes=64,64",
                                                                        "target_entropy_scale=0.5"]}
    assert (config["batch_size"], config["learning_starts"], config["tau"], config["target_entropy"]) == (
        256, 5000, 0.005, -0.5)  # Drift-v0 has one action dimension
    for expected in ("'pi': [256, 256]", "'qf': [64, 64]", "'n_quantiles': 25"):
        assert expected in config["policy_kwargs"]
    assert [int(row["step"]) for row in read_csv(run / "eval.csv")] == [100, 200, 300]


def test_sbx_simba_normalises_observations_as_softac_and_keeps_the_statistics_across_a_stop(tmp_path):
    """`sbx-simba-softac` with obs_norm: SBX's SAC with its SimbaPolicy behind VecNormalize (the stand-ins); the
    statistics go into the checkpoint and come back when the same command continues after SIGTERM."""
    import signal

    import yaml

    from softac.run import checkpoint as ckpt

    run = tmp_path / "simba"
    cmd = [sys.executable, "-m", "softac.peers", "run", "sbx-simba-softac", "--env", DRIFT, "--seed", "0", "--steps",
           "1200", "--out", str(run), "--eval-interval", "200", "--eval-episodes", "2", "--log-interval", "100",
           "--checkpoint-interval", "200", "--preset", "simba", "--set", "critic_hidden_sizes=32,32",
           "actor_hidden_sizes=16", "log_std_mode=clamp", "log_std_min=-20"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=child_env(FAKE_PEERS))
    stderr = signal_when(proc, lambda: len(read_csv(run / "eval.csv")) >= 3, signal.SIGTERM)
    assert proc.returncode == 130, stderr
    stopped_at = int(stderr.split("interrupted at step ")[1].split(";")[0])
    meta, arrays = ckpt.load(run / "checkpoints" / "last")
    # VecNormalize's count: its 1e-4 start and one per step (the stand-in counts step observations only)
    assert float(arrays["obs_rms_count"]) == pytest.approx(stopped_at + 1e-4)
    assert meta["sweep"]["preset"] == "simba"
    resumed = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=child_env(FAKE_PEERS))
    assert resumed.returncode == 0, resumed.stderr
    _, arrays = ckpt.load(run / "checkpoints" / "last")
    # the statistics went on from the checkpoint's
    assert float(arrays["obs_rms_count"]) == pytest.approx(1200 + 1e-4)
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert (config["algorithm"], config["settings"]) == ("SAC", "sweep")
    assert "'qf': [32, 32]" in config["policy_kwargs"] and "'n_critics': 2" in config["policy_kwargs"]
    # what SBX's SAC with SimbaPolicy cannot take: MLP networks; SimBa's own tanh-squashed log std (SBX clamps)
    other = [str(tmp_path / "other") if arg == str(run) else arg for arg in cmd[:-2]]  # without the clamp
    for extra, name in ((["log_std_mode=clamp", "log_std_min=-20", "network=mlp"], "cannot take: network != simba"),
                        ([], "cannot take: log_std bounds")):
        r = subprocess.run([*other, *extra], capture_output=True, text=True, timeout=300, env=child_env(FAKE_PEERS))
        assert r.returncode == 2 and name in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_the_tqc_settings_carry_every_setting_or_refuse():
    import optax

    from softac.config.sac_config import SACConfig
    from softac.peers.settings import tqc_settings

    preset = SACConfig.preset("tqc").replace(n_critics=2)
    settings = tqc_settings(preset, act_dim=6)
    assert (settings["top_quantiles_to_drop_per_net"], settings["target_entropy"], settings["ent_coef"]) == (2, -6.0,
                                                                                                         "auto_1.0")
    assert settings["policy_kwargs"]["net_arch"] == {"pi": [256, 256], "qf": [512, 512, 512]}
    decayed = tqc_settings(preset.replace(weight_decay=0.01), act_dim=6)["policy_kwargs"]
    assert decayed["optimizer_class"] is optax.adamw and decayed["optimizer_kwargs"]["weight_decay"] == 0.01
    for change, name in (({"n_critics": 5}, "n_critics"), ({"n_quantiles": 0}, "n_quantiles"),
                         ({"obs_norm": True}, "obs_norm"), ({"alpha_lr": 1e-4}, "alpha_lr"),
                         ({"weight_decay": 0.01, "weight_decay_layers": "output"}, "output layers"),
                         ({"network": "simba", "hidden_sizes": [64]}, "network"),
                         ({"exploration_noise": "gsde"}, "exploration_noise"),
                         ({"lr_schedule": "linear"}, "lr_schedule")):
        with pytest.raises(ValueError, match=name):
            tqc_settings(preset.replace(**change), act_dim=6)


def _peer_command(run, steps="1200", seed="0"):
    return [sys.executable, "-m", "softac.peers", "run", "sbx-crossq", "--env", DRIFT, "--seed", seed, "--steps", steps,
            "--out", str(run), "--eval-interval", "200", "--eval-episodes", "2", "--log-interval", "100",
            "--checkpoint-interval", "200"]


def test_a_peer_run_stopped_by_a_signal_continues_from_its_checkpoint(tmp_path):
    """SIGTERM (what the sweep sends when it is stopped) makes the peer write its checkpoint and exit 130; the
    same command then continues from it, the replay buffer refilled (the stand-in checks it), the logs cut
    back to the checkpoint's step, the seconds of both segments counted, and a run of another seed refused."""
    import signal

    import yaml

    run = tmp_path / "peer"
    proc = subprocess.Popen(_peer_command(run), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=child_env(FAKE_PEERS))
    # stopped past the checkpoint at step 400
    stderr = signal_when(proc, lambda: len(read_csv(run / "eval.csv")) >= 3, signal.SIGTERM)
    assert proc.returncode == 130, stderr
    assert "run the same command again to continue" in stderr.strip().splitlines()[-1]
    assert not (run / "summary.json").exists()
    stopped_at = int(stderr.split("interrupted at step ")[1].split(";")[0])
    assert 600 <= stopped_at < 1200

    other = subprocess.run(_peer_command(run, seed="1"), capture_output=True, text=True, timeout=300,
                           env=child_env(FAKE_PEERS))
    assert other.returncode == 2 and "another run" in other.stderr and "Traceback" not in other.stderr, other.stderr

    resumed = subprocess.run(_peer_command(run), capture_output=True, text=True, timeout=300, env=child_env(FAKE_PEERS))
    assert resumed.returncode == 0, resumed.stderr
    evals = [int(row["step"]) for row in read_csv(run / "eval.csv")]
    assert evals == list(range(200, 1201, 200))  # each step once: rows past the checkpoint were dropped
    rows = read_csv(run / "progress.csv")
    assert [int(r["step"]) for r in rows] == list(range(100, 1201, 100))
    times = [float(r["time_s"]) for r in rows]
    assert times == sorted(times)  # time_s goes on from the first segment's seconds
    summary = json.loads((run / "summary.json").read_text())
    assert summary["steps"] == 1200 and summary["train_time_s"] >= times[-1]
    assert summary["episodes"] == len(read_csv(run / "episodes.csv"))
    segments = yaml.safe_load((run / "config.yaml").read_text())["segments"]
    assert [s["start_step"] for s in segments] == [0, stopped_at]
    # softac cannot load a peer's checkpoint as an agent: one line, exit 2
    ev = run_cli("eval", str(run), "--episodes", "1")
    assert ev.returncode == 2 and "peer's run" in ev.stderr and "Traceback" not in ev.stderr, ev.stderr


def test_a_her_peer_trains_a_goal_env_resumes_with_its_dict_buffer_and_reports_success(tmp_path):
    """sbx-her (SBX's SAC + SB3's HerReplayBuffer, stand-ins): the dict observation goes to the peer as a dict
    (training, and evaluation through softac's flattened envs), the HER buffer's dict arrays and episode
    arrays come back from its checkpoint, and the success rate is in episodes.csv, eval.csv and the summary."""
    import signal

    run = tmp_path / "her"
    command = [sys.executable, "-m", "softac.peers", "run", "sbx-her", "--env", "softac_test_envs:PointGoal-v0",
               "--seed", "0", "--steps", "1500", "--out", str(run), "--eval-interval", "300", "--eval-episodes", "2",
               "--log-interval", "100", "--checkpoint-interval", "300"]
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=child_env(FAKE_PEERS))
    stderr = signal_when(proc, lambda: len(read_csv(run / "eval.csv")) >= 2, signal.SIGTERM)
    assert proc.returncode == 130, stderr
    resumed = subprocess.run(command, capture_output=True, text=True, timeout=300, env=child_env(FAKE_PEERS))
    assert resumed.returncode == 0, resumed.stderr  # the stand-in checks its buffer came back whole
    evals = read_csv(run / "eval.csv")
    assert [int(r["step"]) for r in evals] == [300, 600, 900, 1200, 1500]
    assert all(0.0 <= float(r["success_rate"]) <= 1.0 for r in evals)
    assert {r["success"] for r in read_csv(run / "episodes.csv")} <= {"0", "1"}
    assert json.loads((run / "summary.json").read_text())["last_success"] == float(evals[-1]["success_rate"])


def test_a_her_peer_stops_at_its_target_success(tmp_path):
    """`--target-success` (a sweep's): the peer stops after the first evaluation whose success rate reaches it, as
    softac train does (a rate of 0 is reached by any evaluation: the sweep itself takes only (0, 1]); a rate it
    does not reach leaves the run to its budget."""
    def run_to(target: str, steps: int) -> dict:
        run = tmp_path / target
        r = subprocess.run([sys.executable, "-m", "softac.peers", "run", "sbx-her", "--env",
                            "softac_test_envs:PointGoal-v0", "--seed", "0", "--steps", str(steps), "--out", str(run),
                            "--eval-interval", "300", "--eval-episodes", "2", f"--target-success={target}"],
                           capture_output=True, text=True, timeout=300, env=child_env(FAKE_PEERS))
        assert r.returncode == 0, r.stderr
        summary = json.loads((run / "summary.json").read_text())
        return {"evals": [int(row["step"]) for row in read_csv(run / "eval.csv")],
                **{k: summary[k] for k in ("steps", "stopped_early", "stop_reason")}}

    assert run_to("0", 900) == {"evals": [300], "steps": 300, "stopped_early": True, "stop_reason": "target_success"}
    assert run_to("1.5", 600) == {"evals": [300, 600], "steps": 600, "stopped_early": False, "stop_reason": "steps"}


def test_a_her_peer_on_an_env_without_goals_is_refused_in_one_line(tmp_path):
    r = subprocess.run([sys.executable, "-m", "softac.peers", "run", "sbx-her", "--env", DRIFT, "--steps", "100",
                        "--out", str(tmp_path / "x")], capture_output=True, text=True, timeout=300,
                       env=child_env(FAKE_PEERS))
    assert r.returncode == 2 and "sbx-her needs a goal env" in r.stderr and "Traceback" not in r.stderr, r.stderr


@pytest.mark.parametrize("how", [["--action-repeat", "2"], ["--preset", "tqc", "--set", "n_critics=2",
                                                           "action_repeat=2"]], ids=["option", "setting"])
def test_a_peer_repeats_each_action_as_softac_does(tmp_path, how):
    """`--action-repeat` (a sweep's action_repeat setting; a sweep peer's own --set too): the peer's training
    and evaluation envs repeat each action, so Pendulum's 200-step episodes last 100 agent steps; the run
    records it, and its checkpoint is refused to a run without it."""
    import yaml

    framework = "sbx-crossq" if how[0] == "--action-repeat" else "sbx-tqc-softac"
    run = tmp_path / "run"
    command = [sys.executable, "-m", "softac.peers", "run", framework, "--env", "Pendulum-v1", "--seed", "0", "--steps",
               "300", "--out", str(run), "--eval-interval", "100", "--eval-episodes", "2", "--log-interval", "100",
               "--checkpoint-interval", "100"]
    r = subprocess.run([*command, *how], capture_output=True, text=True, timeout=300, env=child_env(FAKE_PEERS))
    assert r.returncode == 0, r.stderr
    assert yaml.safe_load((run / "config.yaml").read_text())["action_repeat"] == 2
    assert [int(row["length"]) for row in read_csv(run / "episodes.csv")] == [100, 100, 100]
    r = subprocess.run(command, capture_output=True, text=True, timeout=300, env=child_env(FAKE_PEERS))
    assert r.returncode == 2 and "holds the checkpoint of another run" in r.stderr, r.stderr


def test_sb3_zoo_takes_rl_zoos_tuned_settings_for_the_classic_set():
    """`sb3-zoo`: SB3's SAC at RL Zoo's hyperparams/sac.yml for each env of issue 43's classic set."""
    from softac.peers.settings import LinearSchedule, rl_zoo_sac_settings

    car = rl_zoo_sac_settings("MountainCarContinuous-v0")
    assert (car["use_sde"], car["policy_kwargs"], car["train_freq"], car["ent_coef"]) == (
        True, {"log_std_init": -3.67, "net_arch": [64, 64]}, 32, 0.1)
    lunar = rl_zoo_sac_settings("LunarLanderContinuous-v3")["learning_rate"]
    assert isinstance(lunar, LinearSchedule) and repr(lunar) == "lin_0.00073"
    assert (lunar(1.0), lunar(0.5), lunar(0.0)) == (7.3e-4, 3.65e-4, 0.0)  # SB3 passes the progress remaining
    assert rl_zoo_sac_settings("BipedalWalker-v3")["gamma"] == 0.98
    assert rl_zoo_sac_settings("Pendulum-v1") == {"learning_rate": 1e-3}
    with pytest.raises(ValueError, match="not for Hopper-v5"):
        rl_zoo_sac_settings("Hopper-v5")
