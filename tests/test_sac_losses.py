"""The three SAC losses as pure functions, each pinned on a hand-computed case: its value and the sign of
its gradient (the direction a gradient step moves the parameters).

The losses run in float32, the hand computations in float64: rel=1e-5 is ~170 float32 roundings (2^-24) of
the result, for a few dozen operations on terms no larger than the result; the log-probabilities, which can
be ten times smaller than their terms, get a bound from the terms' sizes."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softac.learner import losses, policy
from softac.learner.networks import init_actor, init_critics

pytestmark = pytest.mark.numerics

OBS, ACT, BATCH = 3, 2, 4
POLICY = policy.Policy("relu", -20.0, 2.0, "clamp")
CRITICS = losses.Critics("relu", unroll=True)


def constant_actor(mean, log_std):
    """An actor whose output is [mean, log_std] for every observation: zero weights, the last bias set."""
    layers = init_actor(np.random.default_rng(0), OBS, ACT, [4], "default")
    layers = [{"w": np.zeros_like(layer["w"]), "b": np.zeros_like(layer["b"])} for layer in layers]
    layers[-1]["b"] = np.asarray([*mean, *log_std], np.float32)
    return layers


def constant_critics(*values):
    """Critics with Q_i(s, a) = values[i] everywhere."""
    critics = init_critics(np.random.default_rng(0), OBS, ACT, [4], "default", len(values))
    critics = jax.tree_util.tree_map(np.zeros_like, critics)
    critics[-1]["b"] = np.asarray(values, np.float32).reshape(len(values), 1)
    return critics


def critics_rising_in_first_action(n=2):
    """Q_i(s, a) = a_0 + 10 for every critic (one hidden unit passes a_0 + 10 through its ReLU)."""
    critics = constant_critics(*[0.0] * n)
    critics[0]["w"][:, OBS, 0] = 1.0
    critics[0]["b"][:, 0] = 10.0
    critics[1]["w"][:, 0, 0] = 1.0
    return critics


def hand_sample(key, mean, log_std):
    """The policy's reparameterised sample and log-density, computed in NumPy from the same noise."""
    eps = np.asarray(jax.random.normal(key, (BATCH, ACT)))
    std = np.exp(np.asarray(log_std))
    u = np.asarray(mean) + std * eps
    gaussian = -0.5 * eps**2 - np.log(std) - 0.5 * np.log(2 * np.pi)
    log_prob = np.sum(gaussian - np.log(1.0 - np.tanh(u) ** 2), axis=-1)
    return u, log_prob


def batch(rewards, terminated, steps=None):
    rng = np.random.default_rng(1)
    return losses.Batch(obs=jnp.asarray(rng.standard_normal((BATCH, OBS)), jnp.float32),
                     actions=jnp.asarray(np.tanh(rng.standard_normal((BATCH, ACT))), jnp.float32),
                     rewards=jnp.asarray(rewards, jnp.float32), next_obs=jnp.asarray(rng.standard_normal((BATCH, OBS)),
                                                                                       jnp.float32),
                     terminated=jnp.asarray(terminated, jnp.float32),
                     steps=jnp.asarray(steps if steps is not None else [1.0] * BATCH, jnp.float32))


@pytest.mark.parametrize("n_step,steps", [(1, None), (3, [1.0, 2.0, 3.0, 1.0])])
def test_critic_loss_is_the_soft_bellman_error_to_the_smaller_target(n_step, steps):
    key = jax.random.PRNGKey(7)
    mean, log_std = [0.3, -0.2], [-0.5, 0.1]
    rewards, terminated, alpha, gamma = [1.0, -2.0, 0.5, 3.0], [0.0, 1.0, 0.0, 0.0], 0.5, 0.9
    critic, target_critic = constant_critics(1.0, 2.0), constant_critics(3.0, 5.0)

    loss, metrics = losses.critic_loss(critic, target_critic, constant_actor(mean, log_std), jnp.float32(alpha),
                                    batch(rewards, terminated, steps), key, POLICY, CRITICS, gamma, n_step)

    _, next_log_prob = hand_sample(key, mean, log_std)
    discount = gamma ** np.asarray(steps) if n_step > 1 else gamma
    target = np.asarray(rewards) + discount * (1 - np.asarray(terminated)) * (3.0 - alpha * next_log_prob)
    want = 0.5 * (np.mean((1.0 - target) ** 2) + np.mean((2.0 - target) ** 2))
    assert float(loss) == pytest.approx(want, rel=1e-5)
    assert (float(metrics["q1_mean"]), float(metrics["q2_mean"])) == (1.0, 2.0)

    # the gradient moves each critic towards the target (and the target critics not at all)
    grads = jax.grad(lambda c: losses.critic_loss(c, target_critic, constant_actor(mean, log_std), jnp.float32(alpha),
                                               batch(rewards, terminated, steps), key, POLICY, CRITICS, gamma,
                                               n_step)[0])(critic)
    np.testing.assert_allclose(np.asarray(grads[-1]["b"])[:, 0], [np.mean(1.0 - target), np.mean(2.0 - target)],
                               rtol=1e-5)


