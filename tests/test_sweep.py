"""`softac sweep`: trials on a local Ray Tune, summaries, resume, search; bad input fails before Ray starts."""

import csv
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from conftest import (TESTS, assert_clean_error, assert_same_last_checkpoint, child_env, ray_test_cluster, run_cli,
                      signal_when)
from softac import sweep
from softac.errors import SoftacError
from softac.sweep.driver import local_cpus

pytest.importorskip("ray.tune", reason="the [ray] extra is not installed")

# tiny trials: a few seconds each, evaluated every 200 steps on 2 episodes
TINY_SET = ["--set", "hidden_sizes=[16,16]", "batch_size=32", "learning_starts=100", "buffer_size=5000",
            "eval_interval=200", "eval_episodes=2", "log_interval=100", "checkpoint_interval=200"]
DRIFT = "softac_test_envs:Drift-v0"


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _commands(out: Path, trial: str) -> list[str]:
    return [line for line in (out / "_logs" / f"{trial}.log").read_text().splitlines() if line.startswith("$ ")]


# ---- parsing and validation (no Ray) ---------------------------------------------------------

def test_seeds_count_list_and_first_seed():
    assert sweep.parse_seeds("3") == [0, 1, 2]
    assert sweep.parse_seeds("2", first=10) == [10, 11]
    assert sweep.parse_seeds("4,7,9") == [4, 7, 9]
    assert sweep.parse_seeds("0,") == [0]
    with pytest.raises(SoftacError, match="for seed 0 alone write --seeds 0,"):
        sweep.parse_seeds("0")
    for bad in ("-2", "x", "1,1", "-1,2", ","):
        with pytest.raises(SoftacError):
            sweep.parse_seeds(bad)


def test_grid_values_split_outside_brackets_and_name_trials():
    grid = sweep.parse_grid(["tau=0.005,0.02", "hidden_sizes=[64,64],[256, 256]"])
    assert grid == {"tau": [0.005, 0.02], "hidden_sizes": [[64, 64], [256, 256]]}
    trials = sweep.grid_trials(sweep.SweepSpec(env_id="InvertedPendulum-v5", steps=100, seeds=[0, 1], grid=grid))
    assert len(trials) == 8 and len({t["name"] for t in trials}) == 8
    assert trials[0]["name"] == "tau=0.005,hidden_sizes=64x64,seed=0"
    assert trials[0]["values"] == {"tau": 0.005, "hidden_sizes": [64, 64]}
    for bad in (["tau"], ["tau=1,,2"], ["tau=1,1"], ["tau=1", "tau=2"]):
        with pytest.raises(SoftacError):
            sweep.parse_grid(bad)


def test_trial_command_passes_grid_values_and_resumes_partial_runs(tmp_path):
    spec = sweep.SweepSpec(env_id=DRIFT, steps=500, seeds=[3], preset="sb3", overrides=["tau=0.01"],
                           grid={"hidden_sizes": [[8, 8]]})
    trial = sweep.grid_trials(spec)[0]
    cmd = sweep.trial_command(spec, spec.base_config(), trial, tmp_path / trial["name"])
    assert cmd[1:4] == ["-m", "softac", "train"]
    assert cmd[cmd.index("--seed") + 1] == "3" and cmd[cmd.index("--steps") + 1] == "500"
    assert cmd[cmd.index("--preset") + 1] == "sb3"
    assert cmd[cmd.index("--set") + 1:] == ["tau=0.01", "hidden_sizes=[8,8]"]
    (tmp_path / trial["name"] / "checkpoints" / "last").mkdir(parents=True)
    assert sweep.trial_state(tmp_path / trial["name"]) == "partial"
    resume = sweep.trial_command(spec, spec.base_config(), trial, tmp_path / trial["name"])
    assert resume[3:5] == ["train", "--resume"]


def test_a_peer_trial_checkpoints_at_the_sweeps_interval_and_continues_with_the_same_command(tmp_path):
    spec = sweep.SweepSpec(env_id=DRIFT, steps=500, seeds=[0], framework="sbx-crossq",
                           overrides=["eval_interval=100"])
    trial, run = sweep.grid_trials(spec)[0], tmp_path / "seed=0"
    cmd = sweep.trial_command(spec, spec.base_config(), trial, run)
    assert cmd[1:5] == ["-m", "softac.peers", "run", "sbx-crossq"]
    assert cmd[cmd.index("--checkpoint-interval") + 1] == str(spec.base_config().checkpoint_interval)
    (run / "checkpoints" / "last").mkdir(parents=True)  # partial: `python -m softac.peers run` continues it
    assert sweep.trial_state(run) == "partial" and sweep.trial_command(spec, spec.base_config(), trial, run) == cmd
    assert "--action-repeat" not in cmd
    # the env's action repeat (DMC's 2) goes to a peer at any settings: it repeats actions as softac does
    repeated = sweep.SweepSpec(env_id=DRIFT, steps=500, seeds=[0], framework="sbx-crossq-softac",
                               overrides=["action_repeat=2"])
    cmd = sweep.trial_command(repeated, repeated.base_config(), trial, tmp_path / "repeated")
    assert cmd[cmd.index("--action-repeat") + 1] == "2"


