"""Training from data (issue 68): offline datasets from a softac run's replay buffer or Minari's format, mixed into
each batch (RLPD's symmetric sampling) or copied into the replay first, exact resume with the dataset checked by
checksum, `softac dataset` writing Minari datasets, REDQ's subset targets, and the refusals, each one line."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import TESTS, assert_clean_error, assert_same_training, run_cli, straight_and_resumed, tiny_config
from softac.config.sac_config import SACConfig
from softac.errors import ConfigError

ENV = "softac_test_envs:Drift-v0"  # 2 observations, actions in [-1, 3]; episodes terminate or hit 25 steps


def trained_run(directory: Path, env_id: str, steps: int, **settings) -> Path:
    """A run of 2 envs (seed 3) trained `steps` steps into directory/source, its last checkpoint with its buffer."""
    from softac import SAC

    SAC(tiny_config(env_id, n_envs=2, seed=3, **settings)).learn(steps, run_dir=directory / "source", progress=False)
    return directory / "source"


@pytest.fixture(scope="module")
def source_run(tmp_path_factory) -> Path:
    """A run of 2 envs whose last checkpoint holds its 400-row replay buffer, full and wrapped (600 steps)."""
    return trained_run(tmp_path_factory.mktemp("offline"), ENV, 600, buffer_size=400, learning_starts=100)


def test_redq_subset_targets_take_the_lowest_of_the_drawn_critics():
    """target_q=subset: the soft target from the lowest of M target critics drawn once per update (Chen et al. 2021,
    as RLPD), only those evaluated at the next state; by hand from the critics' own outputs."""
    from softac.learner import build, losses
    from softac.learner.losses import Batch

    cfg = SACConfig().replace(hidden_sizes=[16], n_critics=10, target_q="subset", target_q_subset=2)
    fns = build.build(cfg, 3, 1)
    state = fns.init(0)
    critics, policy = fns.settings.critics, fns.settings.policy
    rng = np.random.default_rng(1)
    batch = Batch(*(jnp.asarray(a, jnp.float32) for a in (rng.normal(size=(5, 3)), rng.uniform(-1, 1, (5, 1)),
                                                          rng.normal(size=5), rng.normal(size=(5, 3)), np.zeros(5),
                                                          np.ones(5))))
    key = jax.random.PRNGKey(7)
    target = jax.tree_util.tree_map(lambda p: p * 1.5, state.critic)  # targets apart from the online critics
    loss, _ = losses.critic_loss(state.critic, target, state.actor, jnp.float32(0.2), batch, key, policy, critics, 0.99)

    drawn = np.asarray(jax.random.permutation(jax.random.fold_in(key, 0x5E7), 10))[:2]
    next_actions, next_log_prob = policy.sample(state.actor, (), batch.next_obs, key)
    next_q = np.asarray(critics.q_values(target, (), batch.next_obs, next_actions))  # all ten, by hand
    soft = batch.rewards + 0.99 * (next_q[drawn].min(axis=0) - 0.2 * np.asarray(next_log_prob))
    q = np.asarray(critics.q_values(state.critic, (), batch.obs, batch.actions))
    np.testing.assert_allclose(float(loss), 0.5 * np.sum(np.mean((q - soft) ** 2, axis=1)), rtol=1e-5)
    everyone = batch.rewards + 0.99 * (next_q.min(axis=0) - 0.2 * np.asarray(next_log_prob))
    assert abs(float(loss) - 0.5 * np.sum(np.mean((q - everyone) ** 2, axis=1))) > 1e-4  # a pair, not all ten
    assert len(set(drawn)) == 2


def test_offline_settings_are_checked_in_one_line():
    for change, fragment in (({"target_q": "subset", "n_critics": 2, "target_q_subset": 3}, "target_q_subset=3"),
                             ({"target_q": "subset", "n_atoms": 11}, "subset draws scalar critics"),
                             ({"offline_data": "x", "n_step": 3}, "one-step"),
                             ({"offline_fraction": 1.0}, "offline_fraction=1.0"),
                             ({"offline_mode": "both"}, "offline_mode='both'"),
                             ({"offline_data": "x", "offline_mode": "prefill", "buffer_obs_once": True},
                              "buffer_obs_once")):
        with pytest.raises(ConfigError, match=fragment):
            SACConfig().replace(**change)


