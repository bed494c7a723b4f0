"""The SAC maths: squashed-Gaussian log-prob, log-std bounds, action rescaling, Polyak, the update."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from float_bounds import assert_within_bound, mlp_bound
from softac.base import cpus
from softac.learner.networks import layers
from softac.learner import build, losses, policy, sac
from softac.config.sac_config import SACConfig
from softac.learner.metrics import metric_means


def squashed_probability(lo, hi, mean, std):
    """P(lo < tanh(U) <= hi) for U ~ N(mean, std^2): an independent route to the density. In a tail, from erfc:
    a difference of two CDF values near 1 keeps only ~1e-16 / (hi - lo) of the density (1e-2 of its log where
    it is 1e-8)."""
    z_lo, z_hi = ((math.atanh(a) - mean) / (std * math.sqrt(2.0)) for a in (lo, hi))
    if z_lo > 0:
        return 0.5 * (math.erfc(z_lo) - math.erfc(z_hi))
    if z_hi < 0:
        return 0.5 * (math.erfc(-z_hi) - math.erfc(-z_lo))
    return 0.5 * (math.erf(z_hi) - math.erf(z_lo))


@pytest.mark.parametrize("mean,log_std", [(0.0, 0.0), (0.7, -0.5), (-1.5, 0.8), (2.5, -1.5)])
@pytest.mark.numerics
def test_log_prob_matches_numerical_density(mean, log_std):
    std = math.exp(log_std)
    h = 1e-6
    for a in np.linspace(-0.995, 0.995, 41):
        numerical = squashed_probability(a - h, a + h, mean, std) / (2 * h)
        if numerical < 1e-8:
            continue
        u = jnp.array([[math.atanh(a)]], jnp.float64 if jax.config.jax_enable_x64 else jnp.float32)
        ours = float(policy.squashed_gaussian_log_prob(u, jnp.array([[mean]]), jnp.array([[log_std]]))[0])
        # float32: a dozen roundings (2^-24) of terms whose sizes add up to `size` (1.7 of them at most, seen);
        # the central difference is within (h / (1 - |a|))^2 ~ 4e-8 of the density
        z = (math.atanh(a) - mean) / std
        size = 0.5 * z**2 + abs(log_std) + 1.0 + abs(math.log(1.0 - a * a)) + 2.0 * abs(math.atanh(a))
        assert ours == pytest.approx(math.log(numerical), abs=32 * 2**-24 * size + 1e-7), a


@pytest.mark.numerics
def test_log_prob_density_integrates_to_one():
    a = np.linspace(-1 + 1e-7, 1 - 1e-7, 400_001)
    u = jnp.asarray(np.arctanh(a)[:, None], jnp.float32)
    logp = np.asarray(policy.squashed_gaussian_log_prob(u, jnp.full_like(u, 0.4), jnp.full_like(u, -0.3)))
    integrate = getattr(np, "trapezoid", None) or np.trapz  # (NumPy < 2 names it trapz)
    # the quadrature is exact to ~1e-15 here (in float64); the float32 log-density is off by a dozen roundings
    # of its terms, of sizes ~5 where the mass is: 32 * 2^-24 * 5 ~ 1e-5
    assert integrate(np.exp(logp), a) == pytest.approx(1.0, abs=1e-5)


@pytest.mark.numerics
def test_log_prob_is_finite_where_tanh_saturates():
    u = jnp.array([[-40.0], [-12.0], [12.0], [40.0]])
    logp = policy.squashed_gaussian_log_prob(u, jnp.zeros_like(u), jnp.zeros_like(u))
    assert np.all(np.isfinite(np.asarray(logp)))
    # the exact form keeps growing like 2|u| where the naive log(1 - tanh^2 + 1e-6) is stuck at log(1e-6)
    assert float(policy.log_one_minus_tanh_sq(jnp.array(40.0))) == pytest.approx(2 * (math.log(2) - 40), rel=1e-5)


@pytest.mark.numerics
def test_log_prob_sums_over_action_dims():
    u = jnp.array([[0.3, -0.2]])
    mean, log_std = jnp.array([[0.1, 0.0]]), jnp.array([[-0.2, 0.4]])
    both = float(policy.squashed_gaussian_log_prob(u, mean, log_std)[0])
    each = sum(float(policy.squashed_gaussian_log_prob(u[:, i:i + 1], mean[:, i:i + 1], log_std[:, i:i + 1])[0])
               for i in range(2))
    assert both == pytest.approx(each, rel=1e-5)


@pytest.mark.numerics
def test_log_std_bounds():
    raw = jnp.linspace(-50, 50, 101)
    clamped = policy.bound_log_std(raw, -5.0, 2.0, "clamp")
    squashed = policy.bound_log_std(raw, -5.0, 2.0, "tanh")
    for bounded in (clamped, squashed):
        assert float(bounded.min()) >= -5.0 and float(bounded.max()) <= 2.0
    assert float(policy.bound_log_std(jnp.array(0.0), -5.0, 2.0, "tanh")) == pytest.approx(-1.5)
    assert float(policy.bound_log_std(jnp.array(1.0), -5.0, 2.0, "clamp")) == 1.0


@pytest.mark.numerics
def test_softplus_log_std_is_braxs_std_softplus_plus_a_floor():
    """log_std_mode softplus: std = softplus(raw) + exp(log_std_min), no upper bound (Brax's NormalTanhDistribution,
    floor 0.001): at raw 0 the std is log 2 + 0.001; far below, the floor; far above, raw + 0.001."""
    floor = np.log(0.001)
    std = lambda raw: float(np.exp(policy.bound_log_std(jnp.array(raw, jnp.float32), floor, 2.0, "softplus")))
    assert std(0.0) == pytest.approx(np.log(2.0) + 0.001, rel=1e-6)
    assert std(-40.0) == pytest.approx(0.001, rel=1e-5)
    assert std(30.0) == pytest.approx(30.001, rel=1e-6)  # above log_std_max's e^2: not bounded


@pytest.mark.numerics
def test_action_rescaling_with_asymmetric_bounds():
    scaler = policy.ActionScaler(np.array([-1.0, 0.0, -10.0]), np.array([3.0, 10.0, -2.0]))
    np.testing.assert_allclose(scaler.to_env(-np.ones(3)), [-1.0, 0.0, -10.0])
    np.testing.assert_allclose(scaler.to_env(np.ones(3)), [3.0, 10.0, -2.0])
    np.testing.assert_allclose(scaler.to_env(np.zeros(3)), [1.0, 5.0, -6.0])
    x = np.random.default_rng(0).uniform(-1, 1, (100, 3)).astype(np.float32)
    np.testing.assert_allclose(scaler.to_normalised(scaler.to_env(x)), x, atol=1e-6)
    assert np.all(scaler.to_env(np.full(3, 1.5)) <= scaler.high)


@pytest.mark.numerics
def test_polyak_update():
    target = {"w": jnp.zeros(3)}
    online = {"w": jnp.ones(3) * 2.0}
    np.testing.assert_allclose(sac.polyak(target, online, 0.1)["w"], 0.2 * np.ones(3), rtol=1e-6)
    np.testing.assert_allclose(sac.polyak(target, online, 1.0)["w"], online["w"])


def _batch(rng, n_steps, batch, obs_dim, act_dim, terminated=0.0):
    return losses.Batch(
        obs=jnp.asarray(rng.normal(size=(n_steps, batch, obs_dim)), jnp.float32),
        actions=jnp.asarray(rng.uniform(-1, 1, (n_steps, batch, act_dim)), jnp.float32),
        rewards=jnp.asarray(rng.normal(size=(n_steps, batch)), jnp.float32),
        next_obs=jnp.asarray(rng.normal(size=(n_steps, batch, obs_dim)), jnp.float32),
        terminated=jnp.full((n_steps, batch), terminated, jnp.float32),
        steps=jnp.ones((n_steps, batch), jnp.float32),
    )


def _leaves(tree):
    return [np.array(x, copy=True) for x in jax.tree_util.tree_leaves(tree)]  # a view would see donated buffers change


@pytest.mark.numerics
def test_update_moves_targets_by_tau_every_interval():
    cfg = SACConfig().replace(hidden_sizes=[16], tau=0.5, target_update_interval=2, batch_size=8)
    functions = build.build(cfg, 3, 2)
    state = functions.init(0)
    before = _leaves(state.target_critic)
    rng = np.random.default_rng(0)
    state, _ = functions.update(state, _batch(rng, 1, 8, 3, 2))
    for a, b in zip(before, _leaves(state.target_critic), strict=True):
        np.testing.assert_array_equal(a, b)  # 1 update: interval 2 not reached
    online_before = _leaves(state.critic)
    prev_target = _leaves(state.target_critic)
    state, _ = functions.update(state, _batch(rng, 1, 8, 3, 2))
    # after the second update: target = 0.5 * online(after step 2) + 0.5 * old target
    for t_old, online, t_new in zip(prev_target, _leaves(state.critic), _leaves(state.target_critic), strict=True):
        np.testing.assert_allclose(t_new, 0.5 * online + 0.5 * t_old, rtol=1e-5, atol=1e-6)
    assert any(not np.array_equal(a, b) for a, b in zip(online_before, _leaves(state.critic), strict=True))
    assert int(state.n_updates) == 2


def test_gradient_steps_fuse_in_one_call():
    cfg = SACConfig().replace(hidden_sizes=[16], batch_size=8, gradient_steps=5)
    functions = build.build(cfg, 3, 2)
    state = functions.init(0)
    state, totals = functions.update(state, _batch(np.random.default_rng(0), 5, 8, 3, 2))
    assert int(state.n_updates) == 5
    assert (float(totals["critic_steps"]), float(totals["actor_steps"])) == (5.0, 5.0)
    assert set(metric_means(totals)) == {"critic_loss", "actor_loss", "alpha", "alpha_loss", "q1_mean", "q2_mean",
                                             "log_prob_mean"}


def test_configs_differing_only_in_the_updates_numbers_share_one_compiled_update(monkeypatch):
    """Learning rates, gamma, tau, alpha and the entropy target are arguments of the compiled update, not
    constants in it (issue 64): a sweep over them compiles one program; a new shape compiles another. (A process
    that has compiled hundreds of programs before this test drops JAX's caches when a build nears the memory-map
    limit, which would empty the cache counted here: held off for these eight small programs.)"""
    monkeypatch.setattr(build, "release_compiled_programs_near_map_limit", lambda: False)
    # shapes of this test's own (5 observations, 3 actions, 12 units): no other test's program in the cache
    base = SACConfig().replace(hidden_sizes=[12], batch_size=8, autotune_alpha=False)
    batch = _batch(np.random.default_rng(0), 2, 8, 5, 3)

    def trained(cfg):
        functions = build.build(cfg, 5, 3)
        return _leaves(functions.update(functions.init(0), batch)[0])

    first = trained(base)
    programs = build.compiled_update._cache_size()
    others = [trained(base.replace(**change)) for change in (
        dict(actor_lr=1e-3, critic_lr=2e-3), dict(gamma=0.9), dict(tau=0.5), dict(alpha=0.5),
        dict(target_entropy=-0.5, autotune_alpha=True, alpha_lr=1e-2), dict(target_entropy=-3.0, autotune_alpha=True))]
    assert build.compiled_update._cache_size() == programs + 1  # the autotuned ones: one other program for both
    for other in others:  # and each number took effect
        assert any(not np.array_equal(a, b) for a, b in zip(first, other, strict=True))
    trained(base.replace(hidden_sizes=[11]))
    assert build.compiled_update._cache_size() == programs + 2


@pytest.mark.numerics
def test_fixed_alpha_is_not_learned_and_autotune_moves_it():
    rng = np.random.default_rng(0)
    fixed = build.build(SACConfig().replace(hidden_sizes=[16], autotune_alpha=False, alpha=0.2), 3, 2)
    state, totals = fixed.update(fixed.init(0), _batch(rng, 3, 8, 3, 2))
    assert metric_means(totals)["alpha"] == pytest.approx(0.2)
    assert float(jnp.exp(state.log_alpha)) == pytest.approx(0.2)
    tuned = build.build(SACConfig().replace(hidden_sizes=[16], alpha=0.5), 3, 2)
    state, totals = tuned.update(tuned.init(0), _batch(rng, 3, 8, 3, 2))
    assert float(jnp.exp(state.log_alpha)) != pytest.approx(0.5)
    assert tuned.target_entropy == -2.0


@pytest.mark.numerics
def test_terminated_transitions_do_not_bootstrap():
    """With gamma=1 and terminated=1 the critic's target is the reward alone."""
    cfg = SACConfig().replace(hidden_sizes=[16], gamma=1.0, critic_lr=0.05, batch_size=16)
    functions = build.build(cfg, 2, 1)
    state = functions.init(1)
    rng = np.random.default_rng(1)
    batch = _batch(rng, 1, 16, 2, 1, terminated=1.0)
    batch = batch._replace(rewards=jnp.full((1, 16), 3.0), next_obs=batch.next_obs * 100.0)
    batches = losses.Batch(*[jnp.repeat(x, 300, axis=0) for x in batch])
    state, totals = functions.update(state, batches)
    assert metric_means(totals)["q1_mean"] == pytest.approx(3.0, abs=0.15)