@pytest.mark.parametrize("key, flag, value, other, named", [
    ("target_return", "--target-return", 200.0, -5.5, ", stops at 200"),
    ("target_success", "--target-success", 0.75, 0.5, ", stops at success 0.75"),
])
def test_a_target_goes_to_every_trials_command_and_names_the_configuration(tmp_path, key, flag, value, other, named):
    """`softac sweep --target-return R` (`--target-success S`): softac's new and resumed trials and a peer's stop
    at it (train's flag; `python -m softac.peers run` takes the same), and tables say so."""
    for framework in ("softac", "sbx"):
        spec = sweep.SweepSpec(env_id=DRIFT, steps=500, seeds=[0], framework=framework, **{key: value})
        trial, run = sweep.grid_trials(spec)[0], tmp_path / framework / "seed=0"
        cmd = sweep.trial_command(spec, spec.base_config(), trial, run)
        assert f"{flag}={value!r}" in cmd
        assert spec.describe().endswith(named)
    (run.parent.parent / "softac" / "seed=0" / "checkpoints" / "last").mkdir(parents=True)
    spec = sweep.SweepSpec(env_id=DRIFT, steps=500, seeds=[0], **{key: other})
    resume = sweep.trial_command(spec, spec.base_config(), trial, tmp_path / "softac" / "seed=0")
    assert resume[3:5] == ["train", "--resume"] and f"{flag}={other!r}" in resume
    plain = sweep.SweepSpec(env_id=DRIFT, steps=500, seeds=[0])
    assert not any(arg.startswith("--target") for arg in sweep.trial_command(plain, plain.base_config(), trial,
                                                                             tmp_path / "new"))
    # a sweep.json written before the key existed is the same sweep without a target
    assert getattr(sweep.SweepSpec.from_dict({"env_id": DRIFT, "steps": 500, "seeds": [0]}), key) is None


def test_the_check_command_of_a_search_keeps_its_preset_and_overrides():
    """summary.md's "check it on more seeds" line must train the best trial's configuration: the search's
    --preset and --set, with the sampled values in place of an override of the same key."""
    import shlex

    from softac.cli.main import build_parser
    from softac.cli.commands import sweep_spec_from_args

    search = sweep.SweepSpec(env_id="InvertedPendulum-v5", steps=3000, seeds=[0], preset="sb3",
                             overrides=["tau=0.01", "hidden_sizes=[64,64]", "gamma=0.98"], search="random",
                             samples=4, space={"tau": {"loguniform": [0.001, 0.1]}, "batch_size": {"choice": [64]}})
    best = {"tau": 0.0321, "batch_size": 64}
    line = sweep.check_command(search, best, seeds=5, out="/tmp/check dir")
    argv = shlex.split(line)
    assert argv[:2] == ["softac", "sweep"]
    check = sweep_spec_from_args(build_parser().parse_args(argv[1:]))
    assert check.preset == "sb3" and check.seeds == [0, 1, 2, 3, 4] and check.steps == 3000
    assert check.search is None and not check.grid
    expected = search.base_config().replace(tau=0.0321, batch_size=64)
    assert check.base_config() == expected
    assert check.base_config().hidden_sizes == [64, 64] and check.base_config().gamma == 0.98
    plain = sweep.SweepSpec(env_id="Pusher-v5", steps=100, seeds=[0], search="random", samples=2)
    assert sweep.check_command(plain, {"tau": 0.02}) == ("softac sweep --env Pusher-v5 --seeds 5 --steps 100 "
                                                         "--set tau=0.02 --out DIR")


def test_search_space_is_checked_against_the_config():
    base = sweep.SweepSpec(env_id="InvertedPendulum-v5", steps=100, seeds=[0]).base_config()
    sweep.check_space(sweep.DEFAULT_SPACE, base)
    for bad in ({"taux": {"uniform": [0.1, 0.2]}}, {"tau": {"uniform": [0.2, 0.1]}},
                {"tau": {"loguniform": [0, 0.1]}}, {"tau": {"normal": [0, 1]}}, {"batch_size": {"choice": [0]}}):
        with pytest.raises(SoftacError):
            sweep.check_space(bad, base)


def test_summary_counts_steps_seconds_and_holding_of_the_threshold(tmp_path):
    run = tmp_path / "sweep" / "seed=0"
    run.mkdir(parents=True)
    (run / "config.yaml").write_text("seed: 0\ntau: 0.02\n")
    (run / "eval.csv").write_text("step,mean_return,std_return,episodes\n100,10,0,2\n200,1000,0,2\n"
                                  "300,50,0,2\n400,1000,0,2\n")
    (run / "progress.csv").write_text("step,time_s\n100,1.0\n300,3.0\n400,4.0\n")
    spec = sweep.SweepSpec(env_id="InvertedPendulum-v5", steps=800, seeds=[0])  # stopped at 400 of 800
    [row] = sweep.trial_rows(tmp_path / "sweep", spec, threshold=1000)
    assert row["steps_to_threshold"] == 200 and row["seconds_to_threshold"] == 2.0  # interpolated time
    assert row["held_threshold"] == pytest.approx(2 / 3, abs=5e-4)  # rounded to 3 decimals
    assert row["final_eval_mean"] == 1000 and row["best_eval_mean"] == 1000 and row["status"] == "incomplete"
    [never] = sweep.trial_rows(tmp_path / "sweep", spec, threshold=2000)
    assert never["steps_to_threshold"] is None and never["held_threshold"] is None
    table = sweep.markdown_table(sweep.aggregate([row], [], 1000, name="softac"), 1000)
    assert "| softac | 1 (0 done) |" in table and "| 1/1 | 200 | 2.0 | 67% |" in table
    assert "| 400 | 4.0 | 100.0 |" in table  # median steps, wall s and steps per second
    assert "| final 95% CI | final IQM |" in table and "| [1000.0, 1000.0] | 1000.0 |" in table
    spec.steps = 400  # a trial whose evaluations reached the last step is complete, summary.json or not
    assert sweep.trial_rows(tmp_path / "sweep", spec)[0]["status"] == "done"


def test_a_sweep_directory_removed_under_its_sweep_fails_it_in_one_line(tmp_path):
    """The summary at a sweep's end finds its directory gone (removed or moved while the trials ran): RunFailed,
    which the CLI reports in one line with exit 3, where a FileNotFoundError was an `internal error` (exit 1)."""
    from softac.errors import RunFailed

    spec = sweep.SweepSpec(env_id=DRIFT, steps=400, seeds=[0])
    out = tmp_path / "sweep"
    sweep.prepare_out_dir(out, spec)
    assert sweep.write_summaries(out, spec) == []  # no trial has written anything yet
    __import__("shutil").rmtree(out)
    with pytest.raises(RunFailed, match=f"the sweep directory {out} was removed or moved while the sweep ran"):
        sweep.write_summaries(out, spec)