def test_a_runs_buffer_becomes_its_envs_episodes(source_run):
    """The wrapped ring's rows, oldest first, each env's in order: next_obs continues as the next row's obs inside an
    episode, terminations and time-limit truncations stay apart, the newest episode of each env is cut by the
    data's end (truncated), and the actions are back in the env's units."""
    from softac.run.offline_sources import run_buffer

    buffer = run_buffer(source_run)
    assert len(buffer.rewards) == 400 and sorted(np.bincount(buffer.env)) == [200, 200]
    assert_whole_episodes(buffer, 400)


def test_an_obs_once_runs_buffer_reads_as_whole_transitions(tmp_path):
    """A buffer that stores each observation once: its valid rows, each next observation rebuilt (the next row's,
    or the episode's final one from the side ring), the same episodes' shape."""
    from softac import SAC
    from softac.run.offline_sources import run_buffer

    SAC(tiny_config(ENV, n_envs=2, buffer_size=400, buffer_obs_once=True, learning_starts=600)).learn(
        600, run_dir=tmp_path / "run", progress=False)
    buffer = run_buffer(tmp_path / "run")
    assert 390 <= len(buffer.rewards) < 400  # a full ring's oldest N rows (and any that lost their final) left out
    assert_whole_episodes(buffer, len(buffer.rewards))


def assert_whole_episodes(buffer, rows: int) -> None:
    from softac.learner.policy import ActionScaler
    from softac.run.offline_sources import buffer_episodes

    episodes = buffer_episodes(buffer, ActionScaler(np.array([-1.0]), np.array([3.0])).to_env)
    assert sum(len(ep["rewards"]) for ep in episodes) == rows
    for ep in episodes:
        steps = ep["observations"][:, 1]  # Drift observes its step count: each episode's steps follow on
        assert np.all(np.diff(steps) == 1) and len(ep["observations"]) == len(ep["rewards"]) + 1
        assert ep["terminations"][-1] or ep["truncations"][-1]
        assert not np.any(ep["terminations"][:-1] | ep["truncations"][:-1])
        assert ep["actions"].min() >= -1.0 and ep["actions"].max() <= 3.0
    assert any(ep["terminations"][-1] for ep in episodes) and any(ep["observations"][-1, 1] == 25 for ep in episodes)


def test_offline_rows_fill_their_share_of_each_batch_and_count_in_obs_norm(source_run):
    """offline_mode mix: the last round(0.25 * 32) = 8 rows of each batch are the dataset's (whole transitions of
    it), the rest the env's; a fresh run counts the dataset's observations in obs_norm's statistics first."""
    from softac import SAC

    agent = SAC(tiny_config(ENV, offline_data=str(source_run), offline_fraction=0.25, obs_norm=True))
    agent.learn(250, progress=False)
    data = agent.collector.offline
    assert len(data) == 400 and data.source == str(source_run)
    assert agent.learner.obs_norm.count == 400 + 250
    batch = agent.collector.sample(np.random.default_rng(0), 32, 3)
    assert batch["obs"].shape == (3, 32, 2)
    rows = {tuple(np.r_[o, n]) for o, n in zip(data.obs, data.next_obs)}
    offline = [tuple(np.r_[o, n]) in rows for o, n in zip(batch["obs"][:, 24:].reshape(-1, 2),
                                                         batch["next_obs"][:, 24:].reshape(-1, 2))]
    assert all(offline)
    actions = batch["actions"][:, 24:].reshape(-1)
    assert np.all(np.abs(actions) <= 1.0)  # in [-1, 1], as the replay's


def test_prefill_copies_the_dataset_into_the_replay_first(source_run):
    from softac import SAC
    from softac.replay.offline import OfflineDataError

    agent = SAC(tiny_config(ENV, offline_data=str(source_run), offline_mode="prefill", learning_starts=0))
    agent.learn(10, progress=False)
    assert len(agent.collector.buffer) == 410
    np.testing.assert_array_equal(agent.collector.buffer.obs[:400], agent.collector.offline.obs)
    with pytest.raises(OfflineDataError, match="holds 400 transitions, more than the replay's 300 \\(buffer_size\\)"):
        SAC(tiny_config(ENV, offline_data=str(source_run), offline_mode="prefill", buffer_size=300)).learn(
            10, progress=False)


