"""Nothing lost: each promise of docs/reliability.md, proven by injecting the fault."""

import csv
import errno
import json
import os
import random
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import (assert_clean_error, assert_same_last_checkpoint, assert_training_error, child_env, run_cli,
                      tiny_config)

TINY_SETS = ["--set", "hidden_sizes=32,32", "batch_size=32", "learning_starts=100", "buffer_size=20000",
             "log_interval=100", "eval_interval=0"]


def _popen_train(*args, env=None):
    return subprocess.Popen([sys.executable, "-m", "softac", "train", "--no-progress", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env or child_env())


def _wait_for(predicate, proc, hang_guard=600.0):
    """Until `predicate()` holds (what the process has written says it got there), while `proc` runs; the
    guard only ends a hung test, it measures nothing."""
    deadline = time.monotonic() + hang_guard
    while not predicate():
        assert proc.poll() is None, proc.communicate()[1]
        assert time.monotonic() < deadline, "hang guard: timed out"
        time.sleep(0.05)


def _checkpoint_step(run):
    return json.loads((run / "checkpoints" / "last" / "meta.json").read_text())["num_steps"]


def _csv_rows(path):
    with open(path, newline="") as f:
        return list(csv.reader(f))


def _assert_whole_files(run):
    """Every file a reader sees is whole: CSVs have full rows, checkpoints verify and load."""
    for name in ("progress.csv", "episodes.csv", "eval.csv"):
        if (run / name).exists():
            rows = _csv_rows(run / name)
            assert all(len(r) == len(rows[0]) for r in rows[:-1]), name  # at most the row being written is cut
    from softac.agent import SAC

    return SAC.load(run, which="last")


@pytest.mark.faults
def test_repeated_kill_9_never_loses_more_than_a_checkpoint_interval(tmp_path):
    run = tmp_path / "run"
    rng = random.Random(0)
    interval = 300
    args = ["--env", "softac_test_envs:Drift-v0", "--steps", "1000000", "--out", str(run), *TINY_SETS,
            f"checkpoint_interval={interval}"]
    last_checkpoint = -1
    for round_ in range(5):
        proc = _popen_train(*args) if round_ == 0 else _popen_train("--resume", str(run))
        _wait_for(lambda: (run / "checkpoints" / "last" / "meta.json").exists(), proc)
        time.sleep(rng.uniform(1.0, 4.0))
        assert proc.poll() is None
        proc.send_signal(signal.SIGKILL)
        proc.communicate()
        agent = _assert_whole_files(run)  # loadable after every kill
        step = _checkpoint_step(run)
        assert agent.num_steps == step >= last_checkpoint
        rows = _csv_rows(run / "progress.csv")[1:]
        reached = max((int(r[0]) for r in rows if len(r) > 1 and r[0].isdigit()), default=0)
        assert reached - step <= interval, (reached, step)  # lost at most one checkpoint interval
        last_checkpoint = step
    r = run_cli("train", "--resume", str(run), "--steps", "200", "--no-progress")
    assert r.returncode == 0, r.stderr
    steps = [int(row[0]) for row in _csv_rows(run / "progress.csv")[1:]]
    assert steps == sorted(set(steps))  # resumed logs hold no step twice and no half rows


@pytest.mark.faults
def test_kill_9_before_the_first_periodic_checkpoint_resumes_from_step_0(tmp_path):
    """A run killed before its first periodic checkpoint holds only the one written at step 0 (found when a
    sweep's trials were killed at ~8k steps with checkpoints every 10k): --resume continues it."""
    run = tmp_path / "run"
    proc = _popen_train("--env", "softac_test_envs:Drift-v0", "--steps", "1000000", "--out", str(run), *TINY_SETS,
                        "checkpoint_interval=1000000")
    _wait_for(lambda: (run / "progress.csv").exists() and _csv_rows(run / "progress.csv")[1:], proc)
    proc.send_signal(signal.SIGKILL)
    proc.communicate()
    assert _checkpoint_step(run) == 0
    r = run_cli("train", "--resume", str(run), "--steps", "300", "--no-progress")
    assert r.returncode == 0, r.stderr
    assert _checkpoint_step(run) == 300
    steps = [int(row[0]) for row in _csv_rows(run / "progress.csv")[1:]]
    assert steps == sorted(set(steps)) and steps[-1] == 300  # the killed run's rows were replaced, none twice


def _wait_until_stopped(proc, hang_guard=600.0):
    """Until `proc` is stopped (SIGSTOP); a process that exits instead fails the test with its stderr."""
    deadline = time.monotonic() + hang_guard
    while True:
        pid, status = os.waitpid(proc.pid, os.WNOHANG | os.WUNTRACED)
        if pid and os.WIFSTOPPED(status):
            return
        assert not pid, f"exited ({status}) before stopping: {proc.stderr.read()}"
        assert time.monotonic() < deadline, "hang guard: never stopped"
        time.sleep(0.05)


def _env_log(path):
    """Slow-v0's log (SOFTAC_TEST_ENV_LOG): (event, episode seed) per reset and step, in order."""
    return [(event, int(seed)) for event, seed in (line.split() for line in path.read_text().splitlines())]


@pytest.mark.faults
def test_sigterm_during_evaluation_stops_it_within_the_step_under_way_and_exits_130(tmp_path):
    """SIGTERM in the middle of a 2000-episode evaluation: it stops within the batched step under way, is not
    recorded, and the run checkpoints the step it was at and exits 130. Where the process was and what it did
    after the signal come from the process itself, not from the clock: Slow-v0 logs every reset and step and
    stops the process at its first evaluation step, where the test sends the signal."""
    from softac.run.evaluation import EVAL_SEED_OFFSET, MAX_PARALLEL

    run, log = tmp_path / "run", tmp_path / "env.log"
    proc = _popen_train("--env", "softac_test_envs:Slow-v0", "--steps", "100000", "--out", str(run),
                        "--set", "hidden_sizes=16", "batch_size=16", "learning_starts=50", "eval_interval=100",
                        "eval_episodes=2000", "checkpoint_interval=0", "buffer_size=1000", "log_interval=100",
                        env=child_env(SOFTAC_TEST_ENV_LOG=str(log), SOFTAC_TEST_STOP_IN_EVAL="1"))
    try:
        _wait_until_stopped(proc)
        before = _env_log(log)
        evaluating = [(event, seed) for event, seed in before if seed >= EVAL_SEED_OFFSET]
        # inside the first evaluation, at its first step: its first MAX_PARALLEL episodes started side by side
        assert evaluating == [("reset", EVAL_SEED_OFFSET + i) for i in range(MAX_PARALLEL)] + \
            [("step", EVAL_SEED_OFFSET)]
        assert sum(event == "step" for event, _ in before) == 100 + 1  # after the training steps to step 100
        assert (run / "eval.csv").read_text().count("\n") == 1  # no evaluation recorded yet
        proc.send_signal(signal.SIGTERM)
        proc.send_signal(signal.SIGCONT)
        _, err = proc.communicate(timeout=600)  # a hang guard, not a measure
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, err
    after = _env_log(log)[len(before):]
    # it stepped at most the rest of the batched step under way (one step of each other parallel episode, of
    # the 2000 * up to 25 steps of the whole evaluation), started no new episode, took no training step
    assert all(event == "step" and seed >= EVAL_SEED_OFFSET for event, seed in after), after
    assert len(after) <= MAX_PARALLEL - 1
    assert (run / "eval.csv").read_text().count("\n") == 1  # the cut evaluation was not recorded
    assert _checkpoint_step(run) == 100


@pytest.mark.faults
def test_a_stopped_sweep_trial_stuck_after_its_checkpoint_ends_itself_and_resumes(tmp_path):
    """A sweep trial's process runs outside its Ray worker's process group, so nothing else would end it if it
    hung after a stop: stopped, it ends itself (SIGALRM) once its deadline has passed, wherever it is stuck.
    Here it is started as a trial would start it (its parent's pid in SOFTAC_TRIAL_PARENT), its eval env hangs
    in close() (600 s) after the stop's checkpoint, and the deadline is 2 s: it dies by SIGALRM, and the
    checkpoint it wrote resumes. Without a stop, the deadline plays no part (the run trains past it)."""
    run = tmp_path / "run"
    env = child_env(SOFTAC_TRIAL_PARENT=str(os.getpid()), SOFTAC_TRIAL_STOP_DEADLINE_S="2",
                    SOFTAC_TEST_SLOW_CLOSE_S="600")
    proc = _popen_train("--env", "softac_test_envs:Slow-v0", "--steps", "100000", "--out", str(run),
                        *TINY_SETS[:-1], "eval_interval=100", "eval_episodes=2", "checkpoint_interval=0", env=env)
    evals = run / "eval.csv"
    try:
        _wait_for(lambda: evals.exists() and evals.read_text().count("\n") >= 4, proc)  # 3 evaluations: > 2 s
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=300)  # a hang guard: without the deadline it would sleep 600 s
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == -signal.SIGALRM, err
    step = _checkpoint_step(run)
    assert step >= 300
    resumed = run_cli("train", "--resume", str(run), "--steps", "50", "--no-progress")
    assert resumed.returncode == 0, resumed.stderr
    assert _checkpoint_step(run) == step + 50