def test_a_resumed_sweeps_progress_counts_the_trials_that_ended_before_it(tmp_path):
    """"[k/N]" counts the sweep's trials, those that ended before the driver started included (a resumed grid
    or search), and a trial that Tune runs again after its run finished (the driver was killed in between)
    counts once."""
    from types import SimpleNamespace

    from softac.sweep.driver import _Lines

    def finished(run: Path, steps: int) -> None:
        run.mkdir(parents=True)
        (run / "config.yaml").write_text("seed: 0\ntau: 0.05\n")
        (run / "summary.json").write_text(json.dumps({"steps": steps, "total_steps": steps}))

    grid = sweep.SweepSpec(env_id="InvertedPendulum-v5", steps=1000, seeds=[0, 1, 2])
    finished(tmp_path / "grid" / "seed=0", 1000)
    (tmp_path / "grid" / "seed=1" / "checkpoints" / "last").mkdir(parents=True)  # interrupted: not ended
    assert sweep.ended_trials(tmp_path / "grid", grid) == {"seed=0"}
    lines = _Lines(grid, 3, sweep.ended_trials(tmp_path / "grid", grid), 3, refresh=lambda: [])
    assert lines.done == 1
    lines.trial_ended(SimpleNamespace(config={"trial": {"name": "seed=0"}}, trial_id="a"))  # Tune's rerun of it
    assert lines.done == 1 and not lines.pending
    lines.trial_ended(SimpleNamespace(config={"trial": {"name": "seed=1"}}, trial_id="b"))
    assert lines.done == 2 and lines.pending  # one left: the summary so far is due

    search = sweep.SweepSpec(env_id="InvertedPendulum-v5", steps=1000, seeds=[4], search="random", samples=3,
                             space={"tau": {"uniform": [0.01, 0.1]}})
    finished(tmp_path / "search" / "trial=a1,seed=4", 1000)
    assert sweep.ended_trials(tmp_path / "search", search) == {"trial=a1,seed=4"}
    lines = _Lines(search, 3, sweep.ended_trials(tmp_path / "search", search), 3, refresh=lambda: [])
    lines.trial_ended(SimpleNamespace(config={"tau": 0.05}, trial_id="a1"))
    lines.trial_ended(SimpleNamespace(config={"tau": 0.02}, trial_id="b2"))
    assert lines.done == 2


@pytest.mark.parametrize("args, fragment", [
    (["--grid", "taux=0.1,0.2"], "unknown config key 'taux'"),
    (["--grid", "gamma=0.9,2.0"], "gamma"),
    (["--grid", "tau=0.1", "--search", "random"], "alternatives"),
    (["--asha"], "needs --search"),
    (["--search", "random", "--seeds", "2"], "one seed"),
    (["--seeds", "0"], "--seeds"),
    (["--set", "batch_size=0"], "batch_size"),
    # the sweep sets each trial's seed and budget itself (a trial's --seed and --steps)
    (["--set", "seed=3"], "--set seed: a sweep sets seed from its --seeds; drop it from --set"),
    (["--grid", "total_steps=100,200"], "--grid total_steps: a sweep sets total_steps from its --steps"),
    (["--env", "NoSuchEnv-v9"], "NoSuchEnv-v9"),
    (["--cpus-per-trial", "0"], "--cpus-per-trial"),
    (["--address", "127.0.0.1:1"], "cannot reach the Ray cluster"),
    (["--search", "random", "--space", "/nonexistent/space.yaml"], "space"),
    (["--success-threshold", "1.5"], "--success-threshold is a success rate in (0, 1]"),
    (["--target-success", "0"], "--target-success is a success rate in (0, 1]"),
    (["--framework", "sb3-her"], "--framework sb3-her needs a goal env"),
    (["--framework", "sb3-zoo"], "RL Zoo's SAC settings are here for Pendulum-v1"),  # the default env has none
    (["--max-retries", "-1"], "--max-retries"),
])
def test_bad_sweeps_exit_2_before_ray_starts(tmp_path, args, fragment):
    result = run_cli("sweep", "--out", str(tmp_path / "sweep"), *args, timeout=60)
    assert_clean_error(result, fragment)
    assert not (tmp_path / "sweep" / "_ray").exists()


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no CPU affinity API on this OS")
def test_a_local_ray_offers_trials_the_cpus_this_process_may_run_on():
    """`taskset -c 0 softac sweep ...` runs its 1-CPU trials one at a time on CPU 0, not side by side on it (a
    local Ray sized by the machine's count put two trials on the one CPU)."""
    from softac.sweep.driver import local_cpus

    allowed = os.sched_getaffinity(0)
    try:
        os.sched_setaffinity(0, {min(allowed)})
        assert local_cpus() == 1
    finally:
        os.sched_setaffinity(0, allowed)
    assert local_cpus() == len(allowed)


def test_the_sweep_guide_lists_the_default_search_space():
    readme = (TESTS.parent / "docs" / "guides" / "sweeps.md").read_text()
    block = readme.split("The default search space")[1].split("```yaml\n")[1].split("```")[0]
    assert __import__("yaml").safe_load(block) == sweep.DEFAULT_SPACE


def test_sweep_needs_an_out_dir_and_keeps_other_data(tmp_path):
    assert_clean_error(run_cli("sweep", timeout=60), "--out")
    (tmp_path / "mine.txt").write_text("precious")
    assert_clean_error(run_cli("sweep", "--out", str(tmp_path), timeout=60), "not a sweep directory")
    assert (tmp_path / "mine.txt").read_text() == "precious"
    assert_clean_error(run_cli("sweep", "--resume", str(tmp_path), timeout=60), "not a sweep directory")