@pytest.mark.exact
def test_a_run_with_offline_data_resumes_exactly(source_run, tmp_path):
    """N + M == N+M with each batch half offline: the offline draws come from the run's checkpointed stream."""
    cfg = tiny_config(ENV, offline_data=str(source_run), learning_starts=100, obs_norm=True)
    straight, resumed = straight_and_resumed(cfg, tmp_path, 170, 130)
    assert_same_training(straight, resumed)
    meta = json.loads((tmp_path / "split" / "checkpoints" / "last" / "meta.json").read_text())
    assert meta["offline"] == {"source": str(source_run), "checksum": straight.collector.offline.checksum,
                               "transitions": 400}


def test_softac_dataset_writes_minari_datasets_that_train_and_resume(source_run, tmp_path):
    """`softac dataset` as a user types it: the replay buffer, and fresh noisy episodes of the policy, each a Minari
    dataset that minari.load_dataset reads by id and `softac train --offline-data` trains from; a resumed run
    refuses a dataset that changed since it started."""
    minari = pytest.importorskip("minari")
    root = tmp_path / "datasets"
    replay = run_cli("dataset", str(source_run), "--out", str(root / "softac" / "drift-replay-v0"))
    assert replay.returncode == 0, replay.stderr
    assert "400 transitions" in replay.stdout
    fresh = run_cli("dataset", str(source_run), "--out", str(tmp_path / "fresh"), "--episodes", "3", "--noise", "0.3")
    assert fresh.returncode == 0, fresh.stderr
    assert "3 episodes" in fresh.stdout and "with noise 0.3" in fresh.stdout
    fresh_rows = int(fresh.stdout.split(" transitions")[0].rsplit(" ", 1)[1].replace(",", ""))

    import os

    os.environ["MINARI_DATASETS_PATH"] = str(root)
    try:
        dataset = minari.load_dataset("softac/drift-replay-v0")
        assert dataset.total_steps == 400 and dataset.storage.metadata["author"] == {"softac"}
        episode = next(iter(dataset.iterate_episodes()))
        assert episode.observations.shape[1] == 2 and episode.actions.max() <= 3.0
    finally:
        del os.environ["MINARI_DATASETS_PATH"]

    run = tmp_path / "run"
    train = run_cli("train", "--env", ENV, "--steps", "250", "--out", str(run), "--offline-data", str(tmp_path / "fresh"),
                    "--no-progress", "--set", "hidden_sizes=32,32", "batch_size=32", "learning_starts=200",
                    "eval_interval=0", "obs_norm=true")
    assert train.returncode == 0, train.stderr
    from softac import SAC

    assert SAC.load(run, which="last").learner.obs_norm.count == fresh_rows + 250  # the dataset's counted first
    assert "offline data" in train.stderr and "in 3 episodes" in train.stderr and "mix (0.5 of each batch)" in train.stderr
    shutil.rmtree(tmp_path / "fresh")
    rewritten = run_cli("dataset", str(source_run), "--out", str(tmp_path / "fresh"), "--steps", "30")
    assert rewritten.returncode == 0 and ", 30 transitions" in rewritten.stdout, rewritten.stderr
    resumed = run_cli("train", "--resume", str(run), "--steps", "10", "--no-progress")
    assert_clean_error(resumed, "offline data", "changed since this run started")


def test_bad_offline_data_is_one_line(source_run, tmp_path):
    assert_clean_error(run_cli("train", "--env", "Pendulum-v1", "--out", str(tmp_path / "a"), "--offline-data",
                               str(source_run)), "observes shape (2,) but Pendulum-v1 observes (3,)")
    assert_clean_error(run_cli("train", "--env", ENV, "--out", str(tmp_path / "b"), "--offline-data",
                               str(tmp_path / "nothing")), "not a Minari dataset directory, a softac run")
    assert_clean_error(run_cli("dataset", str(source_run), "--out", str(tmp_path / "c"), "--noise", "0.1"),
                       "give --episodes N or --steps N")


def test_fresh_episodes_stop_at_a_step_count_with_the_last_one_truncated():
    """policy_episodes with `steps`: episodes until that many transitions, the last cut there and marked truncated
    (so that it bootstraps), Gaussian noise in [-1, 1] units moving the actions inside the bounds."""
    import gymnasium as gym

    from softac.learner.policy import ActionScaler
    from softac.outputs.dataset import policy_episodes

    env = gym.make(ENV)
    scaler = ActionScaler(np.array([-1.0]), np.array([3.0]))
    episodes = policy_episodes(lambda obs: np.array([1.0], np.float32), scaler, env, None, 0.5, seed=1, steps=60)
    assert sum(len(ep["rewards"]) for ep in episodes) == 60 and len(episodes) >= 3
    last = episodes[-1]
    assert last["truncations"][-1] or last["terminations"][-1]
    actions = np.concatenate([ep["actions"] for ep in episodes])
    assert actions.min() >= -1.0 and actions.max() <= 3.0 and actions.std() > 0.1  # noise of 0.5 * 2 in env units
    again = policy_episodes(lambda obs: np.array([1.0], np.float32), scaler, env, None, 0.5, seed=1, steps=60)
    np.testing.assert_array_equal(np.concatenate([ep["actions"] for ep in again]), actions)  # seeded


