"""Training with the envs on the device (issue 67): MuJoCo Playground's envs collected N at a time inside the
update's jit by default, the training loop's host work between chunks, exact resume mid-episode (the envs' state
pytree, the device's replay buffer, the keys), and the settings it does not run yet refused in one line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import assert_clean_error, assert_same_learner, assert_same_run_state, run_cli, tiny_config
from softac.config.sac_config import SACConfig
from softac.errors import ConfigError
from softac.run.csv_logs import read_csv

ENV = "playground:CartpoleSwingup"


def device_config(**extra) -> SACConfig:
    # action repeat 10: 100-step episodes, so that some end inside a short test; obs_norm and reward_scale, whose
    # running statistics the chunks carry
    return tiny_config(ENV, **{**dict(n_envs=4, action_repeat=10, learning_starts=200, buffer_size=2000,
                                      obs_norm=True, reward_scale="std"), **extra})


def test_the_device_choice_and_what_it_refuses():
    assert device_config().collects_on_device
    assert not device_config(collect_on="host").collects_on_device
    assert not tiny_config("Pendulum-v1").collects_on_device
    assert device_config(n_envs=4096).n_envs == 4096  # vmapped arrays: thousands of envs
    with pytest.raises(ConfigError, match=r"n_envs=4096: must be <= 1024 \(more envs: MuJoCo Playground's"):
        device_config(n_envs=4096, collect_on="host")
    with pytest.raises(ConfigError, match="collect_on='device': device collection steps MuJoCo Playground's envs"):
        tiny_config("Pendulum-v1", collect_on="device")
    with pytest.raises(ConfigError, match="pixels=True: is not run by device collection yet"):
        device_config(pixels=True, obs_norm=False)
    for mode in ("mix", "prefill"):  # offline data mixed into each batch, or the replay's first rows (tests below)
        assert device_config(offline_data="runs/x", offline_mode=mode).offline_mode == mode
    assert device_config(n_step=3).n_step == 3  # n-step returns on the device (test_device_envs)


def resumed_as_straight(cfg: SACConfig, tmp_path, first: int, then: int) -> tuple:
    """N + M == N+M on the device: an agent trained first + then env steps in one go, and one trained `first`,
    loaded from its last checkpoint (a device collector again) and trained `then` more, alike in their learner,
    run state, checkpoint meta and every array of their replay and envs. Returns (straight, resumed, arrays)."""
    from softac import SAC

    straight = SAC(cfg)
    straight.learn(first + then, run_dir=tmp_path / "straight", progress=False)
    SAC(cfg).learn(first, run_dir=tmp_path / "split", progress=False)
    resumed = SAC.load(tmp_path / "split", which="last")
    assert resumed.num_steps == first and type(resumed.collector).__name__ == "DeviceCollector"
    resumed.learn(then, run_dir=tmp_path / "split", progress=False)
    assert_same_learner(straight, resumed)
    assert_same_run_state(straight, resumed)
    (meta_a, arrays_a), (meta_b, arrays_b) = (agent.collector.checkpoint_parts(True) for agent in (straight, resumed))
    assert meta_a == meta_b and arrays_a.keys() == arrays_b.keys()
    for name in arrays_a:
        np.testing.assert_array_equal(arrays_a[name], arrays_b[name], err_msg=name)
    return straight, resumed, arrays_a


pytestmark = pytest.mark.playground


@pytest.fixture(scope="module", autouse=True)
def _playground():
    pytest.importorskip("mujoco_playground")


@pytest.mark.exact
def test_a_device_run_resumes_exactly_mid_episode(tmp_path):
    """N + M == N+M: 320 + 280 env steps against 600 in one go, the split inside the envs' second episodes and
    inside a chunk of the straight run; the episodes that ended are logged alike. The warm-up acts with the initial
    policy (warmup_actions policy, Brax's prefill), whose zeroed head and std under e^-8 keep its actions near 0,
    but for the half of the rows that random_action_prob makes uniform. Pink exploration noise: its sequences and
    positions carried across the split in the run state."""
    cfg = device_config(warmup_actions="policy", zero_actor_head=True, log_std_max=-8.0, random_action_prob=0.5,
                        exploration_noise="pink", noise_sequence_length=100)
    straight, resumed, arrays_a = resumed_as_straight(cfg, tmp_path, 320, 280)
    assert len(arrays_a["buffer/rewards"]) == 600
    # the pink noise the chunks stepped: every env 50 agent steps into its second episode and sequence
    assert list(straight.run_state.noise.position) == [50] * 4
    warm = np.abs(arrays_a["buffer/actions"][:200, 0])
    policy_rows = warm < 0.01  # a uniform action lands there with probability 0.01
    assert 0.35 < policy_rows.mean() < 0.65 and warm[~policy_rows].max() > 0.9, policy_rows.mean()
    episodes = [read_csv(tmp_path / run / "episodes.csv") for run in ("straight", "split")]
    assert episodes[0] == episodes[1] and [int(float(e["length"])) for e in episodes[0]] == [100] * 4
    assert straight.num_episodes == resumed.num_episodes == 4
    assert straight.learner.obs_norm.count == 600  # every observation acted on, the warm-up's too
    np.testing.assert_array_equal(straight.learner.obs_norm.m2, resumed.learner.obs_norm.m2)

    # reward_scale: the chunks' running returns are the host's RunningReturnScale fed the same rewards (the replay's
    # rows, vector step by vector step) and episode ends (every env's at its 100th step), to float32's rounding
    from softac.learner.normalization import RunningReturnScale

    host = RunningReturnScale(4, cfg.gamma, "std", cfg.v_max)
    rewards = arrays_a["buffer/rewards"].reshape(150, 4)
    for t, row in enumerate(rewards):
        host.update(row, np.full(4, t == 99))
    device = straight.learner.return_scale
    assert device.stats.count == host.stats.count == 600 and device.max_abs == pytest.approx(host.max_abs, rel=1e-5)
    np.testing.assert_allclose(device.returns, host.returns, rtol=1e-5)
    assert device.scale == pytest.approx(host.scale, rel=1e-4) and device.scale != 1.0
    assert resumed.learner.return_scale.scale == device.scale

    # evaluation on the device: all episodes at once, deterministic, each counted to its end (100 agent steps)
    from softac.run.device_transitions import device_episodes
    from softac.run.evaluation import summarize

    a, b = (summarize(*device_episodes(agent.learner, agent.collector, 3, seed=7)) for agent in (straight, resumed))
    assert a == b and a["episodes"] == 3 and a["lengths"] == [100] * 3 and len(set(a["returns"])) == 3


@pytest.mark.exact
def test_a_device_run_storing_each_observation_once_resumes_exactly(tmp_path):
    """buffer_obs_once on the device: 240 + 160 env steps against 400, the 200-row replay past full (its oldest
    rows invalid, the episodes' final observations in the side ring), the learner, the replay's arrays and the
    envs alike; the checkpoint keeps one observation array. With 3-step returns, walked over the obs-once rows,
    and FlashSAC's held exploration noise (its hold carried across the split in the run state)."""
    cfg = device_config(buffer_obs_once=True, buffer_size=200, learning_starts=120, n_step=3,
                        exploration_noise="repeat")
    straight, _, arrays_a = resumed_as_straight(cfg, tmp_path, 240, 160)
    assert "buffer/next_obs" not in arrays_a
    # the 400th env step ends every env's 100-step episode: their final observations are the ring's 4, and no
    # successor was written over the oldest rows, so all 200 rows can be drawn
    assert len(arrays_a["buffer/valid"]) == 200 and arrays_a["buffer/valid"].all()
    assert sorted(arrays_a["buffer/final_owner"][arrays_a["buffer/final_owner"] >= 0]) == [196, 197, 198, 199]
    assert straight.run_state.noise.count >= 1 and np.any(straight.run_state.noise.noise != 0)


@pytest.fixture(scope="module")
def host_run(tmp_path_factory):
    """A host-collected Playground run of 400 env steps (4 envs, no update): its replay is the offline data below."""
    from softac import SAC

    run = tmp_path_factory.mktemp("device-offline") / "source"
    SAC(device_config(collect_on="host", learning_starts=400)).learn(400, run_dir=run, progress=False)
    return run


def test_a_device_run_prefilled_with_offline_data_starts_from_its_rows(host_run):
    """offline_mode prefill on the device: the dataset's transitions are the replay's first rows, then the envs'
    follow; written a vector step (4 rows) at a time, a dataset of 398 rows gives 396 and says so in one line."""
    import dataclasses

    from softac import SAC

    agent = SAC(device_config(offline_data=str(host_run), offline_mode="prefill", learning_starts=0))
    agent.learn(40, progress=False)
    rows, data = agent.collector.replay_rows(), agent.collector.offline
    assert len(rows["rewards"]) == 440 and int(rows["position"]) == 440 and agent.collector.offline_device is None
    np.testing.assert_array_equal(rows["obs"][:400], data.obs)
    np.testing.assert_array_equal(rows["next_obs"][:400], data.next_obs)
    np.testing.assert_array_equal(rows["done"][:400], (data.terminated > 0) | data.truncated)
    shorter = dataclasses.replace(data, **{k: getattr(data, k)[:398] for k in ("obs", "actions", "rewards", "next_obs",
                                                                                "terminated", "truncated")})
    with pytest.warns(UserWarning, match="last 2 transitions are left out"):
        replay = agent.collector.prefilled(agent.collector.empty_replay(), shorter)
    assert int(replay.size) == 396 and int(replay.position) == 396


@pytest.mark.exact
def test_a_device_run_mixes_offline_data_into_its_batches_and_resumes_exactly(host_run, tmp_path, monkeypatch):
    """offline_data on the device (issue 68): a host-collected run's replay as the dataset, put on the device whole,
    half of each batch drawn from it inside the chunk (RLPD's symmetric sampling, from the chunks' key); obs_norm
    counts the dataset first; 240 + 160 == 400; the checkpoint records the dataset, and a device run's replay reads
    back as offline data row for row. Exploring with gSDE: each env's exploration matrix (features x actions)
    redrawn every sde_sample_freq policy steps from the device's key, carried across the split in the run state."""
    import jax

    from softac import SAC
    from softac.replay import device_buffer
    from softac.run import device_transitions
    from softac.run.offline_sources import run_buffer

    source = host_run
    traced = []
    mixed_rows = device_transitions.mixed_rows
    monkeypatch.setattr(device_transitions, "mixed_rows",
                        lambda drawn, offline, key, rows: traced.append((drawn.obs.shape, offline.obs.shape, rows))
                        or mixed_rows(drawn, offline, key, rows))
    cfg = device_config(offline_data=str(source), exploration_noise="gsde", sde_sample_freq=8)
    straight, _, _ = resumed_as_straight(cfg, tmp_path, 240, 160)
    assert traced and traced[0] == ((1, 16, 5), (400, 5), 16)  # half of each 32-row batch from the dataset
    assert straight.learner.obs_norm.count == 400 + 400
    noise = straight.run_state.noise  # 50 policy steps after 50 uniform: drawn at the 1st, 9th, ..., 49th
    assert noise.weights.shape == (4, 32, 1) and noise.since_draw == 2 and np.any(noise.weights != 0)
    meta = json.loads((tmp_path / "split" / "checkpoints" / "last" / "meta.json").read_text())
    assert meta["offline"]["source"] == str(source) and meta["offline"]["transitions"] == 400

    # the mix itself: the replay's rows first, the dataset's after, as the host's mixed_batches
    drawn = device_buffer.sample(straight.collector.replay, jax.random.PRNGKey(0), 2, 16, 4)
    batch = mixed_rows(drawn, straight.collector.offline_device, jax.random.PRNGKey(1), 16)
    assert batch.obs.shape == (2, 32, 5) and np.all(np.asarray(batch.steps) == 1)
    data = straight.collector.offline
    dataset = {tuple(np.r_[o, n]) for o, n in zip(data.obs, data.next_obs)}
    rows = [tuple(np.r_[o, n]) for o, n in zip(np.asarray(batch.obs).reshape(64, 5),
                                                np.asarray(batch.next_obs).reshape(64, 5))]
    assert all(row in dataset for i, row in enumerate(rows) if i % 32 >= 16)
    assert not any(row in dataset for i, row in enumerate(rows) if i % 32 < 16)

    written = run_buffer(tmp_path / "straight")  # a device run as a source: its replay as transitions
    own = straight.collector.replay_rows()
    assert len(written.rewards) == 400 and sorted(np.bincount(written.env)) == [100] * 4
    np.testing.assert_array_equal(written.obs, own["obs"])
    np.testing.assert_array_equal(written.next_obs, own["next_obs"])
    pytest.importorskip("minari")  # and as a dataset: each env's episodes of its replay
    from minari.dataset.minari_dataset import MinariDataset

    straight.write_dataset(tmp_path / "dataset")
    dataset = MinariDataset(tmp_path / "dataset" / "data")
    assert dataset.total_steps == 400 and dataset.total_episodes == 4  # each env's one episode, cut at 100 steps


def test_the_cli_trains_on_the_device_by_default_and_refuses_in_one_line(tmp_path):
    run = tmp_path / "run"
    # device_config()'s settings (and so its compiled chunk, from the compile cache where the test above ran first)
    result = run_cli("train", "--env", ENV, "--steps", "400", "--out", str(run), "--no-progress", "--n-envs", "4",
                     "--set", "hidden_sizes=32,32", "batch_size=32", "learning_starts=200", "eval_interval=400",
                     "eval_episodes=1", "log_interval=100", "action_repeat=10", "buffer_size=2000", "obs_norm=true",
                     "reward_scale=std")
    assert result.returncode == 0, result.stderr
    assert [int(float(r["step"])) for r in read_csv(run / "progress.csv")] == [100, 200, 300, 400]
    assert [int(float(r["step"])) for r in read_csv(run / "eval.csv")] == [400]
    rows = read_csv(run / "progress.csv")
    assert rows[-1]["critic_loss"] not in ("", None) and np.isfinite(float(rows[-1]["critic_loss"]))
    # softac eval of a device run evaluates on the device: its last checkpoint gives the final evaluation again
    again = run_cli("eval", str(run), "--checkpoint", "last", "--episodes", "1", "--json")
    assert again.returncode == 0, again.stderr
    assert json.loads(again.stdout)["mean_return"] == pytest.approx(float(read_csv(run / "eval.csv")[-1]["mean_return"]),
                                                                   rel=1e-5)
    refused = run_cli("train", "--env", ENV, "--steps", "10", "--out", str(tmp_path / "r"), "--set",
                      "pixels=true", "obs_norm=false")
    assert_clean_error(refused, "pixels=True: is not run by device collection yet")
    assert not (tmp_path / "r").exists()