@pytest.mark.faults
def test_sigterm_during_a_checkpoint_write_finishes_it_then_exits(tmp_path, monkeypatch):
    from softac.run import checkpoint as ckpt
    from softac.agent import SAC
    from softac.errors import TrainingInterrupted

    real_save, calls = ckpt.save, []

    def save_with_signal(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            os.kill(os.getpid(), signal.SIGTERM)  # arrives in the middle of the second write
        return real_save(*args, **kwargs)

    monkeypatch.setattr(ckpt, "save", save_with_signal)
    agent = SAC(tiny_config(checkpoint_interval=200))
    with pytest.raises(TrainingInterrupted):
        agent.learn(100_000, run_dir=tmp_path / "run", progress=False)
    assert SAC.load(tmp_path / "run", which="last").num_steps == agent.num_steps


def test_full_disk_keeps_the_previous_checkpoint(tmp_path, monkeypatch):
    from softac.agent import SAC
    from softac.errors import SoftacError

    from softac.run import checkpoint

    real_write, calls = checkpoint._write_npz, []

    def write_then_disk_full(file, arrays):
        calls.append(1)
        if len(calls) >= 3:
            file.write(b"partial")
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(file, arrays)

    monkeypatch.setattr(checkpoint, "_write_npz", write_then_disk_full)
    run = tmp_path / "run"
    agent = SAC(tiny_config(checkpoint_interval=200))
    with pytest.raises(SoftacError, match="No space left on device; the previous checkpoint is kept"):
        agent.learn(1000, run_dir=run, progress=False)
    monkeypatch.setattr(checkpoint, "_write_npz", real_write)
    assert SAC.load(run, which="last").num_steps == 200
    leftovers = [p.name for p in (run / "checkpoints" / "last").iterdir() if p.name.startswith(".")]
    assert leftovers == []


def test_full_disk_on_a_real_small_filesystem(tmp_path):
    mount = tmp_path / "small"
    mount.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mount)],
                      capture_output=True).returncode != 0:
        pytest.skip("cannot mount a small tmpfs here (needs root)")
    try:
        run = mount / "run"
        # a 20k-transition buffer of Pusher-sized rows outgrows 2 MiB after a few thousand steps
        r = run_cli("train", "--env", "Pusher-v5", "--steps", "20000", "--out", str(run), "--no-progress",
                    *TINY_SETS, "checkpoint_interval=1000", "learning_starts=20000", timeout=300)
        assert_training_error(r, "could not write checkpoint", "No space left on device",
                           "the previous checkpoint is kept")
        from softac.agent import SAC

        kept = SAC.load(run, which="last").num_steps  # a checkpoint written before the disk filled
        assert kept >= 1000 and kept % 1000 == 0, kept
    finally:
        subprocess.run(["umount", str(mount)], capture_output=True)


