"""Env worker processes (env_workers): the same transitions as in-process envs, exact resume across worker
counts, a dead worker or a raising env as a clear error, and no process left behind."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import assert_clean_error, assert_same_training, assert_training_error, child_env, run_cli
from softac import SAC
from softac.run.callbacks import Callback
from softac.config.sac_config import ConfigError
from softac.envs.workers import WorkerEnvPool, split_evenly
from softac.envs.make import EnvError, EnvFailed, EnvPool, copy_env
from softac_test_envs import DriftEnv

TINY_SETS = ["--set", "hidden_sizes=32,32", "batch_size=32", "learning_starts=100", "buffer_size=5000",
             "log_interval=100", "eval_interval=0"]


def _running(pid: int) -> bool:
    """Is `pid` a live process (a zombie has exited; it only waits to be reaped)?"""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _worker_pids(parent: int) -> list[int]:
    """The env worker processes (spawned multiprocessing children) of `parent`."""
    pids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            ppid = int(stat.read_text().rsplit(")", 1)[1].split()[1])
            cmdline = (stat.parent / "cmdline").read_bytes()
        except (OSError, IndexError, ValueError):
            continue
        if ppid == parent and b"spawn_main" in cmdline:
            pids.append(int(stat.parent.name))
    return pids


def test_split_evenly_gives_contiguous_slices():
    assert split_evenly(5, 2) == [(0, 2), (2, 5)]
    assert split_evenly(4, 4) == [(0, 1), (1, 2), (2, 3), (3, 4)]


def test_env_workers_must_be_between_0_and_n_envs(tiny):
    assert tiny(n_envs=4, env_workers=4).env_workers == 4
    with pytest.raises(ConfigError, match="env_workers=3: must be between 0 .* and n_envs=2"):
        tiny(n_envs=2, env_workers=3)
    with pytest.raises(ConfigError, match="env_workers"):
        tiny(env_workers=-1)
    assert_clean_error(run_cli("train", "--env-workers", "2"), "env_workers=2", "n_envs=1")


@pytest.mark.parametrize("argv", [["--set", "env_workers=4", "--n-envs", "4"], ["--env-workers", "4", "--set", "n_envs=4"],
                                  ["--set", "env_workers=4", "n_envs=4"]])
def test_env_workers_and_n_envs_are_checked_together_whichever_option_sets_them(argv):
    from softac.cli.main import build_parser
    from softac.cli.commands import _resolve_train_config

    config = _resolve_train_config(build_parser().parse_args(["train", "--env", "InvertedPendulum-v5", *argv]))
    assert (config.n_envs, config.env_workers) == (4, 4)


@pytest.mark.parametrize("source", ["softac_test_envs:Drift-v0", "InvertedPendulum-v5", "instance"])
def test_worker_pool_steps_and_saves_like_the_in_process_pool(source):
    """Step for step the same observations, rewards, ends and episode results; state moved mid-way from the
    workers to in-process envs and to another number of workers carries on exactly."""
    if source == "instance":
        source = DriftEnv(low=-2.0, high=0.5)  # no spec: the workers get it pickled
    n, rng = 3, np.random.default_rng(0)
    act_dim = copy_env(source).action_space.shape[0]
    local = EnvPool(lambda i: copy_env(source), n, seed=5, name="env")
    workers = WorkerEnvPool(source, n, seed=5, name="env", workers=2)
    try:
        np.testing.assert_array_equal(local.reset(0), workers.reset(0))
        finished = 0
        for t in range(120):
            actions = rng.uniform(-1, 1, (n, act_dim)).astype(np.float32)
            a, b = local.step(actions, t), workers.step(actions, t)
            for field in ("next_obs", "rewards", "terminated", "truncated"):
                np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)
            assert a.finished == b.finished
            np.testing.assert_array_equal(local.obs, workers.obs)
            finished += len(a.finished)
            if t == 60:
                meta, arrays = workers.get_state()
                assert meta == local.get_state()[0]
                local = EnvPool(lambda i: copy_env(source), n, seed=5, name="env")
                assert local.set_state(meta, arrays, t)
                workers.close()
                workers = WorkerEnvPool(source, n, seed=5, name="env", workers=3)
                assert workers.set_state(meta, arrays, t)
        assert finished > 0  # resets of finished envs were compared too
    finally:
        workers.close()


def test_an_env_instance_that_cannot_be_sent_to_workers_is_a_clear_error():
    class Local(DriftEnv):  # a local class cannot be pickled
        pass

    with pytest.raises(EnvError, match="cannot be sent to env worker processes.*gymnasium.register"):
        WorkerEnvPool(Local(), 2, seed=0, name="Local", workers=2)


def test_env_workers_give_the_same_run_and_leave_no_process(tiny):
    runs = []
    for env_workers in (0, 2):
        agent = SAC(tiny(n_envs=3, env_workers=env_workers))
        agent.collector.start(agent.num_steps)
        pool = agent.collector.pool
        pids = getattr(pool, "pids", [])
        agent.learn(450, progress=False)
        assert agent.collector.pool is None if env_workers else agent.collector.pool is pool
        assert pids == [] or not any(map(_running, pids))
        runs.append(agent)
    local, workers = runs
    assert_same_training(local, workers)
    assert local.num_episodes == workers.num_episodes > 0


@pytest.fixture(scope="module")
def straight_run(tmp_path_factory):
    """900 steps in one go, envs in-process: what every split run below must equal."""
    from conftest import tiny_config

    agent = SAC(tiny_config(n_envs=2, gradient_steps=2, eval_interval=300))
    agent.learn(900, run_dir=tmp_path_factory.mktemp("straight") / "run", progress=False)
    return agent


@pytest.mark.exact
@pytest.mark.parametrize("first_workers,then_workers,how", [
    (2, 2, "load"), (2, 0, "load"), (0, 2, "load"), (2, 2, "learn again")])
def test_resume_with_env_workers_is_exact(tiny, tmp_path, straight_run, first_workers, then_workers, how):
    """500 steps, a checkpoint (or just a second learn() call, after which the workers were closed), 400
    more: the same as 900 in one go, whichever of workers or in-process envs stepped each part."""
    first = SAC(tiny(n_envs=2, gradient_steps=2, eval_interval=300, env_workers=first_workers))
    first.learn(500, run_dir=tmp_path / "split", progress=False)
    if how == "load":
        then = SAC.load(tmp_path / "split", which="last", env_workers=then_workers)
        assert then.config.env_workers == then_workers
    else:
        then = first
    then.learn(400, run_dir=tmp_path / "split", progress=False)
    assert_same_training(straight_run, then)


def test_a_killed_worker_fails_the_run_naming_the_env_and_the_next_learn_starts_afresh(tiny):
    agent = SAC(tiny("softac_test_envs:Slow-v0", n_envs=2, env_workers=2))
    agent.collector.start(agent.num_steps)
    pool = agent.collector.pool
    victim = pool.pids[1]

    class KillAtStep100(Callback):  # in the loop itself: not a thread racing the loop (which may finish first)
        def on_step(self, info):
            if info.step == 100:
                os.kill(victim, signal.SIGKILL)

    with pytest.raises(EnvFailed, match=rf"env softac_test_envs:Slow-v0: the env worker process {victim} \(env 1\) "
                                        r"was killed by SIGKILL at step 100"):
        agent.learn(4000, progress=False, callbacks=[KillAtStep100()])
    assert not any(map(_running, pool.pids)) and agent.collector.pool is None
    steps = agent.num_steps
    agent.learn(40, progress=False)  # new workers, fresh episodes
    assert agent.num_steps == steps + 40


def test_workers_exit_when_their_parent_is_killed_outright():
    code = ("import time\n"
            "from softac.envs.workers import WorkerEnvPool\n"
            "pool = WorkerEnvPool('softac_test_envs:Drift-v0', 2, seed=0, name='Drift-v0', workers=2)\n"
            "print(*pool.pids, flush=True)\n"
            "time.sleep(600)\n")
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                              env=child_env())
    workers = [int(pid) for pid in parent.stdout.readline().split()]
    assert len(workers) == 2 and all(map(_running, workers))
    parent.kill()
    parent.wait()
    deadline = time.monotonic() + 300  # a hang guard only: they see their pipe close at once
    while any(map(_running, workers)):
        assert time.monotonic() < deadline, "orphaned env workers"
        time.sleep(0.1)


@pytest.mark.parametrize("env_id,fragments", [
    ("BrokenStep-v0", ["BrokenStep-v0 raised in step at step", "simulator exploded"]),
    ("Crashing-v0", ["Crashing-v0: the env worker process", "was killed by SIGKILL at step"]),
])
def test_a_failing_env_in_a_worker_exits_3_and_keeps_the_checkpoint(tmp_path, env_id, fragments):
    run = tmp_path / "run"
    r = run_cli("train", "--env", f"softac_test_envs:{env_id}", "--steps", "3000", "--n-envs", "2",
                "--env-workers", "2", "--out", str(run), *TINY_SETS, "checkpoint_interval=20", "--no-progress")
    assert_training_error(r, *fragments)
    assert SAC.load(run, which="last").num_steps >= 20


@pytest.mark.faults
def test_ctrl_c_checkpoints_closes_the_workers_and_resumes_in_process(tmp_path):
    """Ctrl-C reaches the whole process group, workers too: they ignore it, the loop checkpoints and closes
    them, and the run resumes with its envs in-process."""
    run = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "softac", "train", "--env", "softac_test_envs:Slow-v0",
                             "--steps", "1000000", "--n-envs", "2", "--env-workers", "2", "--out", str(run),
                             "--no-progress", *TINY_SETS, "checkpoint_interval=0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env=child_env())
    deadline = time.monotonic() + 600  # a hang guard only
    while not (run / "progress.csv").exists() or len((run / "progress.csv").read_text().splitlines()) < 3:
        assert time.monotonic() < deadline and proc.poll() is None, proc.communicate()[1]
        time.sleep(0.1)
    workers = _worker_pids(proc.pid)
    assert len(workers) == 2
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "interrupted at step" in err and "Traceback" not in err
    assert not any(map(_running, workers))
    r = run_cli("train", "--resume", str(run), "--env-workers", "0", "--steps", "100", "--no-progress")
    assert r.returncode == 0, r.stderr
