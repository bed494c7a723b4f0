"""The metrics a run logs (issue 42): each progress row holds the mean of each metric over the gradient steps of
its interval that computed it, the actor's over actor steps only; a row whose interval had no actor step leaves
the actor's cells empty rather than showing a placeholder 0."""

import math

import numpy as np
import pytest

from softac import SAC
from softac.learner import build
from softac.config.sac_config import SACConfig
from softac.run.csv_logs import read_csv
from softac.learner.metrics import metric_means

from conftest import straight_and_resumed
from test_sac_math import _batch

POLICY_COLUMNS = ("actor_loss", "alpha_loss", "log_prob_mean")
CRITIC_COLUMNS = ("critic_loss", "alpha", "q1_mean", "q2_mean")


def test_totals_over_several_calls_are_the_mean_of_each_calls_steps():
    """Three calls of one gradient step under policy_delay 3: the critic's metrics average all three steps, the
    actor's come from the one step that updated it (the third), and a call without an actor step adds none."""
    # alpha 0.5: at alpha 1 (log alpha 0) the alpha loss is 0 itself
    cfg = SACConfig().replace(hidden_sizes=[16], batch_size=8, policy_delay=3, alpha=0.5)
    fns = build.build(cfg, 3, 2)
    batches = [_batch(np.random.default_rng(seed), 1, 8, 3, 2) for seed in range(3)]

    state, per_call = fns.init(0), []
    for b in batches:  # each call's own totals
        state, totals = fns.update(state, b)
        per_call.append({k: float(v) for k, v in totals.items()})
    assert [t["critic_steps"] for t in per_call] == [1.0, 1.0, 1.0]
    assert [t["actor_steps"] for t in per_call] == [0.0, 0.0, 1.0]
    assert metric_means(per_call[0]).keys() == set(CRITIC_COLUMNS)  # no actor step: no actor metrics at all

    state, totals = fns.init(0), None
    for b in batches:  # the same steps, summed across calls
        state, totals = fns.update(state, b, totals)
    means = metric_means(totals)
    # float32 sums of three terms, then one division: a few roundings of the terms' size
    for name in CRITIC_COLUMNS:
        expected = sum(t[name] for t in per_call) / 3
        assert means[name] == pytest.approx(expected, rel=1e-6, abs=1e-7), name
    for name in POLICY_COLUMNS:
        assert means[name] == per_call[2][name] != 0.0, name


def _progress(run):
    return read_csv(run / "progress.csv")


def _actor_step_after(step: int, learning_starts: int, delay: int) -> bool:
    """Did the update made after collecting env step `step` (n envs = 1, one gradient step each) update the
    actor? The k-th update (k = step - learning_starts + 1) does when k is a multiple of the delay."""
    k = step - learning_starts + 1
    return k >= 1 and k % delay == 0


def test_rows_under_policy_delay_hold_interval_means_and_no_placeholders(tiny, tmp_path):
    """log_interval 2 under policy_delay 3: a row's actor cells are empty exactly where neither of its two
    updates stepped the actor, and filled (never 0) where one did; critic cells are filled once learning
    started. A second run with log_interval 100 fills every learning row."""
    delay, starts = 3, 200
    agent = SAC(tiny(policy_delay=delay, log_interval=2, learning_starts=starts, alpha=0.5))
    agent.learn(260, run_dir=tmp_path / "fine", progress=False)
    rows = _progress(tmp_path / "fine")
    assert rows, "no progress rows"
    for row in rows:
        step = int(row["step"])
        learned = step >= starts
        for name in CRITIC_COLUMNS:
            assert (row[name] != "") == learned, (step, name, row[name])
        stepped = any(_actor_step_after(s, starts, delay) for s in (step - 1, step))
        for name in POLICY_COLUMNS:
            assert (row[name] != "") == stepped, (step, name, row[name])
            if stepped:
                assert float(row[name]) != 0.0 and math.isfinite(float(row[name])), (step, name)

    agent = SAC(tiny(policy_delay=delay, log_interval=100, learning_starts=starts, alpha=0.5))
    agent.learn(600, run_dir=tmp_path / "coarse", progress=False)
    learning_rows = [r for r in _progress(tmp_path / "coarse") if int(r["step"]) > starts]
    assert len(learning_rows) == 4
    for row in learning_rows:
        assert all(row[name] not in ("", "0", "0.0") for name in POLICY_COLUMNS + CRITIC_COLUMNS), row


@pytest.mark.exact
def test_a_run_resumed_between_rows_logs_the_rows_of_a_straight_run(tiny, tmp_path):
    """The sums behind the next row travel in the checkpoint: a run stopped at 550 (rows every 100) and resumed
    logs at 600 what a straight run logs there, bit for bit."""
    cfg = tiny(policy_delay=3, total_steps=800)
    straight_and_resumed(cfg, tmp_path, 550, 250)
    columns = ("step", *CRITIC_COLUMNS, *POLICY_COLUMNS)
    rows_a, rows_b = ([{k: row[k] for k in columns} for row in _progress(tmp_path / run)] for run in ("straight", "split"))
    assert [r["step"] for r in rows_a] == [str(step) for step in range(100, 900, 100)]
    assert rows_a == rows_b


def test_every_metric_is_a_progress_column_and_a_plot():
    """The update's metrics are named once (learner/metrics.py): progress.csv has a column for each, in that
    order, and the metric grid (softac plot, softac.show) draws each."""
    from softac.learner.metrics import CRITIC_METRICS, METRICS, POLICY_METRICS
    from softac.outputs.plots import METRIC_GRID
    from softac.run.csv_logs import PROGRESS_COLUMNS

    assert [c for c in PROGRESS_COLUMNS if c in METRICS] == list(METRICS)
    assert set(CRITIC_METRICS) | set(POLICY_METRICS) == set(METRICS)
    drawn = {name for column, _ in METRIC_GRID for name in ((column,) if isinstance(column, str) else column)}
    assert drawn == set(METRICS)