def test_without_ray_the_sweep_says_how_to_install_it(tmp_path):
    fake = tmp_path / "fake"
    (fake / "ray").mkdir(parents=True)
    (fake / "ray" / "__init__.py").write_text("raise ImportError('No module named ray')\n")
    result = run_cli("sweep", "--env", DRIFT, "--steps", "300", "--out", str(tmp_path / "s"), *TINY_SET,
                     env_extra={"PYTHONPATH": child_env(fake)["PYTHONPATH"]}, timeout=60)
    assert_clean_error(result, "pip install 'softac[ray]'")


def test_peers_need_the_bench_extra_and_take_no_softac_settings(tmp_path):
    result = run_cli("sweep", "--framework", "sb3", "--grid", "tau=0.1,0.2", "--out", str(tmp_path / "s"), timeout=60)
    assert_clean_error(result, "SAC at its defaults, not softac's settings")
    result = run_cli("sweep", "--framework", "sbx-crossq-softac", "--preset", "crossq", "--out", str(tmp_path / "s"),
                     timeout=60)
    assert_clean_error(result, "CrossQ at softac's crossq preset settings", "not softac's settings")


def test_a_peer_at_the_sweeps_settings_refuses_what_it_cannot_take(tmp_path):
    """sbx-tqc-softac takes --preset and --set; the tqc preset's five critics are more than SBX's TQC has."""
    result = run_cli("sweep", "--framework", "sbx-tqc-softac", "--env", "InvertedPendulum-v5", "--preset", "tqc",
                     "--out", str(tmp_path / "s"), timeout=60)
    assert_clean_error(result, "--framework sbx-tqc-softac: settings SBX's TQC cannot take: n_critics != 2")
    result = run_cli("sweep", "--framework", "sbx-tqc-softac", "--env", "InvertedPendulum-v5", "--preset", "tqc",
                     "--grid", "tau=0.1,0.2", "--out", str(tmp_path / "s"), timeout=60)
    assert_clean_error(result, "--grid and --search are for softac")
    assert not (tmp_path / "s" / "_ray").exists()


@pytest.mark.parametrize("framework", ["sb3", "sbx", "sbx-crossq", "sbx-crossq-softac"])
def test_peers_take_eval_settings_spelled_either_way(framework):
    for pair in ("eval-interval=5000", "eval_interval=5000", " eval_episodes=5", "action_repeat=2"):
        spec = sweep.SweepSpec(env_id="InvertedPendulum-v5", steps=100, seeds=[0], overrides=[pair],
                               framework=framework)
        try:
            sweep.validate(spec)
        except SoftacError as exc:  # without the [bench] extra: that, not a refusal of the key
            assert "not softac's settings" not in str(exc) and "[bench]" in str(exc), str(exc)
    spec = sweep.SweepSpec(env_id="InvertedPendulum-v5", steps=100, seeds=[0], overrides=["tau=0.1"],
                           framework=framework)
    with pytest.raises(SoftacError, match="not softac's settings"):
        sweep.validate(spec)


# ---- on a local Ray ----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def shared_ray():
    """One Ray for the sweeps here that need none of their own: a head of this machine's CPUs (Ray's test
    cluster, the trials' environment as a local Ray's: conftest.ray_test_cluster), which each joins through
    RAY_ADDRESS, as under `ray job submit`. Each then skips a local Ray's start and stop (5.5 s of a 2-trial
    sweep's 23.5 s, measured on an AMD EPYC; issue 64). The sweeps of a local Ray's own behaviour start their
    own: a driver stopped by a signal, a failing trial's report, a pinned trial against `softac train --cpus 1`,
    and one driver per directory (test_run_lock)."""
    with ray_test_cluster(num_cpus=local_cpus()) as cluster:
        yield {"RAY_ADDRESS": cluster.address}


@pytest.fixture(scope="module")
def grid_sweep(tmp_path_factory, shared_ray):
    out = tmp_path_factory.mktemp("sweeps") / "grid"
    result = run_cli(*GRID_SWEEP, "--out", str(out), *TINY_SET, timeout=600, env_extra=shared_ray)
    return out, result


# the grid sweep's command; a test that runs it again passes the same arguments, so that the summary it
# rewrites is the one the other tests of the shared sweep read, in whatever order they run
GRID_SWEEP = ["sweep", "--env", DRIFT, "--seeds", "2", "--grid", "tau=0.05,0.2", "--steps", "400", "--threshold=-1e9"]


@pytest.mark.ray
def test_grid_sweep_writes_one_ordinary_run_per_trial_and_a_summary(grid_sweep):
    out, result = grid_sweep
    assert result.returncode == 0, result.stderr
    rows = _rows(out / "summary.csv")
    assert [r["trial"] for r in rows] == ["tau=0.05,seed=0", "tau=0.05,seed=1", "tau=0.2,seed=0", "tau=0.2,seed=1"]
    assert list(rows[0]) == ["trial", "seed", "tau", "final_eval_mean", "best_eval_mean", "steps", "wall_s", "status",
                             "steps_to_threshold", "seconds_to_threshold", "held_threshold"]
    for row in rows:
        assert row["status"] == "done" and row["steps"] == "400"
        assert row["steps_to_threshold"] == "200"  # the first eval clears a threshold of -1e9
        assert row["held_threshold"] == "1.0"
        run = out / row["trial"]
        config = json.loads(json.dumps(__import__("yaml").safe_load((run / "config.yaml").read_text())))
        assert config["tau"] == float(row["tau"]) and config["seed"] == int(row["seed"])
        assert config["hidden_sizes"] == [16, 16] and config["total_steps"] == 400
        evals = _rows(run / "eval.csv")
        assert [e["step"] for e in evals] == ["200", "400"]
        assert float(row["final_eval_mean"]) == float(evals[-1]["mean_return"])  # eval.csv's value, copied
        # best: the highest evaluation of the trial's eval.csv, the first one to reach it (the run's
        # summary.json, at the precision eval.csv keeps, names the same value and its step); final: the last
        returns = [float(e["mean_return"]) for e in evals]
        best_row = evals[returns.index(max(returns))]
        assert float(row["best_eval_mean"]) == max(returns)
        summary = json.loads((run / "summary.json").read_text())
        assert (f"{summary['best_eval']:.6g}", summary["best_step"]) == (best_row["mean_return"], int(best_row["step"]))
        assert (f"{summary['last_eval']:.6g}", summary["steps"]) == (evals[-1]["mean_return"], 400)
    # an ordinary run directory: `softac eval` loads it
    ev = run_cli("eval", str(out / rows[0]["trial"]), "--episodes", "2", "--json", timeout=120)
    assert ev.returncode == 0, ev.stderr
    assert "mean_return" in json.loads(ev.stdout)
    md = (out / "summary.md").read_text()
    assert "| tau=0.05 | 2 |" in md and "| tau=0.2 | 2 |" in md and "±" in md
    assert "| 2/2 |" in md and "| 100% |" in md  # reached the threshold and held it, per configuration
    for name in ("comparison.png", "final_returns.png"):
        assert (out / "plots" / name).stat().st_size > 10_000
    assert "[4/4] finished" in result.stderr
    assert "summary so far (1 of 4 trials ended)" in result.stderr  # written while the other trials ran