@pytest.mark.parametrize("env_id,fragment", [
    ("NanObs-v0", "non-finite observation at step"),
    ("NanReward-v0", "non-finite reward at step"),
    ("BrokenStep-v0", "BrokenStep-v0 raised in step at step"),
    ("BrokenReset-v0", "BrokenReset-v0 raised in reset at step"),
    ("HugeReward-v0", "training diverged at step"),
])
def test_bad_env_or_divergence_stops_with_exit_3_and_keeps_the_checkpoint(tmp_path, env_id, fragment):
    run = tmp_path / "run"
    r = run_cli("train", "--env", f"softac_test_envs:{env_id}", "--steps", "3000", "--out", str(run), *TINY_SETS,
                "checkpoint_interval=20", "--no-progress")
    assert_training_error(r, fragment)
    from softac.agent import SAC
    import jax

    agent = SAC.load(run, which="last")
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree_util.tree_leaves(agent.learner.state))


def test_checkpoints_never_execute_code(tmp_path):
    from softac.agent import SAC

    agent = SAC(tiny_config())
    agent.save(tmp_path / "ckpt")
    meta = json.loads((tmp_path / "ckpt" / "meta.json").read_text())
    arrays = tmp_path / "ckpt" / meta["arrays_file"]
    with open(arrays, "wb") as f:  # a pickled object array, as a malicious file would carry
        np.savez(f, act_key=np.array([object()], dtype=object))
    import hashlib

    meta["sha256"] = hashlib.sha256(arrays.read_bytes()).hexdigest()
    (tmp_path / "ckpt" / "meta.json").write_text(json.dumps(meta))
    assert_clean_error(run_cli("eval", str(tmp_path / "ckpt")), "corrupt checkpoint", "cannot read")
    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign" / "meta.json").write_bytes(os.urandom(64))
    assert_clean_error(run_cli("eval", str(tmp_path / "foreign")), "corrupt checkpoint")


