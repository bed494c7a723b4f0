"""Envs and replay on the device (issue 67): N envs vmapped with auto-reset inside the step, the true final
observation kept for a truncated episode's target, terminations apart from truncations, the env's action repeat;
the device replay's ring of N-row writes and its batches; all of it inside one jitted `lax.scan`."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pytest

jax = pytest.importorskip("jax")
import jax.numpy as jnp  # noqa: E402

from softac.envs.device_envs import DeviceEnvs  # noqa: E402
from softac.replay import device_buffer  # noqa: E402


class DriftState(NamedTuple):
    obs: jax.Array  # [position, steps taken, start]
    reward: jax.Array
    done: jax.Array
    position: jax.Array
    t: jax.Array
    start: jax.Array


class Drift:
    """Playground's API in a few lines: the position moves by the action, the reward is the action's size plus
    one, the episode terminates past |position| 5; each reset starts somewhere in [-1, 1] (from its key)."""

    def reset(self, key):
        start = jax.random.uniform(key, (), minval=-1.0, maxval=1.0)
        zero = jnp.zeros(())
        return DriftState(jnp.stack([start, zero, start]), zero, zero, start, zero, start)

    def step(self, state, action):
        position, t = state.position + action[0], state.t + 1
        return DriftState(jnp.stack([position, t, state.start]), 1.0 + jnp.abs(action[0]),
                          (jnp.abs(position) > 5).astype(jnp.float32), position, t, state.start)


def run(envs, batch, actions):
    step = jax.jit(envs.step)
    out = []
    for a in actions:
        batch, s = step(batch, jnp.asarray(a, jnp.float32))
        out.append(jax.tree_util.tree_map(np.asarray, s))
    return batch, out


def test_a_truncated_episode_keeps_its_final_observation_and_is_bootstrapped():
    envs = DeviceEnvs(Drift(), n=3, episode_length=4)
    batch = envs.reset(jax.random.PRNGKey(0))
    starts = np.asarray(batch.obs[:, 0])
    batch, steps = run(envs, batch, [np.full((3, 1), 0.5)] * 5)
    last = steps[3]  # the 4th step reaches the episode length
    assert last.truncated.all() and not last.terminated.any()
    np.testing.assert_allclose(last.next_obs[:, 0], starts + 2.0, rtol=1e-6)  # the final observation, not a reset's
    np.testing.assert_array_equal(last.next_obs[:, 1], 4.0)
    np.testing.assert_allclose(last.episode_returns, 4 * 1.5, rtol=1e-6)
    np.testing.assert_array_equal(last.episode_lengths, 4)
    assert not any(s.truncated.any() or s.episode_lengths.any() for s in steps[:3])
    fifth = steps[4]  # a fresh episode: its first observation is a reset's (t = 0, a new start)
    np.testing.assert_array_equal(fifth.obs[:, 1], 0.0)
    assert not np.allclose(fifth.obs[:, 2], starts)
    np.testing.assert_array_equal(np.asarray(batch.steps), 1)


def test_a_terminated_episode_ends_alone_and_is_not_a_truncation():
    envs = DeviceEnvs(Drift(), n=2, episode_length=100)
    batch = envs.reset(jax.random.PRNGKey(1))
    actions = np.array([[6.0], [0.1]])  # the first env leaves [-5, 5] at once
    batch, (first,) = run(envs, batch, [actions])
    np.testing.assert_array_equal(first.terminated, [True, False])
    np.testing.assert_array_equal(first.truncated, [False, False])
    assert abs(first.next_obs[0, 0]) > 5  # the terminal observation itself
    np.testing.assert_array_equal(np.asarray(batch.obs[:, 1]), [0.0, 1.0])  # only the first was reset
    np.testing.assert_array_equal(first.episode_lengths, [1, 0])


def test_the_envs_action_repeat_sums_rewards_until_the_episode_ends():
    envs = DeviceEnvs(Drift(), n=2, episode_length=100, action_repeat=3)
    batch = envs.reset(jax.random.PRNGKey(2))
    starts = np.asarray(batch.obs[:, 0])
    _, (step,) = run(envs, batch, [np.array([[1.0], [4.0]])])
    # the first env: three steps of 1 (reward 2 each); the second ends after its second step (|x| > 5 from |x| <= 1)
    np.testing.assert_allclose(step.rewards, [6.0, 10.0], rtol=1e-6)
    np.testing.assert_array_equal(step.terminated, [False, True])
    np.testing.assert_allclose(step.next_obs[:, 0], starts + [3.0, 8.0], rtol=1e-6)
    with pytest.raises(ValueError, match=">= 1"):
        DeviceEnvs(Drift(), n=0, episode_length=1)


def test_the_device_replay_writes_n_rows_a_step_round_the_ring_and_samples_what_it_holds():
    assert device_buffer.capacity_for(10, 4) == 8 and device_buffer.capacity_for(3, 4) == 4
    replay = device_buffer.empty(8, 2, 1)
    for i in range(3):  # 12 rows into 8: the first step's rows are overwritten by the third's
        rows = jnp.full((4, 2), float(i))
        replay = device_buffer.insert(replay, rows, rows[:, :1], jnp.full(4, float(i)), rows + 0.5,
                                      jnp.array([0.0, 1.0, 0.0, 0.0]))
    assert (int(replay.position), int(replay.size)) == (4, 8)
    np.testing.assert_array_equal(np.asarray(replay.rewards), [2, 2, 2, 2, 1, 1, 1, 1])
    np.testing.assert_array_equal(np.asarray(replay.next_obs[:, 0]), [2.5] * 4 + [1.5] * 4)
    np.testing.assert_array_equal(np.asarray(replay.terminated), [0, 1, 0, 0] * 2)
    young = device_buffer.insert(device_buffer.empty(8, 2, 1), jnp.ones((4, 2)), jnp.ones((4, 1)), jnp.full(4, 7.0),
                                 jnp.ones((4, 2)), jnp.zeros(4))
    drawn = device_buffer.sample(young, jax.random.PRNGKey(0), 3, 50)
    assert drawn.obs.shape == (3, 50, 2) and drawn.rewards.shape == (3, 50)
    np.testing.assert_array_equal(np.asarray(drawn.rewards), 7.0)  # only the 4 rows written, never the empty ones
    assert device_buffer.bytes_per_row(17, 6) == 4 * (2 * 17 + 6 + 2) + 1  # and the episode-end flag


def test_collection_into_the_replay_runs_in_one_jitted_scan():
    """20 steps of 4 envs of 6-step episodes scanned in one jit: the rows of each truncated episode's last step
    hold its final observation (t = 6), never a reset's (t = 0), and are not marked terminal."""
    envs = DeviceEnvs(Drift(), n=4, episode_length=6)

    @jax.jit
    def collect(batch, replay):
        def one(carry, _):
            batch, replay = carry
            batch, s = envs.step(batch, jnp.full((4, 1), 0.25))
            replay = device_buffer.insert(replay, s.obs, s.actions, s.rewards, s.next_obs, s.terminated)
            return (batch, replay), s.truncated
        return jax.lax.scan(one, (batch, replay), None, length=20)

    (_, replay), truncated = collect(envs.reset(jax.random.PRNGKey(3)), device_buffer.empty(80, 3, 1))
    next_t = np.asarray(replay.next_obs[:, 1]).reshape(20, 4)
    ends = np.isin(np.arange(20), [5, 11, 17])  # the 6th, 12th and 18th steps of every env
    np.testing.assert_array_equal(np.asarray(truncated), np.repeat(ends[:, None], 4, axis=1))
    np.testing.assert_array_equal(next_t[np.asarray(truncated)], 6.0)
    np.testing.assert_array_equal(np.asarray(replay.obs[:, 1]).reshape(20, 4)[6], 0.0)  # a fresh episode's first
    assert not np.asarray(replay.terminated).any()



