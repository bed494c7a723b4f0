"""One run directory, one writer: two processes never write one run (or one sweep directory) at once; the
second is refused with one line naming the holder, and a holder killed with -9 never blocks the next one.
Also the checkpoint writer's own turn-taking, and what a refused start leaves behind (nothing)."""

import json
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from conftest import assert_clean_error, child_env, run_cli
from softac import SAC
from softac.run import checkpoint as ckpt
from softac.errors import SoftacError
from softac.run.run_dir import LOCK, RunLocked, run_lock

DRIFT = "softac_test_envs:Drift-v0"
TINY_SET = ["--set", "hidden_sizes=16,16", "batch_size=16", "learning_starts=100", "eval_interval=200",
            "eval_episodes=2", "log_interval=100", "buffer_size=2000"]


def _popen(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "softac", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=child_env())


def _wait_until(condition, proc: subprocess.Popen, limit_s: float = 300) -> None:
    """Poll until `condition()`; a hang guard only (the process itself says when it is ready)."""
    deadline = time.monotonic() + limit_s
    while not condition():
        if proc.poll() is not None:
            raise AssertionError(f"process ended early ({proc.returncode}): {proc.stderr.read()}")
        if time.monotonic() > deadline:
            proc.kill()
            raise AssertionError("timed out waiting")
        time.sleep(0.1)


def _training(run: Path) -> bool:
    """The run has written its first progress row: its process holds the lock and is in its loop."""
    progress = run / "progress.csv"
    return progress.exists() and len(progress.read_text().splitlines()) >= 2


def _stop(proc: subprocess.Popen, sig: int = signal.SIGKILL) -> None:
    proc.send_signal(sig)
    proc.communicate(timeout=120)


def test_a_second_train_or_resume_of_a_run_being_written_exits_2_naming_the_holder(tmp_path):
    run = tmp_path / "run"
    holder = _popen("train", "--env", DRIFT, "--steps", "10000000", "--out", str(run), "--no-progress", *TINY_SET)
    try:
        _wait_until(lambda: _training(run), holder)
        before = {p: p.read_bytes() for p in (run / "checkpoints").rglob("*") if p.is_file()}
        config = (run / "config.yaml").read_text()

        second = run_cli("train", "--env", DRIFT, "--seed", "1", "--steps", "300", "--out", str(run), "--no-progress",
                         *TINY_SET)
        assert_clean_error(second, str(run), f"pid {holder.pid}")
        assert_clean_error(run_cli("train", "--resume", str(run), "--no-progress"), f"pid {holder.pid}")
        # nothing of the refused processes reached the run: its config and checkpoints are the holder's
        assert (run / "config.yaml").read_text() == config
        assert yaml.safe_load(config)["seed"] == 0
        assert all(p.read_bytes() == data for p, data in before.items() if p.exists())
    finally:
        _stop(holder)
    # the holder died with -9 holding the lock: the next process takes it at once
    r = run_cli("train", "--resume", str(run), "--steps", "100", "--no-progress")
    assert r.returncode == 0, r.stderr


