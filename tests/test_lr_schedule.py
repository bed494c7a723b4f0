"""lr_schedule: learning rates that fall linearly with the env steps (SB3's and RL Zoo's lin_ schedules)."""

import jax
import numpy as np
import pytest

from conftest import assert_same_training, straight_and_resumed, tiny_config
from softac.learner import build, losses
from softac.config.sac_config import ConfigError, SACConfig
from softac.learner.learner import Learner

U = 2.0**-24  # float32's unit roundoff


def _batch(rng, obs_dim=3, act_dim=2, batch=16):
    f = lambda *shape: np.asarray(rng.normal(size=shape), np.float32)
    return losses.Batch(obs=f(1, batch, obs_dim), actions=np.tanh(f(1, batch, act_dim)), rewards=f(1, batch),
                     next_obs=f(1, batch, obs_dim), terminated=np.zeros((1, batch), np.float32),
                     steps=np.ones((1, batch), np.float32))


def _one_update(config: SACConfig, scale):
    functions = build.build(config, 3, 2)
    start = functions.init(0)
    before = [np.array(x, copy=True) for x in jax.tree_util.tree_leaves((start.actor, start.critic, start.log_alpha))]
    args = () if scale is None else (np.float32(scale),)
    state, _ = functions.update(start, _batch(np.random.default_rng(1)), None, *args)
    after = [np.asarray(x) for x in jax.tree_util.tree_leaves((state.actor, state.critic, state.log_alpha))]
    return before, after


@pytest.mark.parametrize("decay", [0.0, 0.01])  # Adam, and AdamW (its decay is scaled by the rate as well)
def test_a_scaled_update_is_the_update_at_the_scaled_rates(decay):
    """Scaling one step's updates by f is Adam's (and AdamW's) step at f times the rates of actor, critics and alpha.
    With f = 1/4 (a power of two: the scaling commutes with rounding) bit for bit; with f = 0.3 within the rounding
    of the two extra products (the update times f, the rate times f) and of each parameter's sum."""
    base = SACConfig().replace(hidden_sizes=[16], batch_size=16, weight_decay=decay, actor_lr=1e-3, critic_lr=1e-3,
                               alpha_lr=1e-3)
    for f in (0.25, 0.3):
        before, scaled = _one_update(base, f)
        _, direct = _one_update(base.replace(actor_lr=1e-3 * f, critic_lr=1e-3 * f, alpha_lr=1e-3 * f), None)
        moved = False
        for p0, a, b in zip(before, scaled, direct):
            if f == 0.25:
                np.testing.assert_array_equal(a, b)
            step = np.abs(b.astype(np.float64) - p0)
            bound = 4 * U * step + U * (np.abs(a) + np.abs(b))
            assert np.all(np.abs(a.astype(np.float64) - b) <= bound)
            moved |= bool(np.any(step > 0))
        assert moved


def test_the_schedule_falls_linearly_with_the_env_steps_to_its_end_fraction():
    learner = Learner.__new__(Learner)
    learner.config = SACConfig().replace(total_steps=1000, lr_schedule="linear", lr_end_fraction=0.1)
    assert [float(learner.lr_scale(step)) for step in (0, 500, 1000, 1500)] == pytest.approx([1.0, 0.55, 0.1, 0.1])
    learner.config = learner.config.replace(lr_end_fraction=0.0)
    assert float(learner.lr_scale(250)) == pytest.approx(0.75)  # SB3's lin_: progress remaining x the rate
    learner.config = SACConfig()
    assert learner.lr_scale(500) is None  # constant rates: the update is the one without a schedule


def test_a_linear_schedule_trains_and_resumes_exactly(tmp_path):
    """N + M == N+M with the rates falling over the run (the schedule follows the env step, which the checkpoint
    holds), down to 0 at total_steps."""
    cfg = tiny_config(learning_starts=100, total_steps=500, lr_schedule="linear")
    straight, resumed = straight_and_resumed(cfg, tmp_path, 300, 200)
    assert_same_training(straight, resumed)
    assert float(straight.learner.lr_scale(500)) == 0.0


def test_bad_schedule_settings_are_refused():
    with pytest.raises(ConfigError, match="lr_schedule"):
        SACConfig().replace(lr_schedule="cosine")
    with pytest.raises(ConfigError, match="lr_end_fraction"):
        SACConfig().replace(lr_end_fraction=1.5)
