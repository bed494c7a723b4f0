"""The `softac` command: outputs, exit codes, one-line errors, resume, signals."""

import contextlib
import csv
import fcntl
import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from conftest import assert_clean_error, assert_same_last_checkpoint, child_env, run_cli, signal_when
from softac.errors import SoftacError

TINY_SETS = ["--set", "hidden_sizes=32,32", "batch_size=32", "learning_starts=200", "buffer_size=5000",
             "log_interval=100", "eval_episodes=2"]


def _metric_rows(path):
    with open(path) as f:
        rows = list(csv.DictReader(f))
    return [{k: v for k, v in r.items() if k not in ("time_s", "fps")} for r in rows]


def test_train_writes_the_run_directory_and_eval_json(tmp_path):
    run = tmp_path / "run"
    r = run_cli("train", "--env", "softac_test_envs:Drift-v0", "--steps", "600", "--out", str(run),
                "--no-progress", *TINY_SETS, "eval_interval=300")
    assert r.returncode == 0, r.stderr
    for name in ("config.yaml", "progress.csv", "episodes.csv", "eval.csv", "tb", "checkpoints/last/meta.json",
                 "checkpoints/best/meta.json"):
        assert (run / name).exists(), name
    header = (run / "progress.csv").read_text().splitlines()[0].split(",")
    assert header == ["step", "time_s", "fps", "episodes", "return_mean", "critic_loss", "actor_loss", "alpha",
                      "alpha_loss", "q1_mean", "q2_mean", "log_prob_mean", "success_rate"]
    assert [row["step"] for row in _metric_rows(run / "eval.csv")] == ["300", "600"]
    assert "Drift-v0" in (run / "config.yaml").read_text()

    r = run_cli("eval", str(run), "--episodes", "3", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert {"mean_return", "std_return", "episodes", "returns", "lengths"} <= set(out)
    assert out["episodes"] == 3 and len(out["returns"]) == 3
    assert out["success_rate"] is None and out["successes"] is None  # Drift-v0 reports no success
    r = run_cli("eval", str(run), "--episodes", "2", "--stochastic", "--checkpoint", "last")
    assert r.returncode == 0 and "stochastic" in r.stdout


@pytest.mark.exact
def test_cli_resume_equals_one_run_on_mujoco(tmp_path):
    sets = ["--set", "hidden_sizes=32,32", "batch_size=32", "learning_starts=300", "buffer_size=5000",
            "log_interval=200", "eval_interval=0"]
    straight, split = tmp_path / "straight", tmp_path / "split"
    assert run_cli("train", "--steps", "1000", "--out", str(straight), "--no-progress", *sets).returncode == 0
    assert run_cli("train", "--steps", "600", "--out", str(split), "--no-progress", *sets).returncode == 0
    r = run_cli("train", "--resume", str(split), "--steps", "400", "--no-progress")
    assert r.returncode == 0, r.stderr
    assert_same_last_checkpoint(straight, split)
    r = run_cli("eval", str(straight), "--episodes", "2", "--json")  # MuJoCo envs split their reward in info
    out = json.loads(r.stdout)
    assert out["reward_terms"] == {"reward_survive": pytest.approx(out["mean_return"])}
    assert "reward terms, mean per episode: survive" in run_cli("eval", str(straight), "--episodes", "2").stdout
    rows_a = _metric_rows(straight / "progress.csv")
    rows_b = [r for r in _metric_rows(split / "progress.csv") if int(r["step"]) % 200 == 0]
    assert rows_a == rows_b


def test_resume_without_steps_finishes_the_configured_total(tmp_path):
    run = tmp_path / "run"
    r = run_cli("train", "--env", "softac_test_envs:Drift-v0", "--steps", "300", "--out", str(run), "--no-progress",
                *TINY_SETS, "eval_interval=0")
    assert r.returncode == 0
    r = run_cli("train", "--resume", str(run), "--no-progress")  # total_steps is 300: nothing left to do
    assert r.returncode == 0 and "training 0 more steps" in r.stderr


def test_total_steps_raises_a_runs_budget_and_trains_as_one_longer_run(tmp_path):
    """`--resume RUN --total-steps N` trains to step N and makes N the run's budget, in its checkpoint (so a
    plain --resume after a stop continues to N, not to the old budget), summary.json and config.yaml; the
    weights, buffer and RNGs are those of one run of N steps."""
    drift = ["--env", "softac_test_envs:Drift-v0", "--no-progress", *TINY_SETS, "eval_interval=0"]
    straight, raised = tmp_path / "straight", tmp_path / "raised"
    assert run_cli("train", "--steps", "500", "--out", str(straight), *drift).returncode == 0
    assert run_cli("train", "--steps", "300", "--out", str(raised), *drift).returncode == 0
    r = run_cli("train", "--resume", str(raised), "--total-steps", "500", "--no-progress")
    assert r.returncode == 0 and "training 200 more steps" in r.stderr, r.stderr
    last = raised / "checkpoints" / "last"
    assert json.loads((last / "meta.json").read_text())["config"]["total_steps"] == 500
    summary = json.loads((raised / "summary.json").read_text())
    assert (summary["steps"], summary["total_steps"]) == (500, 500)
    assert "total_steps: 500" in (raised / "config.yaml").read_text()
    assert_same_last_checkpoint(straight, raised)
    r = run_cli("train", "--resume", str(raised), "--steps", "100", "--no-progress")  # --steps raises it too
    assert r.returncode == 0 and json.loads((last / "meta.json").read_text())["config"]["total_steps"] == 600
    assert "training 0 more steps" in run_cli("train", "--resume", str(raised), "--no-progress").stderr
    assert_clean_error(run_cli("train", "--resume", str(raised), "--total-steps", "400"),
                       "is at step 600, past --total-steps 400")
    assert_clean_error(run_cli("train", "--resume", str(raised), "--total-steps", "900", "--steps", "5"),
                       "give one")
    assert_clean_error(run_cli("train", "--total-steps", "900", "--out", str(tmp_path / "new"), *drift),
                       "--total-steps goes with --resume")


@pytest.mark.faults
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signal_writes_a_checkpoint_and_exits_130(tmp_path, sig):
    run = tmp_path / "run"
    env = child_env()
    proc = subprocess.Popen([sys.executable, "-m", "softac", "train", "--env", "softac_test_envs:Drift-v0",
                             "--steps", "1000000", "--out", str(run), "--no-progress", *TINY_SETS,
                             "eval_interval=0", "checkpoint_interval=0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    progress = run / "progress.csv"
    err = signal_when(proc, lambda: progress.exists() and len(progress.read_text().splitlines()) >= 4, sig)
    assert proc.returncode == 130, err
    assert "interrupted at step" in err and "Traceback" not in err
    r = run_cli("train", "--resume", str(run), "--steps", "100", "--no-progress")
    assert r.returncode == 0, r.stderr


@pytest.mark.faults
def test_repeated_sigterm_while_stopping_still_ends_with_its_line_and_130(tmp_path):
    """A sweep's trial gets SIGTERM twice: from the sweep, then from its Ray worker's death (PR_SET_PDEATHSIG).
    Measured: a second one 0.2-0.8 s after the first killed the process (-15) between its checkpoint and its
    "interrupted" line. Here SIGTERM keeps coming every 20 ms until the process exits."""
    run = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "softac", "train", "--env", "softac_test_envs:Drift-v0",
                             "--steps", "1000000", "--out", str(run), "--no-progress", *TINY_SETS,
                             "eval_interval=0", "checkpoint_interval=0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=child_env())
    progress = run / "progress.csv"
    try:
        deadline = time.monotonic() + 600
        while not (progress.exists() and len(progress.read_text().splitlines()) >= 4):
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.05)
        while proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            time.sleep(0.02)
        err = proc.communicate(timeout=120)[1]
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert "interrupted at step" in err and "Traceback" not in err
    assert (run / "checkpoints" / "last" / "meta.json").exists()


@pytest.mark.faults
def test_main_called_in_process_leaves_the_callers_sigterm_handling_as_it_was_after_a_stop(tmp_path):
    """Only the command's own process (`softac`, `python -m softac`) ignores SIGTERM once stopped: main() called
    in-process (a notebook, a test) restores the default, so processes it starts later can still be stopped
    (seen: a test worker that had run a stopped training in-process started processes that ignored SIGTERM)."""
    script = textwrap.dedent(f"""
        import os, signal, sys, threading, time
        from softac.cli.main import main

        def stop_once_training():
            progress = os.path.join(sys.argv[1], "progress.csv")
            while not (os.path.exists(progress) and len(open(progress).readlines()) >= 3):
                time.sleep(0.05)
            os.kill(os.getpid(), signal.SIGTERM)

        threading.Thread(target=stop_once_training, daemon=True).start()
        code = main(["train", "--env", "softac_test_envs:Drift-v0", "--steps", "1000000", "--out", sys.argv[1],
                     "--no-progress", *{list(TINY_SETS)!r}, "eval_interval=0", "checkpoint_interval=0"])
        print(code, signal.getsignal(signal.SIGTERM) == signal.SIG_DFL)
    """)
    r = subprocess.run([sys.executable, "-c", script, str(tmp_path / "run")], capture_output=True,
                       text=True, timeout=300, env=child_env())
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["130", "True"], (r.stdout, r.stderr)


@pytest.mark.parametrize("args,fragments", [
    (["train", "--env", "InvertedPendulm-v5"], ["unknown environment id", "did you mean InvertedPendulum-v5"]),
    (["train", "--env", "CartPole-v1"], ["Discrete action space"]),
    (["train", "--env", "softac_test_envs:Unbounded-v0"], ["unbounded action space"]),
    (["train", "--env", "nosuchmodule_abc:Foo-v0"], ["cannot import module"]),
    (["train", "--set", "batch_szie=3"], ["unknown config key 'batch_szie'", "batch_size"]),
    (["train", "--set", "gamma=2"], ["gamma"]),
    (["train", "--set", "hidden_sizes=wide"], ["hidden_sizes"]),
    (["train", "--preset", "nope"], ["unknown preset 'nope'"]),
    (["train", "--config", "/nonexistent/c.yaml"], ["config file not found"]),
    (["train", "--steps", "-5"], ["--steps"]),
    # a flag and a --set of its key must agree (the flag used to win silently; issue 65)
    (["train", "--steps", "600", "--set", "total_steps=1200"], ["--steps 600 and --set total_steps=1200 disagree"]),
    (["train", "--set", "buffer_size=100000000000"], ["replay buffer", "available"]),
    (["train", "--resume", "/nonexistent/run"], ["no such run or checkpoint"]),
    (["train", "--cpus", "0"], ["--cpus must be >= 1"]),
    (["train", "--cpus", "4096"], ["--cpus 4096: this process may use"]),
    # pinned only once every input is accepted, so a refused one still gets its one line
    (["train", "--cpus", "1", "--env", "InvertedPendulm-v5"], ["unknown environment id"]),
    (["eval", "/nonexistent/run"], ["no such run or checkpoint"]),
    (["eval", ".", "--episodes", "x"], ["--episodes"]),
    (["bogus"], ["invalid choice"]),
    # an argument no command knows is blamed on the command it followed, once (not "softac: error: softac:")
    (["bench", "--json", "extra"], ["softac: error: softac bench: unrecognized arguments: extra",
                                    "(see softac bench --help)"]),
    (["--bogus"], ["softac: error: unrecognized arguments: --bogus (see softac --help)"]),
])
def test_bad_input_exits_2_with_one_line(args, fragments, tmp_path):
    assert_clean_error(run_cli(*args, cwd=tmp_path), *fragments)


def test_a_flag_and_a_set_of_its_key_may_say_the_same():
    from softac.cli.main import build_parser
    from softac.cli.commands import FLAG_OF_KEY, _resolve_train_config

    args = build_parser().parse_args(["train", "--env", "Pendulum-v1", "--steps", "600", "--seed", "3", "--logger",
                                      "tensorboard,mlflow", "--set", "total_steps=600", "seed=3",
                                      "loggers=tensorboard, mlflow"])
    config = _resolve_train_config(args)
    assert (config.env_id, config.total_steps, config.seed) == ("Pendulum-v1", 600, 3)
    assert set(FLAG_OF_KEY) <= set(type(config).__dataclass_fields__)
    for flag, value, key in (("--seed", "3", "seed=4"), ("--n-envs", "2", "n_envs=3"),
                             ("--logger", "tensorboard", "loggers=none")):
        with pytest.raises(SoftacError, match=f"^{flag} {value} and --set {key} disagree; give one$"):
            _resolve_train_config(build_parser().parse_args(["train", flag, value, "--set", key]))


def test_concurrent_processes_claim_different_cpus(tmp_path, monkeypatch):
    """What `--cpus` and each sweep trial claim: CPUs no other pinned softac process holds, while it lives."""
    from softac.base import cpus

    monkeypatch.setattr(cpus, "CPU_LOCKS", tmp_path)
    allowed = sorted(os.sched_getaffinity(0))
    first = cpus.claim_cpus(1)
    assert first.cpus == allowed[:1] and len(first.locks) == 1 and not first.shared
    second = cpus.claim_cpus(1)  # another process while the first runs
    if len(allowed) > 1:
        assert second.cpus == allowed[1:2] and len(second.locks) == 1 and not second.shared
    else:  # every CPU held: pinned all the same (as many threads, so the same numbers), shared
        assert second.cpus == allowed and second.shared
    everything = cpus.claim_cpus(len(allowed))  # not that many free: all of them, shared
    assert everything.cpus == allowed and everything.shared
    for lock in everything.locks:
        lock.close()
    for lock in first.locks:
        lock.close()  # the first process ended
    assert cpus.claim_cpus(1).cpus == allowed[:1]


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two CPUs")
def test_a_claim_passes_over_a_cpu_that_a_sharing_process_still_uses(tmp_path, monkeypatch):
    """A process that had to share a CPU (none free when it started) keeps running there after the CPUs free
    up; the next claim takes another CPU, not the one that looks free but is in use."""
    from softac.base import cpus

    monkeypatch.setattr(cpus, "CPU_LOCKS", tmp_path)
    allowed = sorted(os.sched_getaffinity(0))
    holders = [cpus.claim_cpus(1) for _ in allowed]  # every CPU held
    sharing = cpus.claim_cpus(1)
    assert sharing.shared and len(sharing.cpus) == 1
    for claim in holders:  # the first processes end
        for lock in claim.locks:
            lock.close()
    later = cpus.claim_cpus(1)
    assert not later.shared and later.cpus != sharing.cpus
    for lock in sharing.locks:
        lock.close()  # the sharing process ended: its CPU is free again
    for lock in later.locks:
        lock.close()
    assert cpus.claim_cpus(1).cpus == allowed[:1]


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two CPUs")
def test_processes_that_must_share_go_to_different_cpus(tmp_path, monkeypatch):
    """Every CPU held (by runs running or stopped): two more processes share, one per CPU, whatever their pids
    (measured before: both on CPU 0, by their pids' parity, while CPU 1 had one process)."""
    from softac.base import cpus

    monkeypatch.setattr(cpus, "CPU_LOCKS", tmp_path)
    monkeypatch.setattr(cpus.os, "getpid", lambda: 4242)  # the same pid parity for both
    allowed = sorted(os.sched_getaffinity(0))
    holders = [cpus.claim_cpus(1) for _ in allowed]
    first, second = cpus.claim_cpus(1), cpus.claim_cpus(1)
    assert first.shared and second.shared and first.cpus != second.cpus
    for claim in (*holders, first, second):
        for lock in claim.locks:
            lock.close()


def test_cpus_pins_the_run_to_a_cpu_no_other_run_holds(tmp_path):
    """`--cpus 1` beside another pinned softac process takes a CPU that process does not hold, and the run's
    config.yaml records how many CPUs it ran on (its numbers depend on it)."""
    allowed = sorted(os.sched_getaffinity(0))
    locks = tmp_path / "tmp" / f"softac-cpus-{os.getuid()}"
    locks.mkdir(parents=True)
    with open(locks / f"cpu{allowed[0]}.lock", "a") as held:  # as a sweep trial or `train --cpus` holds it
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        run = tmp_path / "run"
        r = run_cli("train", "--env", "softac_test_envs:Drift-v0", "--steps", "300", "--out", str(run), "--cpus", "1",
                    "--no-progress", *TINY_SETS, env_extra={"TMPDIR": str(tmp_path / "tmp")})
    assert r.returncode == 0, r.stderr
    expected = f"pinned to CPUs [{allowed[1]}]" if len(allowed) > 1 else f"pinned to CPUs [{allowed[0]}] (shared"
    assert expected in r.stderr.splitlines()[0], r.stderr
    assert "\ncpus: 1\n" in (run / "config.yaml").read_text()


def test_a_run_pinned_beside_runs_holding_every_cpu_records_that_it_shared(tmp_path):
    """No CPU free (every one held by another pinned softac process): `--cpus 1` still pins (the same thread
    count, so the same numbers), says so, and config.yaml's segment records `cpus_shared` (its wall time is not an
    undisturbed run's: docs/results.md leaves such trials' times out)."""
    import yaml

    locks = tmp_path / "tmp" / f"softac-cpus-{os.getuid()}"
    locks.mkdir(parents=True)
    with contextlib.ExitStack() as stack:
        for cpu in sorted(os.sched_getaffinity(0)):
            held = stack.enter_context(open(locks / f"cpu{cpu}.lock", "a"))
            fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        run = tmp_path / "run"
        r = run_cli("train", "--env", "softac_test_envs:Drift-v0", "--steps", "300", "--out", str(run), "--cpus", "1",
                    "--no-progress", *TINY_SETS, env_extra={"TMPDIR": str(tmp_path / "tmp")})
    assert r.returncode == 0, r.stderr
    assert "(shared: no free CPUs)" in r.stderr.splitlines()[0], r.stderr
    [segment] = yaml.safe_load((run / "config.yaml").read_text())["segments"]
    assert segment["cpus_shared"] is True and segment["cpus"] == 1


def test_a_sweep_trials_shared_cpus_reach_its_process(monkeypatch):
    """A sweep trial that had to share its CPUs tells its process (trial_process_env), which records it."""
    from softac.base import cpus
    from softac.sweep import trial_process_env

    allowed = sorted(os.sched_getaffinity(0))
    monkeypatch.setattr(cpus, "_shared", False)
    for shared in (True, False):
        env = trial_process_env(1, allowed, shared)
        for var in (cpus.TRIAL_CPUS_VAR, cpus.TRIAL_SHARED_VAR):
            monkeypatch.delenv(var, raising=False)
            if var in env:
                monkeypatch.setenv(var, env[var])
        cpus.adopt_trial_settings()  # (no parent variable: nothing else happens; the affinity stays as it was)
        assert cpus.cpus_shared() is shared and cpus.TRIAL_SHARED_VAR not in os.environ


def test_checkpoint_problems_are_clean_errors(tmp_path):
    run = tmp_path / "run"
    assert run_cli("train", "--env", "softac_test_envs:Drift-v0", "--steps", "250", "--out", str(run),
                   "--no-progress", *TINY_SETS, "eval_interval=0").returncode == 0
    # the same --out again must not overwrite the run
    assert_clean_error(run_cli("train", "--env", "softac_test_envs:Drift-v0", "--out", str(run)), "already holds a run")
    # resume with a changed config is refused
    assert_clean_error(run_cli("train", "--resume", str(run), "--set", "gamma=0.9"), "drop --set")
    last = run / "checkpoints" / "last"
    arrays = next(last.glob("arrays-*.npz"))
    data = arrays.read_bytes()
    arrays.write_bytes(data[: len(data) // 2])  # truncated
    assert_clean_error(run_cli("eval", str(last)), "corrupt checkpoint")
    arrays.write_bytes(data)
    meta = json.loads((last / "meta.json").read_text())
    (last / "meta.json").write_text(json.dumps(dict(meta, format_version=99)))
    assert_clean_error(run_cli("eval", str(last)), "newer than this softac")
    (last / "meta.json").write_text("{not json")
    assert_clean_error(run_cli("eval", str(last)), "corrupt checkpoint")
    (last / "meta.json").write_text(json.dumps({"format": "something-else"}))
    assert_clean_error(run_cli("eval", str(last)), "not a softac checkpoint")
    empty = tmp_path / "empty"
    empty.mkdir()
    assert_clean_error(run_cli("eval", str(empty)), "holds no checkpoint")


def test_presets_lists_every_preset_a_line_each_and_shows_one_whole():
    from softac.config.presets import load_preset, preset_names

    r = run_cli("presets")
    assert r.returncode == 0
    lines = r.stdout.splitlines()
    assert [line.split()[0] for line in lines] == preset_names()  # a line each, nothing else on stdout
    assert all(len(line) <= 140 for line in lines), max(lines, key=len)
    [dmc] = [line for line in lines if line.startswith("dmc ")]
    assert "[dmc]" in dmc and "action repeat 2" in dmc
    assert "softac presets NAME" in r.stderr
    r = run_cli("presets", "crossq-avg")
    assert r.returncode == 0, r.stderr
    page = r.stdout.splitlines()
    assert page[0] == "crossq-avg  [any env]" and page[1].startswith("CrossQ deploying a weight average")
    assert "Nikishin et al. 2018" in r.stdout and "(with those of crossq, which it extends)" in r.stdout
    assert max(len(line) for line in page) <= 100
    settings = page[page.index(next(line for line in page if line.startswith("settings"))) + 1:]
    assert [line.split(":")[0].strip() for line in settings] == list(load_preset("crossq-avg"))
    assert "  policy_average_tau: 0.001" in settings and "  hidden_sizes: [256, 256]" in settings
    assert_clean_error(run_cli("presets", "crosq"), "unknown preset 'crosq'", "did you mean crossq?")
    assert_clean_error(run_cli("train", "--preset", "dmc", "--steps", "10"), "preset 'dmc' is for DeepMind Control")


def test_a_reader_that_stops_early_gets_no_error():
    """`softac presets | head`: the pipe's reader is gone when softac writes (here closed before softac starts
    writing); softac stops quietly with the shell's SIGPIPE status (141) instead of an internal error."""
    child = subprocess.Popen([sys.executable, "-m", "softac", "presets"], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True, env=child_env())
    child.stdout.close()
    stderr = child.stderr.read()
    assert child.wait(timeout=120) == 141 and stderr == "", stderr


def test_gpu_without_a_gpu_is_a_clean_error(tmp_path):
    import jax

    if jax.default_backend() == "gpu":
        pytest.skip("this machine has a GPU")
    assert_clean_error(run_cli("train", "--device", "gpu", "--out", str(tmp_path / "r")), "finds no GPU", "--device cpu")


def test_help_for_the_root_and_every_command():
    """`softac`, `softac --help` and `softac CMD --help` print usage, never an internal error (argparse formats
    help with %, so a literal % in a help text once broke all of them)."""
    from softac.cli.main import build_parser

    r = run_cli("--help")
    assert r.returncode == 0 and "usage: softac" in r.stdout and not r.stderr, r.stderr
    commands = list(build_parser().commands)
    assert {"train", "eval", "video", "plot", "report", "export", "baselines", "sweep", "bench",
            "presets"} <= set(commands)
    for command in commands:
        assert command in r.stdout, command
    bare = run_cli()
    assert bare.returncode == 2 and "usage: softac" in bare.stderr and "internal error" not in bare.stderr
    for command in commands:
        r = run_cli(command, "--help")
        assert r.returncode == 0, (command, r.stderr)
        assert f"usage: softac {command}" in r.stdout, (command, r.stdout[:200])
        assert "internal error" not in r.stderr + r.stdout, command


def test_the_policy_choices_of_eval_and_video_are_the_learners():
    """cli spells learner.POLICIES out (importing the learner would slow `softac --help`): they must not drift."""
    from softac.cli.main import build_parser
    from softac.learner.learner import POLICIES

    for command in ("eval", "video"):
        [policy] = [a for a in build_parser().commands[command]._actions if a.dest == "policy"]
        assert tuple(policy.choices) == POLICIES and policy.default in POLICIES, command


BOUNDED_ENV = '''
import os

import gymnasium as gym
from softac_test_envs import DriftEnv


class Bounded(DriftEnv):
    def __init__(self):
        super().__init__(high=float(os.environ.get("BOUNDED_HIGH", "3")))


gym.register("Bounded-v0", entry_point=Bounded, max_episode_steps=25)
'''


def test_a_changed_env_with_other_action_bounds_is_refused_unless_asked(tmp_path):
    (tmp_path / "boundedenv.py").write_text(BOUNDED_ENV)
    path = child_env(tmp_path)["PYTHONPATH"]
    run = tmp_path / "run"
    r = run_cli("train", "--env", "boundedenv:Bounded-v0", "--steps", "250", "--out", str(run), "--no-progress",
                *TINY_SETS, "eval_interval=0", env_extra={"PYTHONPATH": path})
    assert r.returncode == 0, r.stderr
    changed = {"PYTHONPATH": path, "BOUNDED_HIGH": "2"}  # the env's definition changed since
    # (the resume last: it saves the run with the new bounds)
    for args in (["eval", str(run)], ["export", str(run), "--format", "numpy"],
                 ["train", "--resume", str(run), "--steps", "50", "--no-progress"]):
        assert_clean_error(run_cli(*args, env_extra=changed), "action bounds", "--allow-new-bounds")
        r = run_cli(*args, "--allow-new-bounds", env_extra=changed)
        assert r.returncode == 0, (args, r.stderr)
    assert_clean_error(run_cli("train", "--env", "boundedenv:Bounded-v0", "--out", str(tmp_path / "new"),
                               "--allow-new-bounds", env_extra=changed), "goes with --resume")


def test_a_warm_up_past_the_run_is_said_when_training_starts(tmp_path):
    """A preset's learning_starts past a short --steps (fastsac's 40,960 transitions) would train nothing: one note
    line says so; a run that learns gets none."""
    run = lambda steps, name: run_cli("train", "--env", "softac_test_envs:Drift-v0", "--steps", steps, "--out",
                                      str(tmp_path / name), "--no-progress", *TINY_SETS, "eval_interval=0",
                                      "learning_starts=100")
    r = run("100", "short")
    assert r.returncode == 0 and ("softac: note: learning_starts=100 is not below the run's 100 steps: it acts at "
                                  "random throughout and never updates") in r.stderr, r.stderr
    r = run("101", "long")
    assert r.returncode == 0 and "note: learning_starts" not in r.stderr
