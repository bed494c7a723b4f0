"""Coloured (pink) exploration noise (issue 43; Eberhard et al. 2023): its statistics, that training acts with
it (a fresh sequence per episode), and exact resume with it; the device's pink and held noise (issue 67), the
functions its chunks step, against the host's."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import assert_clean_error, assert_same_training, run_cli, straight_and_resumed
from softac import SAC
from softac.replay.exploration import ColoredNoise, colored_noise


@pytest.mark.parametrize("length", [1000, 999])
@pytest.mark.parametrize("beta", [0.0, 1.0, 2.0])
def test_colored_noise_has_unit_variance_and_its_spectrum_falls_as_one_over_f_to_the_beta(beta, length):
    x = colored_noise(np.random.default_rng(0), beta, (4000,), length)
    # each step's variance over 4,000 independent sequences (standard error 0.022)
    for t in (0, length // 2, length - 1):
        assert abs(x[:, t].var() - 1.0) < 0.1, (t, x[:, t].var())
    # the mean periodogram's slope on log-log axes is -beta (the zero frequency left out)
    power = np.mean(np.abs(np.fft.rfft(x, axis=1)) ** 2, axis=0)[1:]
    freqs = np.fft.rfftfreq(length)[1:]
    slope = np.polyfit(np.log(freqs), np.log(power), 1)[0]
    assert abs(slope + beta) < 0.05, slope
    lag1 = np.mean(x[:, 1:] * x[:, :-1])
    if beta == 0:
        assert abs(lag1) < 0.01  # white: no correlation between steps
    else:
        assert lag1 > 0.7  # pink and red: neighbouring steps alike


def test_training_acts_with_each_envs_noise_sequence_and_starts_a_fresh_one_each_episode(tiny):
    """With the policy held fixed (no gradient steps), each training action is tanh(mean + std * noise) for
    the next value of its env's sequence: Pendulum's 200-step episodes, sequences of 150 (used up mid-episode,
    then a fresh one) and a fresh one at each episode's end."""
    cfg = tiny("Pendulum-v1", n_envs=2, learning_starts=0, gradient_steps=0, exploration_noise="pink",
               noise_sequence_length=150, buffer_size=1000)
    agent = SAC(cfg)
    agent.learn(500, progress=False)  # 250 steps of each env: one episode end each (at 200)
    buffer = agent.collector.buffer
    replay = ColoredNoise(1.0, 2, 1, 150, cfg.seed)
    for t in range(250):
        if t == 200:
            for env in (0, 1):
                replay.restart(env)
        noise = replay.next()
        rows = slice(2 * t, 2 * t + 2)
        expected, _ = agent.learner.act_with_noise(buffer.obs[rows], noise)
        np.testing.assert_array_equal(buffer.actions[rows], expected)
    # the noise is what moves the actions: consecutive actions of an env are correlated, as its noise is
    mean, log_std = agent.learner.functions.policy.mean_and_log_std(agent.learner.state.actor, (),
                                                                    buffer.obs[:500:2])
    eps = (np.arctanh(np.clip(buffer.actions[:500:2, 0], -0.999999, 0.999999)) - mean[:, 0]) / np.exp(log_std[:, 0])
    assert np.corrcoef(eps[1:], eps[:-1])[0, 1] > 0.5


@pytest.mark.exact
def test_a_run_with_pink_noise_resumes_exactly(tiny, tmp_path):
    cfg = tiny(n_envs=2, exploration_noise="pink", noise_sequence_length=40, noise_beta=1.0)
    straight, resumed = straight_and_resumed(cfg, tmp_path, 430, 270)
    assert_same_training(straight, resumed)  # the noise's random stream, sequences and positions too


def test_bad_noise_settings_are_one_line_errors(tmp_path):
    for setting, words in (("exploration_noise=brown", "must be gaussian, pink, gsde or repeat"),
                           ("noise_beta=-1", "noise_beta"), ("noise_sequence_length=1", "noise_sequence_length")):
        result = run_cli("train", "--env", "Pendulum-v1", "--steps", "10", "--out", str(tmp_path / "r"),
                         "--set", setting)
        assert_clean_error(result, words)