def _steps_with_episode_ends(rng, n_steps, n, obs_dim, act_dim):
    """Vector steps whose envs end episodes at random (a quarter of them ended somewhere), with the true final
    observations where they did: what DeviceEnvs gives the replay."""
    obs = rng.normal(size=(n, obs_dim)).astype(np.float32)
    for _ in range(n_steps):
        done = rng.random(n) < 0.25
        next_obs = rng.normal(size=(n, obs_dim)).astype(np.float32)
        yield (obs, rng.uniform(-1, 1, (n, act_dim)).astype(np.float32), rng.normal(size=n).astype(np.float32),
               next_obs, (done & (rng.random(n) < 0.5)).astype(np.float32), done)
        obs = np.where(done[:, None], rng.normal(size=(n, obs_dim)).astype(np.float32), next_obs)  # resets


def test_the_obs_once_device_replay_holds_what_the_hosts_obs_once_buffer_holds():
    """buffer_obs_once on the device: after the same steps (round the ring twice, the side ring lapped), the same
    observations, final-observation slots and valid rows as the host's ObsOnceReplayBuffer, and every valid row's
    rebuilt next observation is the plain layout's."""
    from softac.replay.buffer import ObsOnceReplayBuffer

    n, obs_dim, act_dim, capacity = 4, 3, 2, 48
    once = device_buffer.empty(capacity, obs_dim, act_dim, once=True, n_envs=n)
    plain = device_buffer.empty(capacity, obs_dim, act_dim)
    host = ObsOnceReplayBuffer(capacity, obs_dim, act_dim, n)
    assert device_buffer.obs_once(once) and not device_buffer.obs_once(plain) and once.next_obs.shape == (0, obs_dim)
    assert once.final_obs.shape[0] == host.final_capacity == 16
    insert = jax.jit(device_buffer.insert)
    for step in _steps_with_episode_ends(np.random.default_rng(0), 30, n, obs_dim, act_dim):
        once = insert(once, *(jnp.asarray(a) for a in step))
        plain = insert(plain, *(jnp.asarray(a) for a in step[:5]))
        host.add(*step)
    np.testing.assert_array_equal(np.asarray(once.valid), host.valid)
    np.testing.assert_array_equal(np.asarray(once.final_slot), host.final_slot)
    np.testing.assert_array_equal(np.asarray(once.obs), host.obs)
    np.testing.assert_array_equal(np.asarray(once.final_obs), host.final_obs)
    assert (int(once.position), int(once.size), int(once.final_pos)) == (host.pos, host.size, host.final_pos)
    valid = np.flatnonzero(host.valid)
    assert 0 < len(valid) < capacity  # some rows invalid: the oldest N of the full buffer, and ring losses
    np.testing.assert_array_equal(host.next_obs_of(valid), np.asarray(plain.next_obs)[valid])

    drawn = jax.jit(device_buffer.sample, static_argnums=(2, 3, 4))(once, jax.random.PRNGKey(3), 5, 64, n)
    pairs = {(tuple(o), tuple(x)) for o, x in zip(np.asarray(drawn.obs).reshape(-1, obs_dim),
                                                  np.asarray(drawn.next_obs).reshape(-1, obs_dim))}
    held = {(tuple(o), tuple(x)) for o, x in zip(np.asarray(plain.obs)[valid], np.asarray(plain.next_obs)[valid])}
    assert pairs <= held and len(pairs) > 40  # only valid rows' transitions, as the plain layout holds them
    assert device_buffer.bytes_per_row(obs_dim, act_dim, True, capacity, n) < device_buffer.bytes_per_row(obs_dim, act_dim)