@pytest.mark.numerics
def test_n_step_target_bootstraps_with_gamma_to_the_steps():
    """An n-step batch row that summed `steps` rewards bootstraps with gamma^steps: the update equals
    one-step SAC with gamma^steps in place of gamma, on the same state, batch and keys."""
    base = SACConfig().replace(hidden_sizes=[16], batch_size=8, gamma=0.9)
    n_step = build.build(base.replace(n_step=3), 3, 2)
    batch = _batch(np.random.default_rng(3), 1, 8, 3, 2)
    for steps in (1.0, 2.0, 3.0):
        one_step = build.build(base.replace(gamma=0.9**steps), 3, 2)
        got, _ = n_step.update(n_step.init(0), batch._replace(steps=jnp.full((1, 8), steps, jnp.float32)))
        want, _ = one_step.update(one_step.init(0), batch)
        for a, b in zip(_leaves(got.critic), _leaves(want.critic), strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    same, _ = n_step.update(n_step.init(0), batch._replace(steps=jnp.full((1, 8), 2.0, jnp.float32)))
    plain, _ = n_step.update(n_step.init(0), batch)
    assert any(not np.allclose(a, b) for a, b in zip(_leaves(same.critic), _leaves(plain.critic), strict=True))


def test_delayed_policy_updates_and_critic_ensemble():
    cfg = SACConfig.preset("cleanrl").replace(hidden_sizes=[16], n_critics=3, init="orthogonal")
    functions = build.build(cfg, 3, 2)
    state = functions.init(0)
    assert jax.tree_util.tree_leaves(state.critic)[0].shape[0] == 3
    actor_before = _leaves(state.actor)
    state, _ = functions.update(state, _batch(np.random.default_rng(0), 1, 8, 3, 2))
    # step 1: no actor step
    assert all(np.array_equal(a, b) for a, b in zip(actor_before, _leaves(state.actor), strict=True))
    state, _ = functions.update(state, _batch(np.random.default_rng(1), 1, 8, 3, 2))
    assert any(not np.array_equal(a, b) for a, b in zip(actor_before, _leaves(state.actor), strict=True))


def _adam_steps(opt_state) -> int:
    return int(opt_state[0].count)


@pytest.mark.parametrize("frequency,delay,actor_steps", [(1, 1, 6), (2, 1, 6), (1, 2, 3), (1, 3, 2), (2, 3, 2)])
def test_policy_schedule_counts_actor_and_alpha_steps(frequency, delay, actor_steps):
    """Over 6 critic steps: CleanRL's policy_frequency catches up (same count), TD3's policy_delay does not."""
    cfg = SACConfig().replace(hidden_sizes=[16], batch_size=8, policy_frequency=frequency, policy_delay=delay)
    functions = build.build(cfg, 3, 2)
    state, _ = functions.update(functions.init(0), _batch(np.random.default_rng(0), 6, 8, 3, 2))
    assert _adam_steps(state.critic_opt) == 6
    assert (_adam_steps(state.actor_opt), _adam_steps(state.alpha_opt)) == (actor_steps, actor_steps)


@pytest.mark.numerics
def test_bfloat16_matmuls_stay_close_to_float32():
    f32 = build.build(SACConfig().replace(hidden_sizes=[64, 64]), 3, 2)
    bf16 = build.build(SACConfig().replace(hidden_sizes=[64, 64], matmul_dtype="bfloat16"), 3, 2)
    state = f32.init(0)
    obs = jnp.asarray(np.random.default_rng(0).normal(size=(32, 3)), jnp.float32)
    a32, a16 = f32.act_deterministic(state.actor, (), obs), bf16.act_deterministic(state.actor, (), obs)
    assert a16.dtype == jnp.float32
    # bf16 keeps 8 significant bits of the 64x64 layer's inputs and weights (2^-9 relative each): a bf16-sized
    # tolerance, CPU-independent (float32 sums differ across CPUs by ~1e-6 of it)
    np.testing.assert_allclose(np.asarray(a16), np.asarray(a32), atol=2e-2)
    new_state, metrics = bf16.update(bf16.init(0), _batch(np.random.default_rng(0), 2, 8, 3, 2))
    assert all(np.isfinite(float(v)) for v in metrics.values())
    assert jax.tree_util.tree_leaves(new_state.actor)[0].dtype == jnp.float32  # parameters stay f32


@pytest.mark.numerics
def test_bfloat16_matmul_gradients_match_float32():
    from softac.learner.networks.layers import bf16_matmul

    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.normal(size=(32, 48)), jnp.float32)
    w = jnp.asarray(rng.normal(size=(48, 24)) / 7.0, jnp.float32)
    upstream = jnp.asarray(rng.normal(size=(32, 24)), jnp.float32)
    loss32 = lambda x, w: jnp.sum(jnp.tanh(x @ w) * upstream)
    loss16 = lambda x, w: jnp.sum(jnp.tanh(bf16_matmul(x, w)) * upstream)
    (dx32, dw32), (dx16, dw16) = jax.grad(loss32, (0, 1))(x, w), jax.grad(loss16, (0, 1))(x, w)
    assert dx16.shape == x.shape and dw16.shape == w.shape and dx16.dtype == dw16.dtype == jnp.float32
    for g16, g32 in ((dx16, dx32), (dw16, dw32)):  # bf16 inputs (8-bit mantissa), f32 accumulation
        assert float(jnp.linalg.norm(g16 - g32) / jnp.linalg.norm(g32)) < 2e-2