@pytest.mark.ray
def test_rerunning_a_finished_sweep_redoes_nothing(grid_sweep):
    out, first = grid_sweep
    before = {p: p.stat().st_mtime_ns for p in out.glob("*/checkpoints/last/*")}
    again = run_cli(*GRID_SWEEP, "--out", str(out), *TINY_SET, timeout=120)
    assert again.returncode == 0, again.stderr
    assert "4 trials (4 already finished)" in again.stderr
    assert {p: p.stat().st_mtime_ns for p in out.glob("*/checkpoints/last/*")} == before
    assert all(len(_commands(out, t)) == 1 for t in ("tau=0.05,seed=0", "tau=0.2,seed=1"))
    different = run_cli("sweep", "--env", DRIFT, "--seeds", "2", "--grid", "tau=0.05,0.2", "--steps", "400",
                        "--out", str(out), *TINY_SET, "gamma=0.9", timeout=60)
    assert_clean_error(different, "differs in overrides", "--resume")
    shorter = run_cli("sweep", "--resume", str(out), "--steps", "300", timeout=60)
    assert_clean_error(shorter, "a sweep of 400 steps per trial; --steps 300 cannot shorten it")


@pytest.mark.ray
def test_trials_stop_at_the_target_return_and_count_as_finished(tmp_path, shared_ray):
    """Each trial stops after the first evaluation that reaches the target (here any: -1e9), its summary says
    so, the sweep's table reports the steps to it, and a rerun redoes nothing."""
    out = tmp_path / "target"
    command = ["sweep", "--env", DRIFT, "--seeds", "2", "--steps", "600", "--target-return=-1e9", "--out", str(out),
               *TINY_SET]
    result = run_cli(*command, timeout=600, env_extra=shared_ray)
    assert result.returncode == 0, result.stderr
    assert "joining the Ray cluster at" in result.stderr
    for row in _rows(out / "summary.csv"):
        summary = json.loads((out / row["trial"] / "summary.json").read_text())
        assert (summary["steps"], summary["stopped_early"], summary["stop_reason"]) == (200, True, "target_return")
        assert row["status"] == "done" and row["steps"] == "200" and row["steps_to_threshold"] == "200"
    assert "Each trial stops at the first evaluation that reaches -1e+09" in (out / "summary.md").read_text()
    again = run_cli(*command, timeout=120)
    assert again.returncode == 0 and "2 trials (2 already finished)" in again.stderr, again.stderr
    given = run_cli("sweep", "--resume", str(out), "--target-return", "5", timeout=60)
    assert_clean_error(given, "--resume continues a sweep with its own settings; drop --target-return")
    given = run_cli("sweep", "--resume", str(out), "--target-success", "0.5", timeout=60)
    assert_clean_error(given, "--resume continues a sweep with its own settings; drop --target-success")


def test_a_grid_sweep_may_gain_seeds_and_nothing_else(tmp_path):
    """`--seeds 5` after `--seeds 3` continues the sweep with seeds 3 and 4 (its finished trials are kept,
    as any rerun keeps them); fewer or other seeds, or a search's seed, are another sweep. (More steps:
    test_a_sweeps_budget_may_grow_for_softacs_grid_only.)"""
    out = tmp_path / "s"
    three = sweep.SweepSpec(env_id=DRIFT, steps=400, seeds=[0, 1, 2], grid={"tau": [0.1, 0.2]})
    sweep.prepare_out_dir(out, three)
    (out / "seed=0").mkdir()  # a trial's run: growing the sweep leaves it alone
    five = dataclasses.replace(three, seeds=[0, 1, 2, 3, 4])
    sweep.prepare_out_dir(out, five)
    assert sweep.load_spec(out) == five and (out / "seed=0").is_dir()
    assert [t["name"] for t in sweep.grid_trials(sweep.load_spec(out))][-2:] == ["tau=0.2,seed=3", "tau=0.2,seed=4"]
    for seeds in ([0, 1, 2], [0, 1, 5, 6], [4, 3, 2, 1, 0], [0, 1, 2, 3, 4, 5]):  # fewer, other, reordered
        if seeds == [0, 1, 2, 3, 4, 5]:
            changed = dataclasses.replace(five, seeds=seeds, overrides=["gamma=0.9"])  # more seeds, other settings
            fragment = "differs in overrides, seeds"
        else:
            changed, fragment = dataclasses.replace(five, seeds=seeds), "may only gain seeds"
        with pytest.raises(SoftacError, match=fragment):
            sweep.prepare_out_dir(out, changed)
    assert sweep.load_spec(out) == five
    search = sweep.SweepSpec(env_id=DRIFT, steps=400, seeds=[0], search="random", samples=2)
    sweep.prepare_out_dir(tmp_path / "search", search)
    with pytest.raises(SoftacError, match=r"differs in seeds\);"):
        sweep.prepare_out_dir(tmp_path / "search", dataclasses.replace(search, seeds=[0, 1]))


