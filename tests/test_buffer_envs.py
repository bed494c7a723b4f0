"""Replay buffer and env pool: truncation bootstraps, termination does not, true final observations."""

import numpy as np
import pytest

from softac.replay.buffer import BufferMemoryError, ReplayBuffer
from softac.envs.make import EnvError, EnvPool, check_spaces, make_env, resolve_env_id


def test_buffer_wraps_and_roundtrips():
    buf = ReplayBuffer(5, obs_dim=2, act_dim=1)
    for i in range(3):
        buf.add(np.full((2, 2), i), np.full((2, 1), i), np.full(2, i), np.full((2, 2), i + 1), np.zeros(2))
    assert len(buf) == 5 and buf.pos == 1
    assert buf.rewards.tolist() == [2, 0, 1, 1, 2]  # the oldest rows were overwritten first
    copy = ReplayBuffer(5, 2, 1)
    copy.load_state_dict(buf.state_dict())
    for name in ReplayBuffer.FIELDS:
        np.testing.assert_array_equal(getattr(copy, name), getattr(buf, name))
    assert (copy.pos, copy.size) == (buf.pos, buf.size)
    batch = buf.sample(np.random.default_rng(0), 4, n_batches=3)
    assert batch["obs"].shape == (3, 4, 2) and batch["terminated"].shape == (3, 4)


def test_buffer_larger_than_memory_is_refused():
    with pytest.raises(BufferMemoryError, match="buffer_size"):
        ReplayBuffer(10**13, obs_dim=100, act_dim=10)


def _pool(env_id="softac_test_envs:Drift-v0", n=1):
    return EnvPool(lambda i: make_env(env_id), n, seed=0, name=env_id)


def test_truncation_keeps_true_final_obs_and_is_not_terminal():
    pool = _pool()
    pool.reset()
    for t in range(25):  # the time limit is 25 and action 1 keeps x still
        result = pool.step(np.array([[1.0]], np.float32), t)
    assert result.truncated[0] and not result.terminated[0]
    assert result.next_obs[0, 1] == 25  # the final observation (step counter 25)
    assert pool.obs[0, 1] == 0  # the pool already moved on to a fresh episode
    # Drift-v0 reports no success; the host's one-step chunks leave each episode's step to the chunk's end
    assert result.finished == [(0, pytest.approx(25.0), 25, None, None)]


def test_termination_is_terminal():
    pool = _pool()
    pool.reset()
    for t in range(25):
        result = pool.step(np.array([[-1.0]], np.float32), t)  # x falls by 0.1 a step: |x| > 0.3 by step ~4
        if result.terminated[0]:
            break
    assert result.terminated[0] and abs(result.next_obs[0, 0]) > 0.3


def test_training_stores_terminated_and_truncated_apart(tiny):
    from softac.agent import SAC

    agent = SAC(tiny(learning_starts=10_000, n_envs=2))
    agent.learn(600, progress=False)
    buf = agent.collector.buffer
    x, t = buf.next_obs[: len(buf), 0], buf.next_obs[: len(buf), 1]
    term = buf.terminated[: len(buf)]
    truncated_rows = (t == 25) & (np.abs(x) <= 0.3)
    assert truncated_rows.any() and term[truncated_rows].max() == 0.0
    assert (term == 1.0).any() and np.all(np.abs(x[term == 1.0]) > 0.3)
    # the stored next_obs continues obs within an episode, never the reset one at its end
    assert np.all(t[truncated_rows] == buf.obs[: len(buf), 1][truncated_rows] + 1)


def test_unknown_env_suggests_close_names():
    with pytest.raises(EnvError, match="did you mean InvertedPendulum-v5"):
        resolve_env_id("InvertedPendulm-v5")


def test_module_env_id_imports_the_module():
    assert resolve_env_id("softac_test_envs:Drift-v0") == "Drift-v0"
    with pytest.raises(EnvError, match="cannot import module"):
        resolve_env_id("no_such_module_xyz:Drift-v0")


def test_spaces_are_checked():
    with pytest.raises(EnvError, match="Discrete action space"):
        check_spaces(make_env("CartPole-v1"))
    with pytest.raises(EnvError, match="unbounded"):
        check_spaces(make_env("softac_test_envs:Unbounded-v0"))
    info = check_spaces(make_env("softac_test_envs:Drift-v0"))
    assert (info.low.tolist(), info.high.tolist()) == ([-1.0], [3.0])