GOAL_ENV = "softac_test_envs:PointGoal-v0"  # observation [x, y, t/20], achieved [x, y], desired goal; 20-step episodes


@pytest.fixture(scope="module")
def goal_run(tmp_path_factory) -> Path:
    """A goal env's run of 2 envs whose 150-row HER buffer wrapped (200 steps: 10 episodes of 20)."""
    return trained_run(tmp_path_factory.mktemp("offline-goal"), GOAL_ENV, 200, buffer_size=150, learning_starts=60)


def test_a_goal_runs_episodes_are_relabelled_by_her_in_each_batch(goal_run):
    """A goal env's HER buffer read as offline data: its rows episode after episode, each step's observation
    continuing the last (t/20 counts up), whole episodes of 20 but for each env's oldest (the ring cut its start);
    in a batch about her_k / (her_k + 1) of the dataset's rows get a goal their episode achieved at or after them
    (future), with the env's reward for it, and the rest keep their own goal and reward."""
    from softac import SAC
    from softac.envs.goals import dict_layout
    from softac.replay.offline import OfflineDataError
    from softac_test_envs import PointGoalEnv

    agent = SAC(tiny_config(GOAL_ENV, offline_data=str(goal_run), learning_starts=60))
    agent.learn(60, progress=False)
    data = agent.collector.offline
    layout = dict_layout(PointGoalEnv().observation_space)
    steps, achieved, desired = (layout.slices[k] for k in ("observation", "achieved_goal", "desired_goal"))
    assert len(data) == 150 and data.episodes == 8 and data.t is not None
    ends = np.flatnonzero(data.truncated)
    assert np.all(data.length[ends] == data.t[ends] + 1) and sorted(set(data.length)) == [15, 20]
    inside = np.flatnonzero(~data.truncated[:-1])
    np.testing.assert_array_equal(data.next_obs[inside], data.obs[inside + 1])
    np.testing.assert_allclose(data.obs[:, steps][:, 2] * 20 - data.t, np.where(data.length == 15, 5, 0), atol=1e-4)

    her = agent.collector.her
    batch = data.sample(np.random.default_rng(5), 400, 1, her)
    obs, next_obs, rewards = batch["obs"][0], batch["next_obs"][0], batch["rewards"][0]
    own = {tuple(row) for row in data.obs}
    kept = np.array([tuple(row) in own for row in obs])
    assert 0.7 < 1 - kept.mean() < 0.9  # her_k 4: 0.8 relabelled (a few draw their own goal back)
    env = PointGoalEnv()
    np.testing.assert_array_equal(rewards, env.compute_reward(next_obs[:, achieved], next_obs[:, desired], {}))
    for o, n in zip(obs[~kept], next_obs[~kept]):
        match = np.flatnonzero(np.all(data.obs[:, :layout.slices["desired_goal"].start] == o[:desired.start], axis=1)
                               & np.all(data.obs[:, steps] == o[steps], axis=1))
        row = match[0]
        later = data.next_obs[row:row + data.length[row] - data.t[row], achieved]
        assert any(np.array_equal(goal, o[desired]) for goal in later)  # a goal its episode reached later
        np.testing.assert_array_equal(n[desired], o[desired])
    with pytest.raises(OfflineDataError, match="cannot be copied into a goal env's HER buffer"):
        SAC(tiny_config(GOAL_ENV, offline_data=str(goal_run), offline_mode="prefill")).learn(10, progress=False)


@pytest.mark.exact
def test_a_goal_env_with_offline_data_resumes_exactly(goal_run, tmp_path):
    """N + M == N+M with the dataset's rows relabelled in each batch: HER's draws come from the run's stream."""
    cfg = tiny_config(GOAL_ENV, offline_data=str(goal_run), learning_starts=60)
    straight, resumed = straight_and_resumed(cfg, tmp_path, 110, 90)
    assert_same_training(straight, resumed)


