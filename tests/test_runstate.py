"""The run state as one unit: saved and restored whole, older checkpoints still load, a run stopped during an
evaluation evaluates first when resumed."""

import numpy as np
import pytest

from softac.run.run_state import RunState


def test_run_state_round_trips_through_its_checkpoint_parts(tmp_path):
    state = RunState.new(seed=3)
    state.num_steps, state.num_episodes, state.train_time_s = 1200, 14, 31.5
    state.best_eval, state.best_step, state.last_eval, state.last_eval_step = 90.0, 1000, 80.0, 1200
    state.recent_returns = [1.0, 2.5]
    state.rng.uniform(size=5)  # advance the stream: the restored one must continue from here
    meta, arrays = state.checkpoint_parts()

    last = tmp_path / "run" / "checkpoints" / "last"
    restored = RunState.new(seed=0)
    restored.restore(meta, arrays, last)
    for name in ("num_steps", "num_episodes", "train_time_s", "best_eval", "best_step", "last_eval",
                 "last_eval_step", "recent_returns"):
        assert getattr(restored, name) == getattr(state, name), name
    np.testing.assert_array_equal(np.asarray(restored.act_key), np.asarray(state.act_key))
    np.testing.assert_array_equal(np.asarray(restored.predict_key), np.asarray(state.predict_key))
    assert restored.rng.uniform() == state.rng.uniform()
    # restored from a run's checkpoints/last, it is that run's latest state; from anywhere else, of no run
    assert restored.run_dir == (tmp_path / "run").resolve() and restored.restored_from == last.resolve()
    elsewhere = RunState.new(seed=0)
    elsewhere.restore(meta, arrays, tmp_path / "run" / "checkpoints" / "best")
    assert elsewhere.run_dir is None


def test_a_checkpoint_from_before_the_run_state_loads():
    """Checkpoints written before RunState kept only the trainer keys that had been set."""
    state = RunState.new(seed=1)
    meta, arrays = state.checkpoint_parts()
    meta["trainer"] = {"best_eval": None, "last_eval": None}
    del meta["train_time_s"]
    restored = RunState.new(seed=2)
    restored.restore(meta, arrays)
    assert (restored.best_step, restored.last_eval_step, restored.recent_returns, restored.train_time_s) == \
        (None, None, [], 0.0)


@pytest.mark.parametrize("steps", [200, 400], ids=["final", "mid-run"])
def test_a_run_stopped_during_an_evaluation_evaluates_first_when_resumed(tmp_path, steps):
    """SIGTERM during an evaluation (the first, at step 200: the last one when the run has 200 steps, else one in
    the middle): the evaluation is cut short, the run checkpoints at that step and exits 130; the resumed segment
    evaluates at that step before going on (also when it has no steps left), so eval.csv is an undisturbed run's.
    A sweep's driver killed as a trial ended, or as a trial evaluated, left runs without that row."""
    import signal
    import subprocess
    import sys
    import time

    from conftest import child_env, run_cli

    args = ["train", "--env", "softac_test_envs:Slow-v0", "--seed", "0", "--steps", str(steps), "--no-progress", "--set",
            "hidden_sizes=[16,16]", "batch_size=32", "learning_starts=100", "eval_interval=200", "eval_episodes=2",
            "checkpoint_interval=200"]
    run = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "softac", *args, "--out", str(run)], stderr=subprocess.PIPE,
                            text=True, env=child_env(SOFTAC_TEST_STOP_IN_EVAL="1"))
    try:
        deadline = time.monotonic() + 300
        while open(f"/proc/{proc.pid}/stat").read().rsplit(")", 1)[1].split()[0] != "T":  # stopped in the eval
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        proc.send_signal(signal.SIGCONT)
        stderr = proc.communicate(timeout=120)[1]
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, stderr
    assert (run / "eval.csv").read_text().count("\n") == 1  # the header only: no evaluation finished
    resumed = run_cli("train", "--resume", str(run), "--no-progress")
    assert resumed.returncode == 0, resumed.stderr
    single = run_cli(*args, "--out", str(tmp_path / "single"))
    assert single.returncode == 0, single.stderr
    assert (run / "eval.csv").read_text() == (tmp_path / "single" / "eval.csv").read_text()
    assert (run / "eval.csv").read_text().count("\n") == 1 + steps // 200
