"""`softac sweep --address` on a multi-node Ray cluster, on this one machine: Ray's own test cluster (a head and
worker nodes, each its own raylet with its own CPUs), as docs/cluster.md describes. A lost node costs no trial
(Tune retries it on a live node, and it continues from its checkpoint bit for bit), a killed driver resumes
without redoing finished trials, and a node that does not see the sweep directory stops the sweep at its start.

The cluster checks node health every 0.5 s (Ray's default: 3 s, 5 misses) so that a lost node is noticed in about
2 s; docs/cluster.md gives the figures at Ray's defaults (benchmarks/cluster_recovery.py)."""

import contextlib
import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import TESTS, assert_same_last_checkpoint, ray_test_cluster, run_cli
from softac import sweep

pytest.importorskip("ray.tune", reason="the [ray] extra is not installed")
pytestmark = pytest.mark.ray

SETTINGS = ["--env", "softac_test_envs:Slow-v0", "--steps", "1500", "--threshold=-1e9", "--set", "hidden_sizes=[16,16]",
            "batch_size=32", "learning_starts=100", "buffer_size=5000", "eval_interval=250", "eval_episodes=2",
            "log_interval=100", "checkpoint_interval=250"]
FAST_HEALTH_CHECKS = {"health_check_period_ms": 500, "health_check_failure_threshold": 3,
                      "health_check_initial_delay_ms": 0, "health_check_timeout_ms": 1000}


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _attempts(out: Path, trial: str) -> list[str]:
    """The trial's `softac train` commands, one per attempt, each ending with the node that ran it."""
    return [line for line in (out / "_logs" / f"{trial}.log").read_text().splitlines() if line.startswith("$ ")]


