"""The run directories of softac and of its peers (`softac sweep --framework sb3|sbx`) give their shared columns
one meaning, so tables and plots compare like with like: progress.csv's `return_mean` is the mean return of
the last 20 training episodes (the peers used 100), `fps` is env steps per second since the previous row
(the peers gave the cumulative rate), `time_s` the run's seconds so far. The peer is a stand-in
(tests/fake_peers) driven through softac's real adapter (softac.peers.peer_run)."""

import subprocess
import sys

import numpy as np
import pytest

from conftest import TESTS, child_env, run_cli
from softac.logs import RECENT_EPISODES, read_csv

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
    run = tmp_path / "peer"
    r = subprocess.run([sys.executable, "-m", "softac.peers", "run", "sbx", "--env", DRIFT, "--seed", "0", "--steps",
                        "700", "--out", str(run), "--eval-interval", "200", "--eval-episodes", "2", "--log-interval",
                        "100"], capture_output=True, text=True, timeout=300, env=child_env(FAKE_PEERS))
    assert r.returncode == 0, r.stderr
    # each 100-step interval takes >= 0.1 s in the stand-in, and those with an evaluation >= 0.05 s more: a
    # cumulative rate (what the peers wrote before) is off from theirs by far more than the rounding allows
    assert_progress_columns_mean_what_softac_means(run, min_interval_s=0.1)
    assert [int(row["step"]) for row in read_csv(run / "eval.csv")] == [200, 400, 600, 700]
    assert (run / ".lock").exists()  # written under the run lock, as softac's runs are


def test_a_softac_run_writes_the_same_columns(tmp_path):
    run = tmp_path / "softac"
    r = run_cli("train", "--env", "softac_test_envs:Slow-v0", "--steps", "700", "--out", str(run), "--no-progress",
                "--set", "hidden_sizes=16,16", "batch_size=16", "learning_starts=100", "eval_interval=200",
                "eval_episodes=2", "log_interval=100")
    assert r.returncode == 0, r.stderr
    assert_progress_columns_mean_what_softac_means(run, min_interval_s=0.1)  # Slow-v0: >= 2 ms a step