def test_two_trains_started_together_into_one_new_directory_leave_one_run(tmp_path):
    """Measured before the lock: both exited 0 and the directory held one seed's config and the other's logs."""
    run = tmp_path / "run"
    procs = [_popen("train", "--env", DRIFT, "--seed", str(seed), "--steps", "400", "--out", str(run),
                    "--no-progress", *TINY_SET) for seed in (0, 1)]
    results = [(p.returncode, err) for p, (_, err) in ((p, p.communicate(timeout=600)) for p in procs)]
    codes = sorted(code for code, _ in results)
    assert codes == [0, 2], results
    winner = [seed for seed, (code, _) in zip((0, 1), results, strict=True) if code == 0][0]
    refused = [err for code, err in results if code == 2][0]
    lines = [line for line in refused.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in refused
    # refused while the other wrote (naming its pid, also when refused before the winner had written it), or
    # after it finished: either way, one line naming why
    assert "is being written by pid" in lines[0] or "already holds a run" in lines[0], lines[0]
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert config["seed"] == winner
    summary = json.loads((run / "summary.json").read_text())
    assert summary["steps"] == 400
    evals = (run / "eval.csv").read_text().splitlines()[1:]
    assert [int(row.split(",")[0]) for row in evals] == [200, 400]  # one run's evaluations, none twice
    assert SAC.load(run, which="last").num_steps == 400


def test_the_api_is_refused_too_and_a_lock_is_reentrant_within_a_process(tmp_path, tiny):
    run = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", """
import sys, time
from softac.run.run_dir import run_lock
with run_lock(sys.argv[1]):
    print("locked", flush=True)
    time.sleep(600)
""", str(run)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        agent = SAC(tiny())
        with pytest.raises(RunLocked, match=f"pid {holder.pid}"):
            agent.learn(100, run_dir=run, progress=False)
        assert agent.num_steps == 0
    finally:
        _stop(holder)
    other = tmp_path / "other"
    with run_lock(other):
        with run_lock(other):  # the CLI holds it, then learn() takes it again
            SAC(tiny()).learn(200, run_dir=other, progress=False)
        assert (other / "summary.json").exists()


def test_a_run_refused_before_it_starts_leaves_nothing(tmp_path, tiny):
    """A bad callback is found before the run directory is written (it used to leave config.yaml and logs)."""
    run = tmp_path / "runs" / "new"
    with pytest.raises(SoftacError, match="callback"):
        SAC(tiny()).learn(100, run_dir=run, callbacks=[object()], progress=False)
    assert not run.exists()
    (tmp_path / "existing").mkdir()
    with pytest.raises(SoftacError, match="callback"):
        SAC(tiny()).learn(100, run_dir=tmp_path / "existing", callbacks=[object()], progress=False)
    assert list((tmp_path / "existing").iterdir()) == []
    r = run_cli("train", "--env", DRIFT, "--out", str(tmp_path / "cli"), "--set", "batch_size=0")
    assert_clean_error(r, "batch_size")
    assert not (tmp_path / "cli").exists()


def test_resume_keeps_each_segments_record_in_config_yaml(tmp_path):
    run = tmp_path / "run"
    r = run_cli("train", "--env", DRIFT, "--steps", "300", "--out", str(run), "--no-progress", *TINY_SET)
    assert r.returncode == 0, r.stderr
    first = yaml.safe_load((run / "config.yaml").read_text())
    r = run_cli("train", "--resume", str(run), "--steps", "100", "--cpus", "1", "--no-progress", "--logger", "none")
    assert r.returncode == 0, r.stderr
    text = (run / "config.yaml").read_text()
    config = yaml.safe_load(text)
    assert "*id" not in text and "&id" not in text  # plain YAML, no aliases
    segments = config["segments"]
    assert [s["start_step"] for s in segments] == [0, 300]
    assert segments[0] == first["segments"][0]  # the first segment's record is kept as it was
    assert segments[1]["cpus"] == 1 and segments[0]["cpus"] == first["cpus"]
    assert segments[0]["pid"] != segments[1]["pid"]
    for segment in segments:
        assert segment["versions"]["softac"] and segment["machine"]
    # the top level keeps the run's start; the config keys are the run's current ones
    assert config["cpus"] == first["cpus"] and config["versions"] == first["versions"]
    assert config["loggers"] == "none"
    from softac.config.sac_config import SACConfig

    assert SACConfig.from_yaml(run / "config.yaml").seed == 0  # the record-only keys are ignored when read back


def test_training_again_in_the_same_process_extends_its_segment(tmp_path, tiny):
    agent = SAC(tiny())
    for _ in range(3):
        agent.learn(100, run_dir=tmp_path / "run", progress=False)
    assert [s["start_step"] for s in yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())["segments"]] == [0]


def test_two_writers_of_one_checkpoint_take_turns(tmp_path, monkeypatch):
    """Writer A is held between its arrays file and its meta.json while B saves into the same directory.
    Without turns, B removed A's new arrays file and A's meta.json then named a missing file."""
    from softac.run import run_dir as rundir

    directory = tmp_path / "ckpt"
    ckpt.save(directory, {"who": "first"}, {"x": np.zeros(3)})
    real_write_atomic = rundir.write_atomic
    a_paused, b_done = threading.Event(), threading.Event()

    def slow_meta(path, data):
        if threading.current_thread().name == "A" and path.name == ckpt.META:
            a_paused.set()
            b_done.wait(3.0)  # B finishes meanwhile unless it waits its turn
        real_write_atomic(path, data)

    monkeypatch.setattr(ckpt, "write_atomic", slow_meta)
    a = threading.Thread(target=ckpt.save, args=(directory, {"who": "A"}, {"x": np.ones(3)}), name="A")
    a.start()
    assert a_paused.wait(60)
    b = threading.Thread(target=lambda: (ckpt.save(directory, {"who": "B"}, {"x": np.full(3, 2.0)}), b_done.set()),
                         name="B")
    b.start()
    a.join(60)
    b.join(60)
    meta, arrays = ckpt.load(directory)
    assert meta["who"] == "B" and arrays["x"].tolist() == [2.0, 2.0, 2.0]  # the last to finish, whole
    assert sorted(p.name for p in directory.glob("arrays-*.npz")) == [meta["arrays_file"]]


def test_a_reader_meeting_a_save_reads_again(tmp_path, monkeypatch):
    directory = tmp_path / "ckpt"
    ckpt.save(directory, {"n": 1}, {"x": np.zeros(2)})
    real_read_arrays, calls = ckpt._read_arrays, []

    def save_in_between(where, meta):
        calls.append(meta["n"])
        if len(calls) == 1:  # a training process replaces the checkpoint between meta.json and the arrays
            ckpt.save(directory, {"n": 2}, {"x": np.ones(2)})
        return real_read_arrays(where, meta)

    monkeypatch.setattr(ckpt, "_read_arrays", save_in_between)
    meta, arrays = ckpt.load(directory)
    assert calls == [1, 2] and meta["n"] == 2 and arrays["x"].tolist() == [1.0, 1.0]


@pytest.mark.ray
def test_a_second_sweep_driver_of_one_directory_exits_2(tmp_path):
    out = tmp_path / "sweep"
    args = ["sweep", "--env", DRIFT, "--seeds", "1", "--steps", "10000000", "--out", str(out), "--threshold=-1e9",
            *TINY_SET]
    holder = _popen(*args)
    try:
        _wait_until(lambda: _training(out / "seed=0"), holder, limit_s=600)
        assert_clean_error(run_cli(*args), str(out), f"pid {holder.pid}", "sweep")
        assert_clean_error(run_cli("sweep", "--resume", str(out)), f"pid {holder.pid}")
        # the trial's own run is locked by its `softac train` process
        assert_clean_error(run_cli("train", "--resume", str(out / "seed=0"), "--no-progress"), "is being written by pid")
    finally:
        _stop(holder, signal.SIGINT)
    assert holder.returncode == 130, holder.returncode
    assert (out / LOCK).exists()  # left in place, never in the way


def test_runs_started_together_share_one_bounded_locked_compile_cache(tmp_path):
    """Two runs of one config at once, one compile cache (softac.base.device) that an unbounded cache wrote into
    before: both train, neither warns of an entry read while the other wrote it (nor of the old entry), the
    cache holds their programs with JAX's lock file (the size limit turns on its eviction and locking), and a
    third run loads its update from there (a hit stamps the entry's access time) and writes no new program."""
    env = {**child_env(), "SOFTAC_COMPILE_CACHE": str(tmp_path / "cache")}
    (tmp_path / "cache").mkdir()
    (tmp_path / "cache" / "jit_old-0-cache").write_bytes(b"x")  # as an unbounded cache left it: no -atime file
    args = ["train", "--env", DRIFT, "--steps", "300", "--no-progress", "--logger", "none", *TINY_SET]
    procs = [subprocess.Popen([sys.executable, "-m", "softac", *args, "--out", str(tmp_path / f"run{i}")],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env) for i in range(2)]
    for proc in procs:
        _, stderr = proc.communicate(timeout=300)
        assert proc.returncode == 0, stderr
        assert "compilation cache" not in stderr and "Warning" not in stderr, stderr
    entries = sorted(p.name for p in (tmp_path / "cache").iterdir())
    assert ".lockfile" in entries and "jit_old-0-atime" in entries  # dated, so JAX's eviction can read it
    [update] = [name[:-len("-cache")] for name in entries
                if name.startswith("jit_update_program-") and name.endswith("-cache")]
    third = subprocess.run([sys.executable, "-c", (
        "import jax; from softac.base.device import COMPILE_CACHE_MAX_BYTES, select_device; select_device('cpu'); "
        "assert jax.config.jax_compilation_cache_max_size == COMPILE_CACHE_MAX_BYTES")], env=env,
        capture_output=True, text=True, timeout=120)
    assert third.returncode == 0, third.stderr
    before = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "cache").glob("*-cache")}
    accessed = (tmp_path / "cache" / f"{update}-atime").read_bytes()
    rerun = subprocess.run([sys.executable, "-m", "softac", *args, "--out", str(tmp_path / "run2")], env=env,
                           capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "cache").glob("*-cache")} == before  # none new
    assert (tmp_path / "cache" / f"{update}-atime").read_bytes() != accessed  # its update loaded from the cache