@pytest.mark.numerics
def test_critic_layer_norm_normalises_hidden_features():
    from softac.learner.networks import critics_apply, init_critics
    from softac.learner.networks.layers import layer_norm

    x = np.random.default_rng(0).normal(3.0, 5.0, (4, 64)).astype(np.float32)
    h = layer_norm(jnp.asarray(x))
    # float32 means over 64 values (gamma_64 = 64 * 2^-24 ~ 4e-6 of their sizes, ~1 in units of h)
    np.testing.assert_allclose(np.asarray(h.mean(-1)), 0.0, atol=1e-5)
    var = x.astype(np.float64).var(-1)  # the std is sqrt(var / (var + eps)), eps = 1e-5: a few gamma_64 off
    np.testing.assert_allclose(np.asarray(h.std(-1)), np.sqrt(var / (var + 1e-5)), rtol=2e-5)
    params = init_critics(np.random.default_rng(0), 3, 2, [32, 32], "default", 2)
    obs, act = jnp.ones((5, 3)) * 1000.0, jnp.zeros((5, 2))
    plain = critics_apply(params, obs, act, "relu")[0]
    normed = critics_apply(params, obs, act, "relu", normalize=True)[0]
    assert normed.shape == plain.shape == (2, 5)
    assert float(jnp.abs(normed).max()) < 0.1 * float(jnp.abs(plain).max())  # huge inputs stay bounded