def _wait_until_no_process_names(path: Path, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while True:
        running = []
        for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
            with contextlib.suppress(OSError):
                if str(path).encode() in cmdline.read_bytes():
                    running.append(cmdline.parent.name)
        if not running:
            return
        assert time.monotonic() < deadline, f"processes still running on {path}: {running}"
        time.sleep(0.1)


def _node(attempt: str) -> str:
    return attempt.rsplit("node ", 1)[1].split()[0]


@pytest.fixture(scope="module")
def cluster():
    """A head without CPUs (the driver's node) and two worker nodes of one CPU each: two trials at a time, one per
    node. The nodes' processes inherit this environment: the test envs' module, and Ray's workers leaving their
    child processes alive on exit (docs/cluster.md's `ray start` does the same)."""
    with ray_test_cluster(num_cpus=0, _system_config=FAST_HEALTH_CHECKS) as cluster:
        _two_live_workers(cluster)
        yield cluster


def _two_live_workers(cluster) -> None:
    """Two worker nodes besides the head (a test that killed one gets a fresh one), and Ray knowing no others."""
    while len(cluster.worker_nodes) < 2:
        cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes(timeout=60)


@pytest.fixture(scope="module")
def undisturbed(cluster, tmp_path_factory):
    """The sweep the disturbed ones are compared with: seeds 0-2 on the cluster, nothing killed."""
    out = tmp_path_factory.mktemp("cluster") / "undisturbed"
    result = run_cli("sweep", *SETTINGS, "--seeds", "3", "--address", cluster.address, "--out", str(out), timeout=600)
    assert result.returncode == 0, result.stderr
    return out


def _same_run(a: Path, b: Path) -> None:
    """Two runs of one trial that ended alike: evaluations, episodes, and the final weights, buffer and RNGs."""
    for name in ("eval.csv", "episodes.csv"):
        assert (a / name).read_text() == (b / name).read_text(), name
    assert_same_last_checkpoint(a, b)


def test_trials_spread_over_the_nodes_and_one_lost_with_its_node_finishes_as_if_undisturbed(cluster, undisturbed,
                                                                                             tmp_path):
    head = cluster
    _two_live_workers(head)
    out = tmp_path / "sweep"
    driver = subprocess.Popen([sys.executable, "-m", "softac", "sweep", *SETTINGS, "--seeds", "2", "--address",
                               head.address, "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True, env={**os.environ, "PYTHONPATH": str(TESTS)})
    try:
        evals = out / "seed=0" / "eval.csv"  # two evaluations, so a checkpoint past step 0 (every 250 steps)
        deadline = time.monotonic() + 300
        while not (evals.exists() and len(evals.read_text().splitlines()) >= 3):
            assert driver.poll() is None, driver.communicate()
            assert time.monotonic() < deadline, "seed=0 made no progress"
            time.sleep(0.05)
        first = {trial: _attempts(out, trial)[0] for trial in ("seed=0", "seed=1")}
        assert _node(first["seed=0"]) != _node(first["seed=1"]), first  # one trial on each node, as Ray placed them
        # the whole node at once, as a machine that loses power: the trial's process, its Ray worker, the raylet
        victim = next(w for w in head.worker_nodes if w.node_id.startswith(_node(first["seed=0"])))
        trial_pid = json.loads((out / "seed=0" / ".lock").read_text())["pid"]
        worker_pid = int(Path(f"/proc/{trial_pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
        os.kill(trial_pid, signal.SIGSTOP)  # it must not see its worker die first (it would checkpoint and exit)
        head.remove_node(victim, allow_graceful=False)
        os.kill(worker_pid, signal.SIGKILL)
        os.kill(trial_pid, signal.SIGKILL)
        stdout, stderr = driver.communicate(timeout=600)
    finally:
        if driver.poll() is None:
            driver.kill()
    assert driver.returncode == 0, stderr
    assert "seed=0: lost (" in stderr and "retry 1 of 3, from its last checkpoint" in stderr, stderr
    assert "Traceback" not in stderr + stdout and "[2/2] finished" in stderr
    attempts = _attempts(out, "seed=0")
    assert len(attempts) == 2 and "--resume" in attempts[1]  # continued from its checkpoint ...
    assert _node(attempts[1]) != _node(attempts[0])  # ... on the node that is still alive
    assert [r["status"] for r in _rows(out / "summary.csv")] == ["done", "done"]
    for trial in ("seed=0", "seed=1"):
        _same_run(out / trial, undisturbed / trial)


def test_a_driver_killed_on_a_cluster_resumes_without_redoing_finished_trials(cluster, undisturbed, tmp_path):
    head = cluster
    _two_live_workers(head)
    out = tmp_path / "sweep"
    env = {**os.environ, "PYTHONPATH": str(TESTS)}
    driver = subprocess.Popen([sys.executable, "-m", "softac", "sweep", *SETTINGS, "--seeds", "3", "--address",
                               head.address, "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True, env=env)
    try:
        deadline = time.monotonic() + 300
        while not any(sweep.trial_state(out / f"seed={s}") == "done" for s in range(2)):
            assert driver.poll() is None, driver.communicate()
            assert time.monotonic() < deadline, "no trial finished"
            time.sleep(0.05)
        driver.kill()  # SIGKILL: no chance to stop its trials; Ray ends them when it sees their driver gone
        driver.communicate(timeout=60)
    finally:
        if driver.poll() is None:
            driver.kill()
    # the killed driver's trial processes end when Ray sees it gone (SIGTERM from their worker's death: a
    # checkpoint), and one near its end may finish meanwhile: count the finished trials once they are all gone
    _wait_until_no_process_names(out, timeout=120)
    finished = {s for s in range(3) if sweep.trial_state(out / f"seed={s}") == "done"}
    assert finished and len(finished) < 3
    resumed = run_cli("sweep", "--resume", str(out), "--address", head.address, "--threshold=-1e9", timeout=600)
    assert resumed.returncode == 0, resumed.stderr
    assert f"3 trials ({len(finished)} already finished)" in resumed.stderr
    for s in range(3):
        attempts = _attempts(out, f"seed={s}")
        if s in finished:
            assert len(attempts) == 1  # not redone
        _same_run(out / f"seed={s}", undisturbed / f"seed={s}")
    timeless = lambda path: [{k: v for k, v in row.items() if "second" not in k and k != "wall_s"}  # noqa: E731
                             for row in _rows(path)]
    assert timeless(out / "summary.csv") == timeless(undisturbed / "summary.csv")
    assert (out / "summary.md").read_text().count("| 3 |") == (undisturbed / "summary.md").read_text().count("| 3 |")


def test_a_node_that_does_not_see_the_sweep_directory_stops_the_sweep_before_its_trials(cluster, tmp_path):
    """A node whose filesystem lacks DIR: here a node started in its own mount namespace with an empty tmpfs over
    DIR's parent, as a node without the shared filesystem would be (it needs unshare and mount: root, or user
    namespaces)."""
    head = cluster
    _two_live_workers(head)
    hidden = tmp_path / "shared"
    hidden.mkdir()
    probe = subprocess.run(["unshare", "-m", "sh", "-c", f"mount -t tmpfs tmpfs {hidden}"], capture_output=True)
    if probe.returncode != 0:
        pytest.skip(f"cannot make a mount namespace here: {probe.stderr.decode().strip()}")
    ray_cli = Path(sys.executable).parent / "ray"
    node_log = tmp_path / "node.log"
    node = None
    try:
        for _attempt in range(3):  # `ray start` gives its raylet 30 s to register (fixed in Ray): on a loaded
            with open(node_log, "w") as log:  # 2-core machine that ran out once; a node that never joins is retried
                node = subprocess.Popen(["unshare", "-m", "sh", "-c", f"mount -t tmpfs tmpfs {hidden} && exec "
                                         f"{ray_cli} start --address={head.address} --num-cpus=1 --block"],
                                        start_new_session=True, stdout=log, stderr=subprocess.STDOUT)
            deadline = time.monotonic() + 120
            while len(head.global_state._live_node_ids()) < 4 and node.poll() is None:
                assert time.monotonic() < deadline, node_log.read_text()[-3000:]
                time.sleep(0.2)
            if node.poll() is None:
                break
            with contextlib.suppress(ProcessLookupError):  # whatever that attempt left running
                os.killpg(node.pid, signal.SIGKILL)
        assert node.poll() is None, node_log.read_text()[-3000:]
        out = hidden / "sweep"
        result = run_cli("sweep", *SETTINGS, "--seeds", "2", "--address", head.address, "--out", str(out), timeout=300)
        assert result.returncode == 2, result.stderr
        lines = [ln for ln in result.stderr.splitlines() if ln.startswith("softac:")]
        assert len(lines) == 1 and "does not see the sweep directory" in lines[0] and "(3 of 4 nodes do)" in lines[0]
        assert "Traceback" not in result.stderr
        assert not (out / "seed=0").exists() and not (out / "_logs").exists()  # no trial started
    finally:
        if node is not None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(node.pid, signal.SIGKILL)
            node.wait(30)
        head.wait_for_nodes(timeout=60)  # until Ray has marked it dead
        shutil.rmtree(hidden, ignore_errors=True)


def test_a_trial_lost_more_often_than_retried_fails_the_sweep_naming_it(cluster, tmp_path):
    """On a local Ray, started beside the cluster (without --address a sweep does not join a Ray that `ray start`
    runs on the machine): Crashing-v0 kills its own process (SIGKILL) at its 30th step, every attempt."""
    out = tmp_path / "sweep"
    result = run_cli("sweep", "--env", "softac_test_envs:Crashing-v0", "--steps", "400", "--max-retries", "2",
                     "--out", str(out), "--set", "hidden_sizes=[16,16]", "batch_size=32", "learning_starts=100",
                     timeout=600)
    assert result.returncode == 3, result.stderr
    assert "Traceback" not in result.stderr
    assert result.stderr.count("seed=0: lost (seed=0: its process was killed by SIGKILL") == 2, result.stderr
    assert "retry 2 of 2" in result.stderr and "[1/1] FAILED seed=0 after 2 retries" in result.stderr
    last = [line for line in result.stderr.splitlines() if line.startswith("softac:")]
    assert "1 trial(s) failed, first: seed=0: its process was killed by SIGKILL" in last[0], last
    assert len(_attempts(out, "seed=0")) == 3