@pytest.mark.parametrize("once", [False, True], ids=["plain", "obs-once"])
def test_the_device_replays_n_step_returns_are_the_hosts(once):
    """n_step 3 on the device: for every row held after the ring wrapped, the same last row, discounted reward sum
    and step count as the host's buffer of the same layout fed the same steps (episode ends stop a walk, rows not
    written yet are not entered; obs once: invalid rows not entered either), and the sampled batch's next
    observation and termination are the last row's."""
    from softac.replay.buffer import ObsOnceReplayBuffer, ReplayBuffer

    n, obs_dim, act_dim, capacity, gamma = 4, 3, 2, 48, 0.9
    replay = device_buffer.empty(capacity, obs_dim, act_dim, once=once, n_envs=n)
    host = (ObsOnceReplayBuffer(capacity, obs_dim, act_dim, n, n_step=3, gamma=gamma) if once
            else ReplayBuffer(capacity, obs_dim, act_dim, n_envs=n, n_step=3, gamma=gamma))
    insert = jax.jit(device_buffer.insert)
    for step in _steps_with_episode_ends(np.random.default_rng(1), 17, n, obs_dim, act_dim):  # 68 rows into 48
        replay = insert(replay, *(jnp.asarray(a) for a in step))
        host.add(*step)
    rows = np.arange(capacity)
    rows = rows[host.valid] if once else rows
    last, rewards, steps = jax.jit(device_buffer.n_step_rows, static_argnums=(2, 3, 4))(replay, jnp.asarray(rows), n, 3,
                                                                                        gamma)
    host_last, host_rewards, host_steps = host._n_step_rows(rows)
    np.testing.assert_array_equal(np.asarray(last), host_last)
    np.testing.assert_array_equal(np.asarray(steps), host_steps)
    np.testing.assert_allclose(np.asarray(rewards), host_rewards, rtol=1e-6, atol=1e-6)
    assert set(np.asarray(steps).astype(int)) == {1, 2, 3}  # walks cut by episode ends and by the newest rows

    drawn = jax.jit(device_buffer.sample, static_argnums=(2, 3, 4, 5, 6))(replay, jax.random.PRNGKey(2), 2, 64, n, 3,
                                                                          gamma)
    assert drawn.steps.shape == (2, 64) and float(drawn.steps.max()) <= 3.0
    by_obs = {tuple(np.asarray(replay.obs)[r]): i for i, r in enumerate(rows)}
    for o, x, term, total in zip(np.asarray(drawn.obs).reshape(-1, obs_dim), np.asarray(drawn.next_obs).reshape(-1, obs_dim),
                                 np.asarray(drawn.terminated).reshape(-1), np.asarray(drawn.rewards).reshape(-1)):
        i = by_obs[tuple(o)]
        end = host_last[i]
        expected_next = host.next_obs_of(np.array([end]))[0] if once else host.next_obs[end]
        np.testing.assert_array_equal(x, expected_next)
        assert term == host.terminated[end] and total == pytest.approx(host_rewards[i], rel=1e-6, abs=1e-6)