@pytest.mark.numerics
def test_unrolled_and_vmapped_critics_agree():
    from softac.learner.networks import critics_apply, init_critics

    params = init_critics(np.random.default_rng(0), 3, 2, [32, 32], "default", 3)
    rng = np.random.default_rng(1)
    obs, act = jnp.asarray(rng.normal(size=(7, 3)), jnp.float32), jnp.asarray(rng.uniform(-1, 1, (7, 2)), jnp.float32)
    # two float32 programs that may sum in different orders: each within the float32 bound of the exact Q-values
    x = np.concatenate([np.asarray(obs), np.asarray(act)], axis=-1)
    exact = [mlp_bound([{k: v[i] for k, v in layer.items()} for layer in params], x, "relu") for i in range(3)]
    for unroll in (True, False):
        q = np.asarray(critics_apply(params, obs, act, "relu", unroll=unroll)[0])
        for i, (reference, bound) in enumerate(exact):
            assert_within_bound(q[i], reference[:, 0], bound[:, 0], f"critic {i}, unroll={unroll}")


def test_matmul_dtype_auto_picks_bfloat16_only_where_it_is_fast(monkeypatch):
    monkeypatch.setattr(build, "cpu_has_bf16", lambda: False)
    assert build.build(SACConfig().replace(matmul_dtype="auto"), 3, 2).matmul_dtype == "float32"
    monkeypatch.setattr(build, "cpu_has_bf16", lambda: True)
    monkeypatch.setattr(build, "jit_keeps_bf16_rounding", lambda: True)
    assert build.build(SACConfig().replace(matmul_dtype="auto"), 3, 2).matmul_dtype == "bfloat16"
    assert build.build(SACConfig().replace(matmul_dtype="float32"), 3, 2).matmul_dtype == "float32"
    # a JAX whose compiler drops the bf16 rounding (0.4.30 on a CPU) multiplies in float32 anyway: auto says so
    monkeypatch.setattr(build, "jit_keeps_bf16_rounding", lambda: False)
    assert build.build(SACConfig().replace(matmul_dtype="auto"), 3, 2).matmul_dtype == "float32"