def test_a_sweeps_budget_may_grow_for_softacs_grid_only(tmp_path):
    """More steps per trial (`--resume DIR --steps N`, or the same command with a larger --steps): softac's
    grid trials continue from their checkpoints, so the spec takes the new budget (with more seeds too). A
    shorter budget, a peer's sweep (its checkpoint is tied to its budget) and a search (ASHA's schedule) are
    refused in one line, and the spec stays as it was."""
    grid = sweep.SweepSpec(env_id=DRIFT, steps=400, seeds=[0, 1])
    sweep.prepare_out_dir(tmp_path / "grid", grid)
    longer = dataclasses.replace(grid, steps=900, seeds=[0, 1, 2])
    sweep.prepare_out_dir(tmp_path / "grid", longer)
    assert sweep.load_spec(tmp_path / "grid") == longer
    with pytest.raises(SoftacError, match="a sweep of 900 steps per trial; --steps 500 cannot shorten it"):
        sweep.prepare_out_dir(tmp_path / "grid", dataclasses.replace(longer, steps=500))
    refused = {"peer": (dataclasses.replace(grid, framework="sb3"), "a peer's checkpoint is tied to its budget"),
               "search": (sweep.SweepSpec(env_id=DRIFT, steps=400, seeds=[0], search="random", samples=2),
                          "its budget cannot be raised")}
    for name, (spec, fragment) in refused.items():
        sweep.prepare_out_dir(tmp_path / name, spec)
        with pytest.raises(SoftacError, match=fragment):
            sweep.prepare_out_dir(tmp_path / name, dataclasses.replace(spec, steps=800))
        assert sweep.load_spec(tmp_path / name) == spec


@pytest.mark.ray
def test_plot_takes_sweep_directories(grid_sweep, tmp_path):
    out, _ = grid_sweep
    result = run_cli("plot", str(out), "--out", str(tmp_path / "figs"), timeout=120)
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "figs" / "comparison.png").exists()
    assert (tmp_path / "figs" / "tau=0.2,seed=1" / "learning_curve.png").exists()


@pytest.mark.ray
def test_a_finished_sweep_given_more_steps_continues_its_trials_exactly(tmp_path, shared_ray):
    """`softac sweep --resume DIR --steps N` past the sweep's budget: each finished trial continues from its
    checkpoint to N (`softac train --resume --total-steps N`), and ends as one run of N steps would (same
    CPU count), its evaluations on the same grid; the summary and sweep.json say N."""
    out, straight = tmp_path / "s", tmp_path / "straight"
    first = run_cli("sweep", "--env", DRIFT, "--seeds", "1", "--steps", "400", "--out", str(out), *TINY_SET,
                    timeout=600, env_extra=shared_ray)
    assert first.returncode == 0, first.stderr
    more = run_cli("sweep", "--resume", str(out), "--steps", "800", timeout=600, env_extra=shared_ray)
    assert more.returncode == 0, more.stderr
    assert "1 trial (0 already finished)" in more.stderr and "800 steps each" in more.stderr
    commands = _commands(out, "seed=0")
    assert len(commands) == 2 and "--resume" in commands[1] and "--total-steps 800" in commands[1]
    assert [(r["status"], r["steps"]) for r in _rows(out / "summary.csv")] == [("done", "800")]
    assert sweep.load_spec(out).steps == 800
    assert [int(e["step"]) for e in _rows(out / "seed=0" / "eval.csv")] == [200, 400, 600, 800]
    one = run_cli("train", "--env", DRIFT, "--seed", "0", "--steps", "800", "--cpus", "1", "--out", str(straight),
                  "--no-progress", *TINY_SET)
    assert one.returncode == 0, one.stderr
    assert_same_last_checkpoint(straight, out / "seed=0")
    again = run_cli("sweep", "--resume", str(out), timeout=120)
    assert again.returncode == 0 and "1 trial (1 already finished)" in again.stderr, again.stderr


@pytest.mark.ray
def test_an_interrupted_sweep_resumes_without_redoing_finished_trials(tmp_path):
    out = tmp_path / "sweep"
    env = child_env()
    args = ["sweep", "--env", "softac_test_envs:Slow-v0", "--seeds", "3", "--steps", "2500", "--max-concurrent", "1",
            "--out", str(out), *TINY_SET]
    driver = subprocess.Popen([sys.executable, "-m", "softac", *args], env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)

    summary_so_far = []

    def first_done_second_under_way() -> bool:  # the second trial with a checkpoint past step 0
        done = [sweep.trial_state(out / f"seed={s}") == "done" for s in range(3)]
        second = out / "seed=1" / "eval.csv"
        if not (done[0] and second.exists() and len(second.read_text().splitlines()) >= 3 and not done[1]):
            return False
        # the summary shows the finished trial while the sweep runs, not only when it ends
        if not (out / "summary.csv").exists():
            return False
        summary_so_far.append(_rows(out / "summary.csv"))
        return True

    stderr = signal_when(driver, first_done_second_under_way, signal.SIGINT)
    assert driver.returncode == 130, stderr
    rows = summary_so_far[0]
    assert rows[0]["trial"] == "seed=0" and rows[0]["status"] == "done", stderr
    assert all(row["status"] == "incomplete" for row in rows[1:])  # the second trial, if it had a row then
    assert "summary so far (1 of 3 trials ended)" in stderr
    assert "--resume" in stderr.splitlines()[-1]
    assert sweep.trial_state(out / "seed=1") == "partial"  # the trial saved a checkpoint when it was stopped
    resumed = run_cli("sweep", "--resume", str(out), timeout=600)
    assert resumed.returncode == 0, resumed.stderr
    assert "3 trials (1 already finished)" in resumed.stderr
    assert len(_commands(out, "seed=0")) == 1  # not redone
    assert "--resume" in _commands(out, "seed=1")[-1]  # continued from its checkpoint
    rows = _rows(out / "summary.csv")
    assert [r["status"] for r in rows] == ["done"] * 3 and {r["steps"] for r in rows} == {"2500"}
    steps = [int(e["step"]) for e in _rows(out / "seed=1" / "eval.csv")]
    assert steps == sorted(set(steps)) and steps[-1] == 2500