def test_env_errors_name_env_and_step():
    pool = _pool("softac_test_envs:BrokenStep-v0")
    pool.reset()
    with pytest.raises(EnvError, match=r"BrokenStep-v0 raised in step at step 30: RuntimeError: simulator exploded"):
        for t in range(40):
            pool.step(np.array([[1.0]], np.float32), t)
    pool = _pool("softac_test_envs:NanObs-v0")
    pool.reset()
    with pytest.raises(EnvError, match="non-finite observation at step 29"):
        for t in range(40):
            pool.step(np.array([[1.0]], np.float32), t)


def test_mujoco_state_restores_exactly():
    a, b = _pool("InvertedPendulum-v5"), _pool("InvertedPendulum-v5")
    a.reset()
    b.reset()
    rng = np.random.default_rng(0)
    for t in range(7):
        a.step(rng.uniform(-1, 1, (1, 1)).astype(np.float32), t)
    meta, arrays = a.get_state()
    assert b.set_state(meta, arrays, 7)
    for t in range(30):
        act = rng.uniform(-1, 1, (1, 1)).astype(np.float32)
        ra, rb = a.step(act, t), b.step(act, t)
        np.testing.assert_array_equal(ra.next_obs, rb.next_obs)
        np.testing.assert_array_equal(ra.rewards, rb.rewards)


@pytest.mark.parametrize("n_envs,capacity", [(1, 40), (3, 50), (4, 64)])
def test_obs_once_buffer_rebuilds_the_same_transitions(n_envs, capacity):
    """Fed the same transitions, the compact buffer reconstructs exactly what the full one stores."""
    from softac.replay.buffer import ObsOnceReplayBuffer

    pool = EnvPool(lambda i: make_env("softac_test_envs:Drift-v0"), n_envs, seed=1, name="Drift-v0")
    pool.reset()
    full = ReplayBuffer(capacity, 2, 1)
    compact = ObsOnceReplayBuffer(capacity, 2, 1, n_envs)
    rng = np.random.default_rng(0)
    for t in range(300):  # wraps the ring several times; episodes end by termination and truncation
        obs = pool.obs
        actions = rng.uniform(-1, 3, (n_envs, 1)).astype(np.float32)
        result = pool.step(actions, t)
        for buf in (full, compact):
            buf.add(obs, actions, result.rewards, result.next_obs, result.terminated,
                    result.terminated | result.truncated)
        rows = np.flatnonzero(compact.valid[: compact.size])
        assert len(rows) >= compact.size - n_envs - compact.final_capacity
        np.testing.assert_array_equal(compact.obs[rows], full.obs[rows])
        np.testing.assert_array_equal(compact.next_obs_of(rows), full.next_obs[rows])
        np.testing.assert_array_equal(compact.terminated[rows], full.terminated[rows])
    batch = compact.sample(np.random.default_rng(1), 16, 3)
    assert batch["next_obs"].shape == (3, 16, 2)
    restored = ObsOnceReplayBuffer(capacity, 2, 1, n_envs)
    restored.load_state_dict(compact.state_dict())
    rows = np.flatnonzero(restored.valid[: restored.size])
    np.testing.assert_array_equal(restored.next_obs_of(rows), full.next_obs[rows])
    from softac.config.sac_config import SACConfig
    from softac.envs.make import SpaceInfo
    from softac.replay.collector import replay_buffer_for

    pusher, spaces = SACConfig.preset("Pusher-v5"), SpaceInfo(23, 7, -np.ones(7), np.ones(7))
    full_bytes = replay_buffer_for(pusher, spaces, None)[1]
    compact_bytes = replay_buffer_for(pusher.replace(buffer_obs_once=True), spaces, None)[1]
    assert full_bytes == 221 and compact_bytes == pytest.approx(133 + 92 / 8)  # one obs saved, a small side ring


def _reference_n_step(log, g, n_envs, n_step, gamma, newest, can_enter=lambda g: True):
    """The n-step return from global transition g, walked over the plain list of every transition added."""
    rewards, last, steps = 0.0, g, 0
    for k in range(n_step):
        at = g + k * n_envs
        if at > newest or (k > 0 and (log[last]["done"] or not can_enter(at))):
            break
        rewards += gamma**k * log[at]["reward"]
        last, steps = at, k + 1
    return last, rewards, steps