def test_softac_dataset_writes_a_goal_envs_dict_observations(goal_run, tmp_path):
    """A goal env's dataset records the env's Dict space and dict observations (Minari's recover_environment, other
    libraries), from the replay buffer and from fresh episodes; --offline-data reads it back flattened, and an env
    observing something else is refused in one line naming both."""
    minari = pytest.importorskip("minari")
    replay = run_cli("dataset", str(goal_run), "--out", str(tmp_path / "replay"))
    assert replay.returncode == 0, replay.stderr
    fresh = run_cli("dataset", str(goal_run), "--out", str(tmp_path / "fresh"), "--episodes", "2")
    assert fresh.returncode == 0, fresh.stderr
    from minari.dataset.minari_dataset import MinariDataset

    from softac import SAC
    from softac.run.offline_sources import run_buffer

    written = MinariDataset(tmp_path / "replay" / "data")
    assert type(written.observation_space).__name__ == "Dict" and written.total_steps == 150
    first = next(iter(written.iterate_episodes()))
    assert set(first.observations) == {"observation", "achieved_goal", "desired_goal"}
    assert first.observations["observation"].shape == (len(first.rewards) + 1, 3)
    assert np.all(first.observations["desired_goal"] == first.observations["desired_goal"][0])  # one goal an episode
    assert len(list(MinariDataset(tmp_path / "fresh" / "data").iterate_episodes())) == 2

    agent = SAC(tiny_config(GOAL_ENV, offline_data=str(tmp_path / "replay"), learning_starts=60))
    agent.learn(60, progress=False)
    data, rows = agent.collector.offline, run_buffer(goal_run, agent.spaces.layout)
    assert len(data) == 150 and data.t is not None
    np.testing.assert_array_equal(np.sort(data.obs, axis=0), np.sort(rows.obs, axis=0))  # the same rows, flattened
    assert_clean_error(run_cli("train", "--env", ENV, "--out", str(tmp_path / "x"), "--offline-data",
                               str(tmp_path / "replay")),
                       "observes a dict of achieved_goal (2), desired_goal (2), observation (3) values but "
                       f"{ENV} observes shape (2,)")


def test_a_run_too_large_for_the_memory_is_refused_before_its_checkpoint_is_read(source_run, monkeypatch):
    import softac.base.memory as memory
    from softac import SAC
    from softac.replay.offline import OfflineDataError
    from softac.run import checkpoint as ckpt
    from softac.run.offline_sources import load_offline_data

    agent = SAC(tiny_config(ENV))
    monkeypatch.setattr(memory, "available_memory_bytes", lambda: 1000)
    monkeypatch.setattr(ckpt, "load", lambda *args, **kwargs: pytest.fail("the checkpoint was read"))
    with pytest.raises(OfflineDataError, match=r"^offline data .*source: its checkpoint's arrays need [\d.]+ KiB but "
                                               r"only 1000.0 B is available$"):
        load_offline_data(str(source_run), ENV, agent.spaces, agent.learner.scaler.to_normalised)


IMAGE_ENV = "softac_test_envs:DotImage-v0"  # 16x16 RGB frames, stacked in 2s; 20-step episodes
IMAGE = dict(encoder_channels=8, encoder_features=16, augment_pad=2, frame_stack=2, n_envs=2, buffer_size=120)


