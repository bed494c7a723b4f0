"""XQC's and FlashSAC's pieces besides the categorical critic (issue 66), each against a hand computation or its
authors' rule: the bn_mlp and flashsac networks' forward passes (float64 references), their weight projections
(XQC's unit kernels; FlashSAC's unit kernels and normalisations at norm sqrt(width)) after every step, FlashSAC's
target entropy from a fixed std, its noise repetition (holds drawn from a truncated Zeta distribution) and an
exact resume of both presets' settings at a tiny size.

Float bounds: the networks run in float32 against float64 references on inputs of unit size; rel=1e-4 (and an
absolute 1e-5) is ~1,700 float32 roundings for a few hundred operations per output."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softac.config.sac_config import ConfigError, SACConfig
from softac.learner import build
from softac.learner.metrics import metric_means
from softac.learner.networks import NETWORKS
from softac.learner.networks.layers import BatchRenorm
from softac.replay.exploration import RepeatedNoise, truncated_zeta_cdf

from conftest import assert_same_training, straight_and_resumed
from test_crossq import _batches

NORM = BatchRenorm(0.99, 1e-5)


def _random_stats(rng, tree):
    """Running statistics of the shapes in `tree` away from their initial (0, 1), so the references use them."""
    return jax.tree_util.tree_map(lambda a: (rng.uniform(0.5, 2.0, a.shape) if np.all(a == 1) else
                                             rng.normal(0, 0.3, a.shape)).astype(np.float32), tree)


def _bn(x, layer, stats, eps):
    return (x - stats["mean"]) / np.sqrt(stats["var"] + eps) * layer["norm_scale"] + layer["norm_bias"]


def _float64(tree):
    return jax.tree_util.tree_map(lambda a: np.asarray(a, np.float64), tree)


def _evaluated(network, seed):
    """A kind's network (5 inputs, two layers of 8, 3 outputs) with its initial parameters perturbed and random
    running statistics, and its features on 4 random rows in evaluation mode: (params, stats, x, features)."""
    rng = np.random.default_rng(seed)
    kind = NETWORKS[network]
    params = kind.init(rng, 5, [8, 8], 3, "orthogonal", 1.0)
    params = jax.tree_util.tree_map(lambda a: (a + rng.normal(0, 0.1, a.shape)).astype(np.float32), params)
    stats = _random_stats(rng, kind.init_stats(5, [8, 8], 3))
    x = rng.normal(size=(4, 5)).astype(np.float32)
    features, _ = kind.features(params, stats, jnp.asarray(x), "relu", "float32", batch_renorm=NORM, train=False)
    return params, stats, x, features


@pytest.mark.numerics
def test_bn_mlp_is_batch_norm_on_the_input_then_dense_batch_norm_relu_per_layer():
    params, stats, x, features = _evaluated("bn_mlp", seed=0)
    out = np.asarray(features @ params["head"]["w"] + params["head"]["b"])

    p, s = _float64(params), _float64(stats)
    h = _bn(x.astype(np.float64), p["input"], s["input"], NORM.eps)
    for layer, layer_stats in zip(p["layers"], s["layers"]):
        h = np.maximum(_bn(h @ layer["w"], layer, layer_stats, NORM.eps), 0.0)  # no bias before the norm
    np.testing.assert_allclose(out, h @ p["head"]["w"] + p["head"]["b"], rtol=1e-4, atol=1e-5)
    assert "b" not in params["layers"][0]


@pytest.mark.numerics
def test_flashsac_is_an_embedding_inverted_residual_blocks_and_an_rms_norm():
    params, stats, x, features = _evaluated("flashsac", seed=1)
    assert params["blocks"][0]["w1"].shape == (8, 32) and params["blocks"][0]["w2"].shape == (32, 8)

    p, s = _float64(params), _float64(stats)
    h = _bn(x.astype(np.float64), p["input"], s["input"], NORM.eps) @ p["embed"]["w"]
    for block, block_stats in zip(p["blocks"], s["blocks"]):
        inner = np.maximum(_bn(h @ block["w1"], block["norm1"], block_stats["norm1"], NORM.eps), 0.0)
        h = h + np.maximum(_bn(inner @ block["w2"], block["norm2"], block_stats["norm2"], NORM.eps), 0.0)
    want = h / np.sqrt(np.mean(h**2, axis=-1, keepdims=True) + 1e-6) * p["head"]["rms_scale"]
    np.testing.assert_allclose(np.asarray(features), want, rtol=1e-4, atol=1e-5)


@pytest.mark.numerics
@pytest.mark.parametrize("network", ["bn_mlp", "flashsac"])
def test_weight_norm_keeps_each_kinds_parameters_where_its_authors_do_after_every_step(network):
    cfg = SACConfig().replace(crossq=True, network=network, weight_norm=True, target_critics="on", n_atoms=11,
                              hidden_sizes=[16, 16], batch_size=8)
    fns = build.build(cfg, 3, 2)
    state, totals = fns.update(fns.init(0), _batches(np.random.default_rng(0), 3, 8))
    assert all(np.isfinite(v) for v in metric_means(totals).values())
    for params, stacked in ((state.actor, False), (state.critic, True)):
        if network == "bn_mlp":
            kernels = [params["head"]["w"]] + [layer["w"] for layer in params["layers"]]
        else:
            kernels = [params["head"]["w"], params["embed"]["w"]] + [b[k] for b in params["blocks"] for k in ("w1", "w2")]
        for w in kernels:  # each unit's incoming weights: unit norm (its column, the input axis)
            np.testing.assert_allclose(np.linalg.norm(np.asarray(w), axis=-2), 1.0, rtol=1e-5)
        if network == "flashsac":  # a normalisation's (scale, bias) as one vector, and the RMSNorm's scale: sqrt(width)
            norms = [params["input"]] + [b[k] for b in params["blocks"] for k in ("norm1", "norm2")]
            for layer in norms:
                width = layer["norm_scale"].shape[-1]
                joint = np.sqrt(np.sum(np.square(layer["norm_scale"]) + np.square(layer["norm_bias"]), axis=-1))
                np.testing.assert_allclose(joint, np.sqrt(width), rtol=1e-5)
            rms = np.asarray(params["head"]["rms_scale"])
            np.testing.assert_allclose(np.linalg.norm(rms, axis=-1), np.sqrt(rms.shape[-1]), rtol=1e-5)
        bias = np.asarray(params["head"]["b"])  # free: the actor's [mean, log std] or the critics' 11 logits
        assert bias.shape[-1] == (11 if stacked else 4) and bias.ndim == (2 if stacked else 1)


def test_flashsacs_target_entropy_is_a_gaussians_of_the_fixed_std():
    target = build.build(SACConfig().replace(hidden_sizes=[8], target_entropy_std=0.15), 3, 6).target_entropy
    assert target == pytest.approx(0.5 * 6 * np.log(2 * np.pi * np.e * 0.15**2))  # -2.87 for 6 action dims
    assert build.build(SACConfig().replace(hidden_sizes=[8], target_entropy_std=0.15, target_entropy=-1.0), 3,
                       6).target_entropy == -1.0  # a number given wins


def test_repeated_noise_holds_each_draw_for_a_zeta_distributed_number_of_steps():
    cdf = truncated_zeta_cdf(2.0, 16)
    pmf = np.diff(np.concatenate([[0.0], cdf]))
    np.testing.assert_allclose(pmf, (1.0 / np.arange(1, 17) ** 2) / np.sum(1.0 / np.arange(1, 17) ** 2))
    noise = RepeatedNoise(2.0, 16, n_envs=3, act_dim=2, seed=0)
    draws = [noise.next().copy() for _ in range(20_000)]
    holds, run = [], 1
    for a, b in zip(draws, draws[1:]):
        if np.array_equal(a, b):
            run += 1
        else:
            holds.append(run)
            run = 1
    holds = np.asarray(holds)
    assert holds.max() <= 16 and draws[0].shape == (3, 2)
    seen = np.bincount(holds, minlength=17)[1:] / len(holds)
    assert np.abs(seen - pmf).max() < 0.02  # ~4,000 holds: a few standard errors of each frequency
    assert not np.array_equal(draws[0][0], draws[0][1])  # each env its own noise, held together


def test_repeated_noise_resumes_its_hold_exactly():
    noise = RepeatedNoise(2.0, 16, 2, 3, seed=4)
    for _ in range(7):
        noise.next()
    meta, arrays = noise.checkpoint_parts()
    again = RepeatedNoise(2.0, 16, 2, 3, seed=99)
    again.restore(meta, arrays)
    for _ in range(40):
        np.testing.assert_array_equal(noise.next(), again.next())


@pytest.mark.parametrize("values,fragment", [
    ({"network": "flashsac"}, "network"),  # needs crossq's batch statistics
    ({"network": "bn_mlp"}, "network"),
    ({"crossq": True, "network": "flashsac", "hidden_sizes": [32, 16]}, "hidden_sizes"),
    ({"exploration_noise": "held"}, "exploration_noise"),
    ({"noise_repeat_max": 0}, "noise_repeat_max"),
    ({"target_entropy_std": -0.1}, "target_entropy_std"),
    ({"batch_norm_eps": 0.0}, "batch_norm_eps"),
])
def test_settings_that_cannot_work_are_refused(values, fragment):
    with pytest.raises(ConfigError, match=fragment):
        SACConfig().replace(**values)


@pytest.mark.exact
@pytest.mark.parametrize("preset", ["xqc", "flashsac"])
def test_the_presets_settings_resume_exactly_at_a_tiny_size(tiny, tmp_path, preset):
    """The preset's every flag (networks, projections, categorical critics, reward scale, noise, delays) at a
    test's widths and budget: 300 + 200 steps split at 300 train as 500 straight."""
    settings = SACConfig.preset(preset).to_dict()
    keep = {k: settings[k] for k in ("crossq", "network", "weight_norm", "target_critics", "tau", "batch_norm_eps",
                                     "n_atoms", "categorical_target", "reward_scale", "alpha", "target_entropy_std",
                                     "target_entropy_scale", "log_std_mode", "log_std_min", "policy_delay",
                                     "exploration_noise", "init", "lr_schedule", "lr_end_fraction")}
    cfg = tiny(n_envs=2, eval_interval=300, hidden_sizes=[16, 16], actor_hidden_sizes=[], critic_hidden_sizes=[],
               batch_renorm_warmup=10**9, **keep)
    straight, resumed = straight_and_resumed(cfg, tmp_path, 300, 200)
    assert_same_training(straight, resumed)
    assert (tmp_path / "straight" / "eval.csv").read_text() == (tmp_path / "split" / "eval.csv").read_text()