@pytest.mark.ray
@pytest.mark.parametrize("framework", ["softac", "sbx-crossq"])
def test_a_stopped_sweep_lets_its_running_trial_write_its_checkpoint(tmp_path, framework):
    """Ctrl-C or SIGTERM on the driver alone: Ray ends the trial's worker, the trial gets SIGTERM, writes its
    checkpoint where it stands and exits, and the driver waits for it. Ray's workers SIGKILLed their child
    processes on exit, which cut a peer's checkpoint short (a .tmp file left, the last steps lost); and Ray kills
    a worker's process group when Tune gives up waiting for the trial to stop (5 s), which killed a trial still
    winding down (seen in CI: its log lacked "interrupted at step"). The envs here take 8 s each to close, so
    the trial outlasts those 5 s (without the fix this failed for sbx-crossq each time tried, for softac once in
    two). No periodic checkpoint falls within these runs, so the checkpoint there is the one written when
    stopped."""
    out = tmp_path / "sweep"
    settings = (["--set", "hidden_sizes=[16,16]", "batch_size=32", "learning_starts=100", "eval_interval=200",
                 "eval_episodes=2", "checkpoint_interval=100000"] if framework == "softac"
                else ["--framework", framework, "--set", "eval_interval=200"])
    driver = subprocess.Popen([sys.executable, "-m", "softac", "sweep", "--env", "softac_test_envs:Slow-v0",
                               "--seeds", "1", "--steps", "50000", "--max-concurrent", "1", "--out", str(out),
                               *settings],
                              env=child_env(TESTS / "fake_peers", SOFTAC_TEST_SLOW_CLOSE_S="8"),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    evals = out / "seed=0" / "eval.csv"
    stderr = signal_when(driver, lambda: evals.exists() and len(evals.read_text().splitlines()) >= 3, signal.SIGTERM)
    assert driver.returncode in (130, 143), stderr
    log = (out / "_logs" / "seed=0.log").read_text()
    assert "interrupted at step " in log, log
    last = out / "seed=0" / "checkpoints" / "last"
    assert (last / "meta.json").exists() and not [p.name for p in last.iterdir() if p.name.endswith(".tmp")]
    assert sweep.trial_state(out / "seed=0") == "partial"


@pytest.mark.ray
@pytest.mark.parametrize("search, asha", [("optuna", True), ("random", False)])
def test_search_samples_configurations_from_the_space(tmp_path, search, asha, shared_ray):
    # a continuous key the host draws with (random_action_prob) and one that shapes the compiled update
    # (batch_size): the trials compile two update programs, where a sampled tau gave each its own (issue 64)
    space = tmp_path / "space.yaml"
    space.write_text("random_action_prob: {loguniform: [0.01, 0.2]}\nbatch_size: {choice: [16, 32]}\n")
    out = tmp_path / "search"
    result = run_cli("sweep", "--env", DRIFT, "--search", search, "--samples", "3", "--space", str(space),
                     "--steps", "600", "--out", str(out), *TINY_SET, *(["--asha"] if asha else []), timeout=600,
                     env_extra=shared_ray)
    assert result.returncode == 0, result.stderr
    rows = _rows(out / "summary.csv")
    assert len(rows) == 3 and len({r["trial"] for r in rows}) == 3
    for row in rows:
        assert 0.01 <= float(row["random_action_prob"]) <= 0.2 and row["batch_size"] in ("16", "32")
        assert row["status"] in (("done", "stopped early") if asha else ("done",))
    md = (out / "summary.md").read_text()
    assert "Best trial" in md and "--set" in md and " random_action_prob=" in md
    argv = __import__("shlex").split(md.split("more seeds: `")[1].split("`")[0])
    sets = argv[argv.index("--set") + 1:argv.index("--out")]
    kept = [pair for pair in TINY_SET[1:] if not pair.startswith("batch_size=")]  # batch_size is sampled
    assert sets[:len(kept)] == kept  # the search's overrides, then its sampled values
    assert {pair.split("=")[0] for pair in sets[len(kept):]} == {"random_action_prob", "batch_size"}
    again = run_cli("sweep", "--resume", str(out), timeout=300)  # a finished search is not rerun
    assert again.returncode == 0, again.stderr
    assert len(_rows(out / "summary.csv")) == 3


@pytest.mark.ray
def test_python_api_runs_a_sweep(tmp_path, monkeypatch, shared_ray):
    monkeypatch.setenv("PYTHONPATH", str(TESTS) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    monkeypatch.setenv("RAY_ADDRESS", shared_ray["RAY_ADDRESS"])
    tiny = [pair for pair in TINY_SET[1:]]
    spec = sweep.SweepSpec(env_id=DRIFT, steps=300, seeds=[5], overrides=tiny, grid={"gamma": [0.9]})
    result = sweep.run_sweep(spec, tmp_path / "api", log=lambda *a: None)
    assert result["trials"] == 1 and result["unfinished"] == [] and result["failed"] == []
    assert (tmp_path / "api" / "gamma=0.9,seed=5" / "summary.json").exists()
    assert {p.name for p in result["files"]} >= {"summary.csv", "summary.md", "comparison.png"}


@pytest.mark.ray
def test_a_failing_trial_is_reported_with_its_log_and_the_others_finish(tmp_path):
    out = tmp_path / "sweep"
    broken, fine = "softac_test_envs:BrokenStep-v0", DRIFT  # BrokenStep raises in step at step 30
    result = run_cli("sweep", "--env", DRIFT, "--grid", f"env_id={broken},{fine}", "--steps", "400",
                     "--out", str(out), *TINY_SET, timeout=600)
    assert result.returncode == 3, result.stderr  # a run that started and failed, not bad input
    assert "Traceback" not in result.stderr and "Warning" not in result.stderr
    assert result.stderr.count("FAILED env_id=") == 1 and "finished env_id=" in result.stderr
    last = [line for line in result.stderr.splitlines() if line.startswith("softac:")]
    assert "1 trial(s) failed" in last[0] and "_logs" in last[0], last
    assert "1 of 2 trials unfinished" in last[-1] and "--resume" in last[-1]
    log = (out / "_logs" / f"env_id={broken},seed=0.log").read_text()
    assert "softac: error:" in log and "raised in step" in log
    rows = {r["trial"]: r["status"] for r in _rows(out / "summary.csv")}
    assert rows[f"env_id={fine},seed=0"] == "done"


def test_a_trial_on_a_node_without_the_sweep_directory_fails_in_one_line_and_writes_nothing(tmp_path, monkeypatch):
    """A node that joined after the sweep's start-up check (docs/cluster.md): the trial reports one line naming
    its node and writes nothing on that node's disk (no run directory, no log)."""
    from ray import tune

    from softac.sweep import trial as trial_module

    reports = []
    monkeypatch.setattr(tune, "report", reports.append)
    monkeypatch.setattr(trial_module, "node_label", lambda: "node 0123456789ab on elsewhere")
    spec = sweep.SweepSpec(env_id=DRIFT, steps=400, seeds=[0])
    out = tmp_path / "not-here"
    sweep.run_trial({"trial": sweep.grid_trials(spec)[0]}, spec.to_dict(), str(out), 1.0)
    assert not out.exists()
    assert len(reports) == 1 and reports[0]["trial_error"].startswith(
        f"seed=0: node 0123456789ab on elsewhere does not see the sweep directory {out} (no sweep.json there)")


def test_a_trial_process_runs_on_its_claimed_cpus_and_ends_with_its_parent(tmp_path):
    """The trial's process pins itself to the trial's CPUs when it starts, and gets SIGTERM when the process that
    started it (the trial's Ray worker) dies, also where that process ignored SIGTERM (inherited through exec)."""
    cpu = sorted(os.sched_getaffinity(0))[-1]
    script = ("from softac.base.cpus import adopt_trial_settings; adopt_trial_settings(); import os, sys, time; "
              "print(sorted(os.sched_getaffinity(0)), flush=True); sys.stdin.read(); time.sleep(60)")
    # a parent that starts the child with the trial's environment, prints the child's pid, then is killed
    parent = subprocess.Popen([sys.executable, "-c", (
        "import signal, subprocess, sys, os; from softac.sweep.trial import trial_process_env; "
        "signal.signal(signal.SIGTERM, signal.SIG_IGN); "
        f"child = subprocess.Popen([sys.executable, '-c', {script!r}], env=trial_process_env(1, [{cpu}]), "
        "stdin=subprocess.PIPE, stdout=sys.stdout); print(child.pid, flush=True); child.wait()")],
        stdout=subprocess.PIPE, text=True, env=child_env())
    try:
        child_pid, affinity = int(parent.stdout.readline()), parent.stdout.readline().strip()
        assert affinity == f"[{cpu}]"
        parent.kill()
        parent.wait(30)
        deadline = time.monotonic() + 30
        while Path(f"/proc/{child_pid}").exists() and "Z" not in Path(f"/proc/{child_pid}/stat").read_text().split()[2]:
            assert time.monotonic() < deadline, "the child outlived its parent"
            time.sleep(0.05)
    finally:
        parent.kill()


@pytest.mark.ray
@pytest.mark.exact
def test_a_pinned_sweep_trial_equals_softac_train_cpus_1(tmp_path):
    """docs/reliability.md: a sweep trial pinned to one CPU repeats `softac train --cpus 1` bit for bit (XLA's
    sums depend on its thread count, which pinning fixes): weights, buffer, RNGs, evaluations, episodes, logs."""
    # networks large enough for XLA to split its sums across threads: on this 2-core machine an unpinned run of
    # these settings differs from a pinned one from the first update on (seen in progress.csv's losses)
    sets = ["--set", "hidden_sizes=256,256", "batch_size=256", "learning_starts=100", "buffer_size=2000",
            "eval_interval=200", "eval_episodes=2", "log_interval=100"]
    r = run_cli("sweep", "--env", DRIFT, "--seeds", "1", "--steps", "400", "--cpus-per-trial", "1", "--threshold=-1e9",
                "--out", str(tmp_path / "sweep"), *sets, timeout=600)
    assert r.returncode == 0, r.stderr
    r = run_cli("train", "--env", DRIFT, "--seed", "0", "--steps", "400", "--cpus", "1", "--no-progress",
                "--out", str(tmp_path / "single"), *sets)
    assert r.returncode == 0, r.stderr
    trial, single = tmp_path / "sweep" / "seed=0", tmp_path / "single"
    for run in (trial, single):
        assert yaml.safe_load((run / "config.yaml").read_text())["cpus"] == 1
    for name in ("eval.csv", "episodes.csv"):
        assert (trial / name).read_text() == (single / name).read_text(), name
    timeless = lambda run: [{k: v for k, v in row.items() if k not in ("time_s", "fps")}  # noqa: E731
                            for row in _rows(run / "progress.csv")]
    assert timeless(trial) == timeless(single) and len(timeless(trial)) == 4
    meta, arrays = assert_same_last_checkpoint(trial, single)  # envs included
    assert any(k.startswith("buffer/") for k in arrays) and "envs" in meta