def test_the_devices_pink_noise_continues_the_hosts_sequences_and_restarts_each_ended_episode():
    """next_pink and restarted, as a device chunk steps them: from a host ColoredNoise's state, each env's values are
    its sequence's, in order; an env whose episode ended (every 100th step here) goes on with a fresh sequence from
    its first value, one of unit variance whose spectrum falls as 1/f (the host's colored_noise, from a JAX key)."""
    import jax
    import jax.numpy as jnp

    from softac.run.device_transitions import colored_sequences, keep_noise_state, next_pink, noise_state, restarted

    pink, host = (1.0, 100), ColoredNoise(1.0, 4, 1, 100, seed=0)

    def step(state, t):
        key = jax.random.fold_in(jax.random.PRNGKey(1), t)
        state, values = next_pink(state, jax.random.fold_in(key, 3), pink)
        return restarted(state, jnp.full(4, (t + 1) % 100 == 0), jax.random.fold_in(key, 4), pink), values

    (sequences, position), values = jax.lax.scan(step, noise_state(host), jnp.arange(280))
    values = np.asarray(values)[:, :, 0]  # [step, env]
    np.testing.assert_allclose(values[:100].T, host.sequences[:, 0], rtol=1e-6)
    assert list(np.asarray(position)) == [80] * 4
    np.testing.assert_array_equal(values[200:280].T, np.asarray(sequences)[:, 0, :80])
    assert not np.allclose(values[100:200], values[:100])  # fresh sequences, not the first ones again
    keep_noise_state(host, (sequences, position))  # back on the host, the run state checkpoints it
    assert list(host.position) == [80] * 4 and host.next()[0, 0] == np.float32(sequences[0, 0, 80])

    x = np.asarray(colored_sequences(jax.random.PRNGKey(2), (2000,), (1.0, 1000)), np.float64)
    assert all(abs(x[:, t].var() - 1.0) < 0.12 for t in (0, 500, 999))
    power = np.mean(np.abs(np.fft.rfft(x, axis=1)) ** 2, axis=0)[1:]
    assert abs(np.polyfit(np.log(np.fft.rfftfreq(1000)[1:]), np.log(power), 1)[0] + 1.0) < 0.05


def test_the_devices_held_noise_holds_every_envs_noise_for_zeta_drawn_steps():
    """next_held, as a device chunk steps it (FlashSAC's noise repetition): each env's standard-normal noise held
    for k steps, every env's redrawn at the same steps (one count for all envs, as the authors'), k from 1 to 16
    and about 2.1 on average (the truncated Zeta of mu 2: sum k^-1 / sum k^-2 over 1..16)."""
    import jax

    from softac.replay.exploration import RepeatedNoise
    from softac.run.device_transitions import keep_noise_state, next_held, noise_state

    host = RepeatedNoise(2.0, 16, 4, 1, seed=0)

    def step(held, key):
        held = next_held(held, key, (2.0, 16))
        return held, held[0]

    last, noise = jax.lax.scan(step, noise_state(host), jax.random.split(jax.random.PRNGKey(0), 2000))
    noise = np.asarray(noise)[:, :, 0]
    changed = np.any(noise[1:] != noise[:-1], axis=1)
    assert np.array_equal(changed, np.all(noise[1:] != noise[:-1], axis=1))  # all envs at once, or none
    holds = np.diff(np.flatnonzero(np.r_[True, changed, True]))
    expected = np.sum(np.arange(1, 17) ** -1.0) / np.sum(np.arange(1, 17) ** -2.0)
    assert holds.min() >= 1 and holds.max() <= 16 and abs(holds[:-1].mean() - expected) < 0.25, holds.mean()
    drawn = noise[np.r_[True, changed]]
    assert abs(drawn.std() - 1.0) < 0.1 and len(set(noise[0])) == 4
    keep_noise_state(host, last)  # back on the host, the run state checkpoints it: the same noise until its hold ends
    assert host.count == holds[-1] and 1 <= host.hold <= 16 and np.array_equal(host.noise[:, 0], noise[-1])