SAPPHIRE_RAPIDS = {"avx2", "avx512f", "avx512_vnni", "avx512_bf16", "amx_bf16", "amx_int8", "amx_tile"}
ZEN5 = {"avx2", "avx512f", "avx512_vnni", "avx512_bf16"}


@pytest.mark.parametrize("cpu, isa, changed_by_avx2_limit", [
    (SAPPHIRE_RAPIDS, "AMX", True),
    (ZEN5, "AVX512_BF16", True),
    ({"avx2", "avx512f"}, "AVX512", True),
    ({"avx", "avx2", "fma", "sse4_2"}, "AVX2", False),  # the AVX2-only AMD EPYC: test-isa would rerun the same code
    ({"sse4_2"}, "SSE4_2", False),
    (set(), None, True),  # no /proc/cpuinfo, or an ARM CPU: cannot tell, so test-isa runs
])
def test_cpu_isa_is_the_newest_instruction_set_xla_knows_and_the_cpu_has(monkeypatch, cpu, isa,
                                                                         changed_by_avx2_limit):
    monkeypatch.setattr(cpus, "cpu_flags", lambda: cpu)
    assert cpus.cpu_isa() == isa
    assert cpus.xla_limit_changes_code("AVX2") is changed_by_avx2_limit
    assert cpus.xla_limit_changes_code("avx2") is changed_by_avx2_limit  # XLA matches the names in any case
    assert cpus.xla_limit_changes_code("PENTIUM")  # a limit XLA does not know: it warns and runs unlimited
    assert not cpus.xla_limit_changes_code("AMX_FP16") or isa is None  # the newest: never a limit