def test_each_critic_learns_toward_its_own_target_critic_with_target_q_each():
    """FastSAC's critics (target_q=each): critic i's soft target comes from target critic i, no minimum."""
    key = jax.random.PRNGKey(7)
    mean, log_std = [0.3, -0.2], [-0.5, 0.1]
    rewards, terminated, alpha, gamma = [1.0, -2.0, 0.5, 3.0], [0.0, 1.0, 0.0, 0.0], 0.5, 0.9
    critics = dataclasses.replace(CRITICS, target_q="each")
    loss, _ = losses.critic_loss(constant_critics(1.0, 2.0), constant_critics(3.0, 5.0), constant_actor(mean, log_std),
                                 jnp.float32(alpha), batch(rewards, terminated), key, POLICY, critics, gamma)
    _, next_log_prob = hand_sample(key, mean, log_std)
    bootstrap = gamma * (1 - np.asarray(terminated))
    targets = [np.asarray(rewards) + bootstrap * (v - alpha * next_log_prob) for v in (3.0, 5.0)]
    want = 0.5 * (np.mean((1.0 - targets[0]) ** 2) + np.mean((2.0 - targets[1]) ** 2))
    assert float(loss) == pytest.approx(want, rel=1e-5)


def test_the_actor_climbs_the_critics_mean_with_actor_q_mean():
    key = jax.random.PRNGKey(3)
    mean, log_std, alpha = [0.3, -0.2], [-0.5, 0.1], 0.2
    obs = batch([0.0] * BATCH, [0.0] * BATCH).obs
    loss, _ = losses.actor_loss(constant_actor(mean, log_std), constant_critics(2.0, -1.0), jnp.float32(alpha), obs,
                                key, POLICY, dataclasses.replace(CRITICS, actor_q="mean"))
    _, want_log_prob = hand_sample(key, mean, log_std)
    assert float(loss) == pytest.approx(alpha * np.mean(want_log_prob) - 0.5, rel=1e-5)  # mean of 2 and -1


def test_actor_loss_trades_entropy_against_the_smaller_q():
    key = jax.random.PRNGKey(3)
    mean, log_std, alpha = [0.3, -0.2], [-0.5, 0.1], 0.2
    obs = batch([0.0] * BATCH, [0.0] * BATCH).obs

    loss, log_prob = losses.actor_loss(constant_actor(mean, log_std), constant_critics(2.0, -1.0), jnp.float32(alpha),
                                    obs, key, POLICY, CRITICS)

    u, want_log_prob = hand_sample(key, mean, log_std)
    eps = (u - np.asarray(mean)) / np.exp(np.asarray(log_std))
    sizes = np.sum(0.5 * eps**2 + np.abs(log_std) + 1.0 + np.abs(np.log(1.0 - np.tanh(u) ** 2)) + 2.0 * np.abs(u), -1)
    np.testing.assert_array_less(np.abs(np.asarray(log_prob) - want_log_prob), 32 * 2**-24 * sizes)
    assert float(loss) == pytest.approx(alpha * np.mean(want_log_prob) - (-1.0), rel=1e-5)


def test_actor_gradient_moves_the_mean_towards_higher_q():
    """With Q = a_0 + 10 and alpha = 0, d loss / d mean_0 = -mean(1 - tanh(u_0)^2) < 0: descent raises it."""
    key = jax.random.PRNGKey(5)
    mean, log_std = [0.3, -0.2], [-0.5, 0.1]
    obs = batch([0.0] * BATCH, [0.0] * BATCH).obs
    grads = jax.grad(lambda a: losses.actor_loss(a, critics_rising_in_first_action(), jnp.float32(0.0), obs, key,
                                              POLICY, CRITICS)[0])(constant_actor(mean, log_std))
    u, _ = hand_sample(key, mean, log_std)
    d_mean = np.asarray(grads[-1]["b"])[:ACT]
    np.testing.assert_allclose(d_mean, [-np.mean(1.0 - np.tanh(u[:, 0]) ** 2), 0.0], rtol=1e-5, atol=1e-7)
    assert d_mean[0] < 0


def test_alpha_loss_value_and_direction():
    log_prob = jnp.asarray([1.0, 2.0])  # entropy -log_prob: -1 and -2
    log_alpha = jnp.float32(np.log(0.5))
    # target entropy -1: log_prob + target = [0, 1], mean 0.5
    assert float(losses.alpha_loss(log_alpha, log_prob, -1.0)) == pytest.approx(-np.log(0.5) * 0.5, rel=1e-6)
    # entropy below the target (-1.5 < -1): descent raises alpha; above it (-1.5 > -3): lowers it
    assert float(jax.grad(losses.alpha_loss)(log_alpha, log_prob, -1.0)) == pytest.approx(-0.5)
    assert float(jax.grad(losses.alpha_loss)(log_alpha, log_prob, -3.0)) == pytest.approx(1.5)
    # the policy's log-probabilities get no gradient from the alpha loss
    assert float(jnp.abs(jax.grad(losses.alpha_loss, argnums=1)(log_alpha, log_prob, -1.0)).sum()) == 0.0