@pytest.mark.exact
def test_same_seed_is_identical_across_processes(tmp_path):
    runs = [tmp_path / "a", tmp_path / "b"]
    for run in runs:
        r = run_cli("train", "--env", "softac_test_envs:Drift-v0", "--steps", "700", "--out", str(run),
                    "--no-progress", *TINY_SETS, "eval_interval=350")
        assert r.returncode == 0, r.stderr

    def metrics(run):
        rows = _csv_rows(run / "progress.csv")
        keep = [i for i, c in enumerate(rows[0]) if c not in ("time_s", "fps")]
        return [[r[i] for i in keep] for r in rows]

    assert metrics(runs[0]) == metrics(runs[1])
    for name in ("episodes.csv", "eval.csv"):
        assert (runs[0] / name).read_text() == (runs[1] / name).read_text()
    assert_same_last_checkpoint(runs[0], runs[1])


# ---- fuzzing: any value runs or is refused with a ConfigError / exit 2, never a traceback ----

from softac.config.sac_config import ConfigError, SACConfig  # noqa: E402

values = st.one_of(st.integers(-10**12, 10**12), st.floats(allow_nan=True, allow_infinity=True),
                   st.booleans(), st.none(), st.text(max_size=12),
                   st.lists(st.integers(-5, 300), max_size=4), st.sampled_from(["auto", "1e3", "256,256", "-1", ""]))


@settings(max_examples=300, deadline=None)
@given(key=st.sampled_from(sorted(SACConfig.field_docs()) + ["bogus_key"]), value=values)
def test_config_fuzz(key, value):
    try:
        SACConfig().replace(**{key: value})
    except ConfigError:
        pass


@settings(max_examples=200, deadline=None)
@given(key=st.sampled_from(sorted(SACConfig.field_docs())), text=st.text(max_size=16))
def test_set_fuzz_parses_or_refuses(key, text):
    try:
        SACConfig().with_overrides([f"{key}={text}"])
    except ConfigError:
        pass


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(pairs=st.lists(st.tuples(st.sampled_from(["batch_size", "hidden_sizes", "gamma", "tau", "n_critics",
                                                 "gradient_steps", "policy_frequency", "policy_delay", "log_std_min", "alpha",
                                                 "target_entropy", "n_envs", "learning_starts", "eval_episodes",
                                                 "buffer_size", "matmul_dtype", "init", "log_std_mode"]),
                                st.sampled_from(["0", "1", "2", "-1", "1e9", "0.5", "nan", "abc", "3,3", "[]",
                                                 "true", "bfloat16", "orthogonal", "tanh", "auto", "1e-3"])),
                      min_size=1, max_size=3))
def test_cli_fuzz_runs_or_exits_2(tmp_path, pairs):
    from softac.cli.main import main

    out = tmp_path / f"run{random.random()}"
    code = main(["train", "--env", "softac_test_envs:Drift-v0", "--steps", "40", "--out", str(out), "--no-progress",
                 "--set", *[f"{k}={v}" for k, v in pairs], "--set", "learning_starts=20", "eval_interval=0"])
    assert code in (0, 2)
