"""Goal envs and hindsight experience replay (issue 31): recognition, relabelling by hand, exact resume,
success rates, bad input. The envs are tests/softac_test_envs.py's PointGoal-v0 (a point reaching a goal,
Gymnasium-Robotics' shape) and its variants; Gymnasium-Robotics' own envs are in test_robotics.py."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import assert_clean_error, assert_same_training, load_benchmark_script, run_cli, straight_and_resumed

from softac import SAC
from softac.replay.buffer import ReplayBuffer
from softac.config.sac_config import ConfigError
from softac.errors import SoftacError
from softac.envs.goals import DictLayout
from softac.replay.her_buffer import HerReplayBuffer
from softac.run.csv_logs import read_csv

GOAL_ENV = "softac_test_envs:PointGoal-v0"


def test_a_goal_env_is_recognised_and_gets_a_her_buffer_that_keeps_the_parts_apart(tiny):
    agent = SAC(tiny(GOAL_ENV))
    layout = agent.spaces.layout
    assert agent.spaces.goal_env and layout.keys == ("achieved_goal", "desired_goal", "observation")
    assert (layout.slices["achieved_goal"], layout.slices["desired_goal"], layout.slices["observation"]) == (
        slice(0, 2), slice(2, 4), slice(4, 7))
    agent.learn(60, progress=False)
    buffer = agent.collector.buffer
    assert isinstance(buffer, HerReplayBuffer) and set(buffer.obs) == {"observation", "achieved_goal", "desired_goal"}
    # each stored part is what the env observed: the achieved goal is the position, also in `observation`
    np.testing.assert_array_equal(buffer.obs["achieved_goal"][:60], buffer.obs["observation"][:60, :2])
    np.testing.assert_array_equal(buffer.next_obs["achieved_goal"][:60], buffer.next_obs["observation"][:60, :2])
    # her=off: the plain buffer, the dict flattened as before
    assert type(SAC(tiny(GOAL_ENV, her="off")).collector._make_buffer()) is ReplayBuffer
    assert SAC(tiny(GOAL_ENV, her="on")).collector.her is not None


def test_predict_takes_the_dict_an_env_observes_and_a_dict_of_batches(tiny):
    agent = SAC(tiny(GOAL_ENV))
    env = agent.make_env().unwrapped
    obs, _ = env.reset(seed=3)
    flat = np.concatenate([obs["achieved_goal"], obs["desired_goal"], obs["observation"]])
    np.testing.assert_array_equal(agent.predict(obs), agent.predict(flat))
    batch = {k: np.stack([v, v * 0.5]) for k, v in obs.items()}  # compared with the same batch, flat
    np.testing.assert_array_equal(agent.predict(batch), agent.predict(np.stack([flat, flat * 0.5])))
    with pytest.raises(SoftacError, match="lacks desired_goal"):
        agent.predict({"observation": obs["observation"], "achieved_goal": obs["achieved_goal"]})


def test_a_dict_observation_that_is_no_goal_env_is_flattened_in_its_spaces_key_order(tiny):
    agent = SAC(tiny("softac_test_envs:DictObs-v0"))
    assert not agent.spaces.goal_env and agent.spaces.layout.keys == ("position", "velocity")
    assert agent.collector.her is None
    agent.learn(250, progress=False)
    assert type(agent.collector.buffer) is ReplayBuffer
    np.testing.assert_array_equal(agent.predict({"velocity": [3.0], "position": [0.1]}), agent.predict([0.1, 3.0]))


# ---- relabelling, by hand -------------------------------------------------------------------------------

LAYOUT = DictLayout(("achieved_goal", "desired_goal", "observation"),
                    {"achieved_goal": slice(0, 1), "desired_goal": slice(1, 2), "observation": slice(2, 3)}, 3)


def _reward(achieved, desired):  # 0 within 0.5 of the goal, else -1
    return -(np.abs(achieved[:, 0] - desired[:, 0]) > 0.5).astype(np.float32)


def _buffer(strategy: str, capacity: int = 100) -> HerReplayBuffer:
    """Two envs, written one vector step at a time. Achieved goals after each step (next_obs), desired goal
    of env 0 is 100, of env 1 is 200; `observation` holds 10 * env + episode number, to tell episodes apart.
        env 0: episode A achieves 1, 2, 3 (ends at step 3), then episode C achieves 4, 5 (not finished)
        env 1: episode B achieves 11, 12, 13, 14 (ends at step 4), then episode D achieves 15 (not finished)
    """
    buffer = HerReplayBuffer(capacity, LAYOUT, act_dim=1, n_envs=2, reward_fn=_reward, strategy=strategy, k=1000)
    env0 = [(1, 1, False), (2, 1, False), (3, 1, True), (4, 3, False), (5, 3, False)]
    env1 = [(11, 2, False), (12, 2, False), (13, 2, False), (14, 2, True), (15, 4, False)]
    previous = [0.0, 10.0]
    for (a0, e0, d0), (a1, e1, d1) in zip(env0, env1):
        obs = np.array([[previous[0], 100, 10 * 0 + e0], [previous[1], 200, 10 * 1 + e1]], np.float32)
        next_obs = np.array([[a0, 100, 10 * 0 + e0], [a1, 200, 10 * 1 + e1]], np.float32)
        buffer.add(obs, np.zeros((2, 1)), np.full(2, -1.0), next_obs, np.zeros(2), np.array([d0, d1]))
        previous = [0.0 if d0 else a0, 10.0 if d1 else a1]
    return buffer


def _sampled_transitions(buffer: HerReplayBuffer, n: int = 4000) -> list[tuple[float, float, float, float]]:
    """(episode tag, achieved goal after the step, relabelled desired goal, reward) for each sampled row."""
    batch = buffer.sample(np.random.default_rng(0), n)
    obs, next_obs, rewards = batch["obs"][0], batch["next_obs"][0], batch["rewards"][0]
    np.testing.assert_array_equal(obs[:, 1], next_obs[:, 1])  # obs and next_obs get the same goal
    return [(o[2], no[0], no[1], r) for o, no, r in zip(obs, next_obs, rewards)]


@pytest.mark.parametrize("strategy", ["future", "final", "episode"])
def test_relabelled_goals_come_from_the_same_episode_of_the_same_env_as_the_strategy_says(strategy):
    buffer = _buffer(strategy)
    achieved = {1: [1, 2, 3], 2: [11, 12, 13, 14]}  # finished episodes: tag -> achieved goals in order
    seen: dict[tuple[int, float], set[float]] = {}
    for tag, ach, goal, reward in _sampled_transitions(buffer):
        if tag in (13.0, 14.0, 3.0, 4.0):  # episodes C and D are not finished: never relabelled
            assert goal in (100.0, 200.0) and reward == -1.0
            continue
        episode = achieved[1 if tag < 10 else 2]
        t = episode.index(ach)
        if goal in (100.0, 200.0):  # kept its own goal (1 in her_k + 1 = 1001 rows)
            continue
        assert goal in episode, (tag, ach, goal)  # never another episode's, never another env's
        if strategy == "future":
            assert episode.index(goal) >= t
        elif strategy == "final":
            assert goal == episode[-1]
        assert reward == (0.0 if abs(ach - goal) <= 0.5 else -1.0)  # the env's reward for the new goal
        seen.setdefault((tag, ach), set()).add(goal)
    # every allowed goal turns up (4000 draws over 7 rows): future from t on, episode anywhere, final the end
    for (tag, ach), goals in seen.items():
        episode = achieved[1 if tag < 10 else 2]
        t = episode.index(ach)
        expected = {"future": set(episode[t:]), "final": {episode[-1]}, "episode": set(episode)}[strategy]
        assert goals == set(map(float, expected)), (strategy, tag, ach, goals)
    assert len(seen) == 7


def test_about_her_k_in_her_k_plus_one_sampled_rows_of_finished_episodes_are_relabelled():
    buffer = HerReplayBuffer(100, LAYOUT, 1, 2, _reward, "final", k=3)
    for t in range(20):  # episodes of 5 steps on both envs, goals 100 and 200 never achieved
        obs = np.array([[t, 100, 0], [t, 200, 1]], np.float32)
        buffer.add(obs, np.zeros((2, 1)), np.full(2, -1.0), obs + [1, 0, 0], np.zeros(2), np.full(2, t % 5 == 4))
    goals = buffer.sample(np.random.default_rng(1), 4000)["obs"][0, :, 1]
    share = np.mean((goals != 100) & (goals != 200))
    assert abs(share - 0.75) < 0.03, share  # binomial(4000, 0.75): std 0.007


def test_episodes_partly_overwritten_in_the_ring_never_lend_another_episodes_goal():
    """A ring of 6 rows over 2 envs holds 3 steps of each: episodes of 4 steps lose their first rows."""
    buffer = HerReplayBuffer(6, LAYOUT, 1, 2, _reward, "episode", k=1000)
    for step in range(11):
        t = step % 4
        obs = np.array([[0, 100, step // 4], [0, 200, 10 + step // 4]], np.float32)
        next_obs = np.array([[100 * (step // 4) + t, 100, step // 4], [1000 + 100 * (step // 4) + t, 200, 10 + step // 4]],
                            np.float32)
        buffer.add(obs, np.zeros((2, 1)), np.zeros(2), next_obs, np.zeros(2), np.full(2, t == 3))
    for tag, ach, goal, _ in _sampled_transitions(buffer, 2000):
        if goal not in (100.0, 200.0):
            assert goal // 100 == ach // 100, (tag, ach, goal)  # the same episode's achieved goal


# ---- training with HER ------------------------------------------------------------------------------

@pytest.mark.exact
@pytest.mark.parametrize("strategy,workers,random_prob", [("future", 0, 0.0), ("episode", 2, 0.3)])
def test_resume_with_her_is_exact(tiny, tmp_path, strategy, workers, random_prob):
    """N+M steps equal N, checkpoint, load, M: the episodes' bookkeeping is in the checkpoint (two envs,
    episodes of 20 steps, the split mid-episode), in-process and in env workers, and with random actions
    mixed in (their numbers come from the run's saved generator)."""
    cfg = tiny(GOAL_ENV, n_envs=2, gradient_steps=2, eval_interval=300, her_strategy=strategy, env_workers=workers,
               random_action_prob=random_prob)
    straight, resumed = straight_and_resumed(cfg, tmp_path, 510, 390)
    assert_same_training(straight, resumed)
    for name in ("eval.csv", "episodes.csv"):
        assert (tmp_path / "straight" / name).read_text() == (tmp_path / "split" / name).read_text(), name


@pytest.mark.exact
def test_env_workers_train_a_goal_env_as_in_process_envs_do(tiny):
    cfg = tiny(GOAL_ENV, n_envs=3, gradient_steps=1)
    a, b = SAC(cfg), SAC(cfg.replace(env_workers=3))
    a.learn(400, progress=False)
    b.learn(400, progress=False)
    assert_same_training(a, b)


def test_success_rates_in_every_log_and_the_summary(tiny, tmp_path):
    agent = SAC(tiny(GOAL_ENV, eval_interval=100, eval_episodes=3, log_interval=100))
    summary = agent.learn(300, run_dir=tmp_path / "run", progress=False)
    episodes, evals, progress = (read_csv(tmp_path / "run" / f) for f in ("episodes.csv", "eval.csv", "progress.csv"))
    assert len(episodes) == 15 and all(row["success"] in ("0", "1") for row in episodes)
    assert len(evals) == 3 and all(0.0 <= float(row["success_rate"]) <= 1.0 for row in evals)
    last_twenty = [float(row["success"]) for row in episodes[-15:]]
    assert float(progress[-1]["success_rate"]) == pytest.approx(np.mean(last_twenty))
    assert summary["last_success"] == float(evals[-1]["success_rate"])
    # an env that reports no success keeps those columns empty
    SAC(tiny(eval_interval=100, eval_episodes=2)).learn(200, run_dir=tmp_path / "drift", progress=False)
    assert {row["success_rate"] for row in read_csv(tmp_path / "drift" / "eval.csv")} == {""}
    assert {row["success"] for row in read_csv(tmp_path / "drift" / "episodes.csv")} == {""}


def test_a_run_written_before_the_success_columns_resumes_with_its_own_header(tiny, tmp_path):
    """progress.csv, episodes.csv and eval.csv of an older run keep their columns (and rows) on resume."""
    run = tmp_path / "run"
    SAC(tiny(eval_interval=100, log_interval=100)).learn(200, run_dir=run, progress=False)
    for name, extra in (("progress.csv", ",success_rate"), ("episodes.csv", ",success"), ("eval.csv", ",success_rate")):
        path = run / name
        lines = path.read_text().splitlines()
        assert lines[0].endswith(extra)
        path.write_text("\n".join([lines[0][: -len(extra)]] + [line.rsplit(",", 1)[0] for line in lines[1:]]) + "\n")
    agent = SAC.load(run, which="last")
    agent.learn(200, run_dir=run, progress=False)
    rows = read_csv(run / "eval.csv")
    assert [int(r["step"]) for r in rows] == [100, 200, 300, 400] and "success_rate" not in rows[0]


@pytest.mark.slow
def test_her_learns_to_reach_goals_that_plain_replay_does_not_in_the_same_steps(tiny):
    """PointGoal-v0's sparse reward: with HER the deterministic policy reaches at least 80% of 20 goals
    within 3000 steps (measured: 0.9-1.0 over seeds 0-2); without it the point rarely finds a goal."""
    results = {}
    for her in ("on", "off"):
        agent = SAC(tiny(GOAL_ENV, her=her, hidden_sizes=[64, 64], batch_size=64, buffer_size=100_000,
                         eval_interval=500, eval_episodes=20))
        results[her] = agent.learn(3000, progress=False, target_success=0.95 if her == "on" else None)
    assert results["on"]["last_success"] >= 0.8, results["on"]
    assert results["off"]["last_success"] <= 0.5, results["off"]


# ---- bad input ------------------------------------------------------------------------------------

def test_her_on_a_non_goal_env_and_conflicting_settings_are_refused_in_one_line(tiny):
    with pytest.raises(SoftacError, match=r"her=on needs a goal env .* observes a 2-value vector"):
        SAC(tiny(her="on"))
    with pytest.raises(SoftacError, match=r"her=on needs a goal env .* observes \('position', 'velocity'\)"):
        SAC(tiny("softac_test_envs:DictObs-v0", her="on"))
    with pytest.raises(SoftacError, match="n_step=3 cannot be combined with HER"):
        SAC(tiny(GOAL_ENV, n_step=3))
    with pytest.raises(SoftacError, match="buffer_obs_once cannot be combined with HER"):
        SAC(tiny(GOAL_ENV, buffer_obs_once=True))
    with pytest.raises(ConfigError, match="her_strategy='nearest': must be future, final or episode"):
        tiny(GOAL_ENV, her_strategy="nearest")
    with pytest.raises(ConfigError, match="her='maybe': must be auto, on or off"):
        tiny(GOAL_ENV, her="maybe")
    assert tiny(GOAL_ENV, her=True).her == "on" and tiny(GOAL_ENV, her=False).her == "off"


def test_cli_goal_env_bad_input_exits_2_in_one_line(tmp_path):
    cases = [
        (["--env", "softac_test_envs:OneGoalReward-v0"], "compute_reward does not accept a batch of goals"),
        (["--env", "softac_test_envs:Drift-v0", "--set", "her=on"], "her=on needs a goal env"),
        (["--env", GOAL_ENV, "--set", "her_strategy=nearest"], "her_strategy='nearest'"),
        (["--env", GOAL_ENV, "--target-success", "1.5"], "--target-success is a success rate in (0, 1]"),
    ]
    for i, (args, message) in enumerate(cases):
        assert_clean_error(run_cli("train", *args, "--steps", "50", "--out", str(tmp_path / f"r{i}")), message)
        assert not (tmp_path / f"r{i}").exists()


def test_cli_target_success_stops_training_and_eval_reports_the_success_rate(tmp_path):
    run = tmp_path / "run"
    args = ["train", "--env", GOAL_ENV, "--steps", "4000", "--out", str(run), "--target-success", "0.1",
            "--set", "hidden_sizes=64,64", "batch_size=64", "learning_starts=200", "eval_interval=200",
            "eval_episodes=10", "--no-progress"]
    result = run_cli(*args)
    assert result.returncode == 0, result.stderr
    summary = json.loads((run / "summary.json").read_text())
    assert summary["stop_reason"] == "target_success" and summary["last_success"] >= 0.1
    assert summary["steps"] < 4000 and "success rate" in result.stderr and "(target reached)" in result.stderr
    result = run_cli("eval", str(run), "--episodes", "5", "--json")
    assert result.returncode == 0, result.stderr
    stats = json.loads(result.stdout)
    assert 0.0 <= stats["success_rate"] <= 1.0 and len(stats["successes"]) == 5
    assert stats["success_rate"] == np.mean(stats["successes"])


def test_exported_policies_of_a_goal_env_take_the_dict(tiny, tmp_path):
    """policy.npz's forward pass takes the dict (one, or a dict of batches); the ONNX graph one input per key."""
    import onnxruntime

    from softac.outputs.export import export_policy
    from softac.learner.numpy_forward import policy_forward

    agent = SAC(tiny(GOAL_ENV))
    agent.learn(250, progress=False)
    env = agent.make_env().unwrapped
    observations = [env.reset(seed=s)[0] for s in range(5)]
    batch = {k: np.stack([o[k] for o in observations]) for k in observations[0]}
    expected = agent.predict(batch)
    with np.load(export_policy(agent, tmp_path / "policy.npz", "numpy")) as npz:
        params = dict(npz)
    assert list(params["obs_keys"]) == ["achieved_goal", "desired_goal", "observation"]
    np.testing.assert_allclose(policy_forward(params, batch), expected, atol=1e-5)
    np.testing.assert_allclose(policy_forward(params, observations[0]), expected[0], atol=1e-5)
    session = onnxruntime.InferenceSession(str(export_policy(agent, tmp_path / "policy.onnx", "onnx")),
                                           providers=["CPUExecutionProvider"])
    assert [i.name for i in session.get_inputs()] == ["achieved_goal", "desired_goal", "observation"]
    np.testing.assert_allclose(session.run(["action"], batch)[0], expected, atol=1e-5)


def test_sweep_summaries_give_success_rates_and_the_steps_to_reach_one(tmp_path):
    from softac import sweep

    spec = sweep.SweepSpec(env_id=GOAL_ENV, steps=300, seeds=[0, 1])
    sweep.prepare_out_dir(tmp_path / "sweep", spec)
    for seed, rates in ((0, ("0.1", "0.95", "0.9")), (1, ("0.0", "0.5", "0.92"))):
        run = tmp_path / "sweep" / f"seed={seed}"
        run.mkdir(parents=True)
        (run / "config.yaml").write_text(f"seed: {seed}\n")
        (run / "eval.csv").write_text("step,mean_return,std_return,episodes,success_rate\n" + "".join(
            f"{100 * (i + 1)},-{10 - i},0,10,{rate}\n" for i, rate in enumerate(rates)))
        (run / "progress.csv").write_text("step,time_s\n100,1.0\n300,3.0\n")
    rows = sweep.trial_rows(tmp_path / "sweep", spec, success_threshold=0.9)
    assert [(r["final_success"], r["best_success"], r["steps_to_success"], r["seconds_to_success"]) for r in rows] == [
        (0.9, 0.95, 200, 2.0), (0.92, 0.92, 300, 3.0)]
    table = sweep.markdown_table(sweep.aggregate(rows, [], None, name="softac"), None, 0.9)
    assert "| final success rate (mean) | reached success 0.9 | median steps to it |" in table
    assert "| 0.91 | 2/2 | 250 |" in table
    files = sweep.write_summaries(tmp_path / "sweep", spec)
    assert "steps_to_success" in (tmp_path / "sweep" / "summary.csv").read_text().splitlines()[0]
    assert any(f.name == "success_comparison.png" for f in files)


def test_plots_and_the_report_of_a_goal_env_run_show_its_success_rate(tiny, tmp_path):
    from softac.outputs.plots import plot_runs
    from softac.outputs.report import build_report

    runs = []
    for seed in (0, 1):
        runs.append(tmp_path / f"run{seed}")
        SAC(tiny(GOAL_ENV, seed=seed, eval_interval=100, eval_episodes=2)).learn(200, run_dir=runs[-1], progress=False)
    assert "success.png" in [p.name for p in plot_runs(runs[:1])]
    assert "success_comparison.png" in [p.name for p in plot_runs(runs, tmp_path / "both")]
    page = build_report(runs[0]).read_text()
    assert "last success rate" in page and "<th>success rate</th>" in page and "alt='Success rate'" in page


def test_goal_movement_script_measures_each_complete_episode_by_hand():
    """benchmarks/goal_movement.py (docs/results-notes.md, FetchPush): how far each episode moved its achieved goal.
    Two envs' rows interleave; an episode whose first step was overwritten, and one still running, are left out."""
    script = load_benchmark_script("goal_movement")
    #            ep 5 (start overwritten)  ep 6: moves 0.05 at t=1, back to 0.01   ep 7: still   ep 8: running
    episode = np.array([5, 6, 5, 6, 7, 6, 7, 8, 8])
    t = np.array([1, 0, 2, 1, 0, 2, 1, 0, 1])
    done = np.array([0, 0, 1, 0, 0, 1, 1, 0, 0], bool)
    start = np.zeros((9, 3), np.float32)
    start[[3, 5]] = [0.03, 0.04, 0.0]  # ep 6's obs at t=1, 2: where t=0 and t=1 left it
    moved_to = start.copy()
    moved_to[1], moved_to[3], moved_to[5] = [0.03, 0.04, 0.0], [0.006, 0.008, 0.0], [0.006, 0.008, 0.0]
    moved_to[[0, 2]] = [1.0, 1.0, 1.0]  # ep 5 moved far, but from a start the buffer no longer holds
    moved_to[[7, 8]] = [1.0, 1.0, 1.0]  # ep 8 moves far but has not ended
    buffer = {"pos_size": np.array([9, 9, 9]), "episode": episode, "t": t, "done": done,
              "obs.achieved_goal": start + 2.0, "next_obs.achieved_goal": moved_to + 2.0}
    ids, farthest = script.movement_by_episode(buffer)
    assert ids.tolist() == [6, 7]
    np.testing.assert_allclose(farthest, [0.05, 0.0], atol=1e-6)
    rows = script.shares_by_block(farthest, ids, block=1, thresholds=[0.01, 0.05])
    assert rows == [{"first_episode": 6, "last_episode": 6, "episodes": 1, "moved_over_0.01": 1.0,
                     "moved_over_0.05": 0.0},  # 0.05 is not farther than 0.05
                    {"first_episode": 7, "last_episode": 7, "episodes": 1, "moved_over_0.01": 0.0,
                     "moved_over_0.05": 0.0}]


def test_goal_movement_script_reads_a_trained_runs_buffer_and_refuses_one_without_goals(tiny, tmp_path, capsys):
    script = load_benchmark_script("goal_movement")
    SAC(tiny(GOAL_ENV)).learn(300, run_dir=tmp_path / "run", progress=False)
    capsys.readouterr()
    assert script.main([str(tmp_path / "run"), "--block", "10", "--thresholds", "0", "100", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    episodes = read_csv(tmp_path / "run" / "episodes.csv")
    assert sum(row["episodes"] for row in rows) == len(episodes) == 15  # 20-step episodes, all complete
    assert [row["episodes"] for row in rows] == [10, 5]
    assert all(row["moved_over_0"] == 1.0 and row["moved_over_100"] == 0.0 for row in rows)  # the point moves
    SAC(tiny()).learn(100, run_dir=tmp_path / "drift", progress=False)
    capsys.readouterr()
    assert script.main([str(tmp_path / "drift")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "holds no goal env's replay buffer" in err
    assert script.main([str(tmp_path / "nothing")]) == 2 and "no such run" in capsys.readouterr().err