def test_an_image_runs_frames_become_a_dataset_and_an_image_runs_offline_data(tmp_path):
    """An image run's frame buffer (each frame stored once) read as frame stacks [2, 16, 16, 3] uint8, oldest first,
    each env's episodes in turn and each episode's stacks held once (a row's next observation the stack after its
    own); written as a Minari dataset of the env's uint8 frame stacks (its replay buffer, and fresh episodes),
    which reads back as the same rows; mixed into an image run's batches in the env's shape; prefill, and images
    with state values packed beside them, refused in one line."""
    minari = pytest.importorskip("minari")  # noqa: F841
    from minari.dataset.minari_dataset import MinariDataset

    from softac import SAC
    from softac.replay.offline import OfflineDataError
    from softac.run.offline_sources import load_offline_data, run_buffer

    source = tmp_path / "source"
    collected = SAC(tiny_config(IMAGE_ENV, **IMAGE, learning_starts=400, seed=2))
    collected.learn(160, run_dir=source, progress=False)  # 160 rows into 120: wrapped, no update needed
    agent = SAC(tiny_config(IMAGE_ENV, **IMAGE, learning_starts=20, offline_data=str(source)))
    data = load_offline_data(str(source), IMAGE_ENV, agent.spaces, agent.learner.scaler.to_normalised)
    rows = run_buffer(source)
    order = np.concatenate([np.flatnonzero(rows.env == e) for e in (0, 1)])
    assert data.next_obs is None and data.obs.dtype == np.uint8 and data.obs.shape[1:] == (2, 16, 16, 3)
    assert len(data) == len(rows.rewards) and 100 <= len(data) <= 120 and len(data.obs) == len(data) + data.episodes
    current, following = data.observations(np.arange(len(data)))
    np.testing.assert_array_equal(current, rows.obs[order])
    np.testing.assert_array_equal(following, rows.next_obs[order])
    np.testing.assert_array_equal(following[:, 0], current[:, 1])  # the stack moves on by one frame

    collected.write_dataset(tmp_path / "replay")
    collected.write_dataset(tmp_path / "fresh", episodes=1)
    written = MinariDataset(tmp_path / "replay" / "data")
    assert written.observation_space.shape == (2, 16, 16, 3) and written.observation_space.dtype == np.uint8
    fresh = next(iter(MinariDataset(tmp_path / "fresh" / "data").iterate_episodes()))
    assert fresh.observations.shape == (21, 2, 16, 16, 3) and fresh.observations.dtype == np.uint8
    again = load_offline_data(str(tmp_path / "replay"), IMAGE_ENV, agent.spaces, agent.learner.scaler.to_normalised)
    np.testing.assert_array_equal(again.obs, data.obs)
    np.testing.assert_array_equal(again.obs_row, data.obs_row)

    agent.learn(40, progress=False)
    batch = agent.collector.sample(np.random.default_rng(0), 32, 1)
    assert batch["obs"].dtype == np.uint8 and batch["obs"].shape == (1, 32, 2, 16, 16, 3)
    held = {stack.tobytes() for stack in data.obs}
    assert all(stack.tobytes() in held for stack in batch["next_obs"][0, 16:])  # the dataset's half
    with pytest.raises(OfflineDataError, match="cannot be copied into an image run's frame buffer"):
        SAC(tiny_config(IMAGE_ENV, **IMAGE, offline_data=str(source), offline_mode="prefill")).learn(10, progress=False)
    packed = SAC(tiny_config("softac_test_envs:DotStateImage-v0", **IMAGE))
    with pytest.raises(OfflineDataError, match="an image with state values .* is not read as offline data"):
        load_offline_data(str(source), "DotStateImage-v0", packed.spaces, packed.learner.scaler.to_normalised)


def test_the_upright_check_tells_a_flipped_halfcheetah_dataset_by_its_pitch(tmp_path):
    """benchmarks/upright.py (issue 68's medium sources): a dataset whose observation 1 (HalfCheetah's torso pitch)
    stays near 0 is upright (exit 0), one near pi, a cheetah on its back, is flipped (exit 1); not a dataset: exit 2."""
    pytest.importorskip("minari")
    import gymnasium as gym

    from softac.replay.offline import write_minari

    rng = np.random.default_rng(0)
    box = gym.spaces.Box(-np.inf, np.inf, (3,), np.float32)

    def dataset(name: str, pitch: float) -> Path:
        episodes = [{"observations": np.c_[rng.normal(size=11), pitch + 0.1 * rng.normal(size=11), rng.normal(size=11)]
                     .astype(np.float32), "actions": rng.uniform(-1, 1, (10, 1)).astype(np.float32),
                     "rewards": rng.normal(size=10), "terminations": [False] * 10, "truncations": [False] * 9 + [True]}
                    for _ in range(3)]
        return write_minari(tmp_path / name, f"test/{name}", episodes, None, box,
                            gym.spaces.Box(-1, 1, (1,), np.float32), "test", "test")

    script = str(TESTS.parent / "benchmarks" / "upright.py")

    def check(path: Path) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, script, str(path)], capture_output=True, text=True)

    upright, flipped = check(dataset("upright-v0", 0.2)), check(dataset("flipped-v0", -3.1))
    assert upright.returncode == 0 and "upright" in upright.stdout, upright.stderr
    assert flipped.returncode == 1 and "mean |pitch| 3.1" in flipped.stdout and "flipped" in flipped.stdout
    assert_clean_error(check(tmp_path), "is not a dataset written by `softac dataset`")