@pytest.mark.parametrize("cpu,xla_flags,bf16", [
    ({"avx2", "fma"}, "", False),
    (ZEN5, "", True),
    (SAPPHIRE_RAPIDS, "", True),
    ({"avx2", "amx_bf16"}, "", True),
    (SAPPHIRE_RAPIDS, "--xla_cpu_max_isa=AVX2", False),  # XLA kept off the bf16 units: auto is float32
    (SAPPHIRE_RAPIDS, "--xla_dump_to=/tmp/x --xla_cpu_max_isa=avx512_vnni", False),  # matched in any case
    (ZEN5, "--xla_cpu_max_isa=SSE4_2", False),
    (ZEN5, "--xla_cpu_max_isa=AVX512_BF16", True),
    (SAPPHIRE_RAPIDS, "--xla_cpu_max_isa=AVX512_BF16", True),
    ({"avx2", "amx_bf16"}, "--xla_cpu_max_isa=AVX512_BF16", False),  # AMX is above that limit
    ({"avx2", "amx_bf16"}, "--xla_cpu_max_isa=AMX", True),
    (ZEN5, "--xla_cpu_max_isa=AMX_FP16", True),
    (ZEN5, "--xla_cpu_max_isa=AVX2 --xla_cpu_max_isa=AMX", True),  # the last one counts, as in XLA
    (ZEN5, "--xla_cpu_max_isa=PENTIUM", True),  # XLA ignores a value it does not know
    ({"avx2"}, "--xla_cpu_max_isa=AMX", False),  # a limit adds no units
])
@pytest.mark.numerics
def test_cpu_has_bf16_honours_xla_max_isa(monkeypatch, cpu, xla_flags, bf16):
    # probed (and cached) before XLA_FLAGS changes: a compile under flags the JAX does not know aborts (0.4.30)
    keeps_rounding = layers.jit_keeps_bf16_rounding()
    monkeypatch.setattr(cpus, "cpu_flags", lambda: cpu)
    monkeypatch.setenv("XLA_FLAGS", xla_flags)
    assert cpus.cpu_has_bf16() is bf16
    if jax.default_backend() == "cpu":
        # JAX 0.4.30's CPU compiler drops the bf16 rounding: auto is float32 there, what it computes anyway
        expected = bf16 and keeps_rounding
        assert build.resolve_matmul_dtype("auto") == ("bfloat16" if expected else "float32")