@pytest.mark.parametrize("n_envs,capacity,n_step", [(1, 30, 3), (3, 50, 4), (2, 64, 5)])
def test_n_step_returns_match_a_walk_over_every_transition(n_envs, capacity, n_step):
    """Sampled n-step rows of both buffers equal a plain walk over the transitions: rewards discounted and
    summed per env (vector envs interleave), stopped after an episode end (termination or truncation),
    never past the newest row, across the ring's wrap; the last row's next obs and terminated flag."""
    from softac.replay.buffer import ObsOnceReplayBuffer

    gamma = 0.9
    pool = EnvPool(lambda i: make_env("softac_test_envs:Drift-v0"), n_envs, seed=2, name="Drift-v0")
    pool.reset()
    full = ReplayBuffer(capacity, 2, 1, n_envs=n_envs, n_step=n_step, gamma=gamma)
    compact = ObsOnceReplayBuffer(capacity, 2, 1, n_envs, n_step=n_step, gamma=gamma)
    rng = np.random.default_rng(0)
    log = []
    ended = {"terminated": 0, "truncated": 0}
    for t in range(200):  # wraps the ring several times
        obs = pool.obs
        actions = rng.uniform(-1, 3, (n_envs, 1)).astype(np.float32)
        result = pool.step(actions, t)
        done = result.terminated | result.truncated
        ended["terminated"] += int(result.terminated.sum())
        ended["truncated"] += int(result.truncated.sum())
        for buf in (full, compact):
            buf.add(obs, actions, result.rewards, result.next_obs, result.terminated, done)
        for e in range(n_envs):
            log.append({"reward": float(result.rewards[e]), "next_obs": result.next_obs[e].copy(),
                        "terminated": float(result.terminated[e]), "done": bool(done[e])})
        newest = len(log) - 1
        oldest = max(0, len(log) - capacity)
        for buf in (full, compact):
            can_enter = (lambda g: True) if buf is full else (lambda g: bool(compact.valid[g % capacity]))
            starts = [g for g in range(oldest, newest + 1) if buf is full or compact.valid[g % capacity]]
            idx = np.array([g % capacity for g in starts])
            if not len(idx):
                continue
            last, rewards, steps = buf._returns_of(idx)
            batch_next = buf.next_obs[last] if buf is full else buf.next_obs_of(last)
            for j, g in enumerate(starts):
                ref_last, ref_rewards, ref_steps = _reference_n_step(log, g, n_envs, n_step, gamma, newest,
                                                                     can_enter)
                assert last[j] == ref_last % capacity and steps[j] == ref_steps
                # float32 discounts, products and a sum of up to n_step terms, each at most 3 in size (Drift's
                # rewards lie in [-3, 1]): n_step + 2 roundings of 2^-24 of their total, in any summation order
                assert rewards[j] == pytest.approx(ref_rewards, rel=0, abs=(n_step + 2) * 2**-24 * 3 * ref_steps)
                np.testing.assert_array_equal(batch_next[j], log[ref_last]["next_obs"])
                assert buf.terminated[last[j]] == log[ref_last]["terminated"]
    assert ended["terminated"] and ended["truncated"]  # both kinds of episode end were walked over
    batch = full.sample(np.random.default_rng(1), 16, 2)
    assert batch["steps"].shape == (2, 16) and batch["steps"].max() == n_step


def test_n_step_by_hand():
    """One env, gamma 0.5, n 3: rewards 1, 2 (truncated), 3, 4 (newest)."""
    buf = ReplayBuffer(10, obs_dim=1, act_dim=1, n_step=3, gamma=0.5)
    for r, truncated in ((1, False), (2, True), (3, False), (4, False)):
        buf.add(np.full((1, 1), r), np.zeros((1, 1)), np.array([r]), np.full((1, 1), 10 * r), np.zeros(1),
                np.array([truncated]))
    last, rewards, steps = buf._returns_of(np.arange(4))
    assert last.tolist() == [1, 1, 3, 3]  # stopped at the truncation, and at the newest row
    assert rewards.tolist() == [1 + 0.5 * 2, 2, 3 + 0.5 * 4, 4]
    assert steps.tolist() == [2, 1, 2, 1]
    assert buf.next_obs[last].ravel().tolist() == [20, 20, 40, 40]  # the true final obs of the truncated step


def test_buffer_checkpoints_from_before_n_step_load():
    """Checkpoints written before the episode-end flag existed load (their runs are one-step)."""
    buf = ReplayBuffer(5, obs_dim=2, act_dim=1)
    buf.add(np.zeros((2, 2)), np.zeros((2, 1)), np.ones(2), np.ones((2, 2)), np.array([0.0, 1.0]))
    state = buf.state_dict()
    del state["done"]
    copy = ReplayBuffer(5, 2, 1)
    copy.load_state_dict(state)
    assert copy.done[:2].tolist() == [False, True] and len(copy) == 2
