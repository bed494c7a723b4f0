"""How long a sweep on a multi-node Ray cluster takes to notice a lost node and to continue the lost trial
(docs/cluster.md). On this one machine: Ray's test cluster (a head without CPUs, worker nodes of one CPU each,
each its own raylet), a `softac sweep --address` of 2 trials on a test env, and one spare node. When the first
trial has a checkpoint past step 0, its whole node goes at once (the trial's process, its Ray worker, the raylet:
kill -9), as a machine that loses power. Measured from that moment, from the driver's lines and the trial's log:

  detect: the driver prints "lost"            (Ray marks the node dead after its health checks fail)
  resume: the retried attempt's process starts (on a live node, from the run's last checkpoint)
  done:   the lost trial finishes

and the trials lost (0 expected: the sweep must exit 0 with every trial done). Ray's health checks at their
defaults (a check every 3 s, dead after 5 missed), or --fast for the test suite's (0.5 s, 3).

  python benchmarks/cluster_recovery.py [--repeats 3] [--fast]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TESTS = Path(__file__).resolve().parent.parent / "tests"
SETTINGS = ["--env", "softac_test_envs:Slow-v0", "--steps", "2000", "--seeds", "2", "--threshold=-1e9", "--set",
            "hidden_sizes=[16,16]", "batch_size=32", "learning_starts=100", "buffer_size=5000", "eval_interval=250",
            "eval_episodes=2", "log_interval=100", "checkpoint_interval=250"]
FAST = {"health_check_period_ms": 500, "health_check_failure_threshold": 3, "health_check_initial_delay_ms": 0,
        "health_check_timeout_ms": 1000}


def _attempts(out: Path, trial: str) -> list[str]:
    log = out / "_logs" / f"{trial}.log"
    return [ln for ln in log.read_text().splitlines() if ln.startswith("$ ")] if log.exists() else []


def one_loss(cluster, out: Path) -> dict[str, float]:
    driver = subprocess.Popen([sys.executable, "-m", "softac", "sweep", *SETTINGS, "--address", cluster.address,
                               "--out", str(out)], stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
    evals = out / "seed=0" / "eval.csv"
    while not (evals.exists() and len(evals.read_text().splitlines()) >= 3):
        if driver.poll() is not None:
            raise SystemExit(f"the sweep ended early: {driver.stderr.read()}")
        time.sleep(0.02)
    node_id = _attempts(out, "seed=0")[0].rsplit("node ", 1)[1].split()[0]
    victim = next(n for n in cluster.worker_nodes if n.node_id.startswith(node_id))
    trial_pid = json.loads((out / "seed=0" / ".lock").read_text())["pid"]
    worker_pid = int(Path(f"/proc/{trial_pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
    os.kill(trial_pid, signal.SIGSTOP)
    killed = time.monotonic()
    cluster.remove_node(victim, allow_graceful=False)
    os.kill(worker_pid, signal.SIGKILL)
    os.kill(trial_pid, signal.SIGKILL)
    detect = resume = None
    import threading

    lines: list[str] = []

    def read() -> None:
        nonlocal detect
        for line in driver.stderr:
            lines.append(line)
            if detect is None and "seed=0: lost" in line:
                detect = time.monotonic() - killed

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    while driver.poll() is None:
        if resume is None and len(_attempts(out, "seed=0")) >= 2:
            resume = time.monotonic() - killed
        time.sleep(0.02)
    reader.join(10)
    done = time.monotonic() - killed
    with open(out / "summary.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    lost = sum(r["status"] != "done" for r in rows) if rows else 2
    if driver.returncode != 0 or detect is None or resume is None:
        raise SystemExit(f"unexpected: exit {driver.returncode}, detect {detect}, resume {resume}:\n{''.join(lines)}")
    return {"detect_s": detect, "resume_s": resume, "done_s": done, "trials_lost": lost}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--fast", action="store_true", help="the test suite's health checks, not Ray's defaults")
    args = parser.parse_args()
    os.environ["PYTHONPATH"] = os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])
    os.environ["RAY_kill_child_processes_on_worker_exit"] = "false"
    from ray.cluster_utils import Cluster

    from softac.base.cpus import machine_description

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 0, "include_dashboard": False,
                                                            "_system_config": FAST if args.fast else {}})
    work = Path(tempfile.mkdtemp(prefix="softac-cluster-"))
    results = []
    try:
        for i in range(args.repeats):
            while len(cluster.worker_nodes) < 3:  # two for the trials, one spare for the retry
                cluster.add_node(num_cpus=1)
            cluster.wait_for_nodes(timeout=120)
            results.append(one_loss(cluster, work / f"sweep{i}"))
            print(f"loss {i + 1}: " + ", ".join(f"{k} {v:.1f}" for k, v in results[-1].items()), flush=True)
    finally:
        cluster.shutdown()
        shutil.rmtree(work, ignore_errors=True)
    health = "the test suite's health checks (0.5 s, 3 missed)" if args.fast else "Ray's default health checks"
    print(f"{machine_description()}; {health}; median of {len(results)}: "
          + ", ".join(f"{k} {statistics.median(r[k] for r in results):.1f}" for k in results[0]))


if __name__ == "__main__":
    main()
