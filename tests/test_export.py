"""`softac export`: the ONNX graph and the NumPy forward pass act as agent.predict(obs, deterministic=True)
does (obs_norm, CrossQ's batch renormalisation, SimBa's residual blocks, every activation, asymmetric action
bounds), without JAX.

XLA (on each CPU its own way), NumPy and onnxruntime sum in different orders, so their float32 actions differ
in the last bits: each program is checked against the float64 reference of the network, within the bound
that float_bounds derives for any float32 evaluation of it, not against another program through a fixed
tolerance."""

import ast
import hashlib
import importlib.util
from pathlib import Path

import numpy as np
import onnxruntime
import pytest

import softac
from conftest import TESTS, assert_clean_error, child_env, run_cli, tiny_config
from float_bounds import action_bound, assert_within_bound
from softac import SAC, SoftacError
from softac.outputs.export import export_policy
from softac.learner.networks.layers import jit_keeps_bf16_rounding

EXPORT_NUMPY = Path(softac.__file__).parent / "learner" / "numpy_forward.py"
DRIFT = "softac_test_envs:Drift-v0"  # actions in [-1, 3]
TRAINED = {  # a few hundred steps each, so that the weights, obs statistics and batch statistics have moved
    "sac": lambda: tiny_config(DRIFT, learning_starts=100),
    "obs_norm": lambda: tiny_config(DRIFT, learning_starts=100, obs_norm=True),
    # 7 action dimensions: the mean's columns are cut from the actor's [mean, log_std] output correctly
    "crossq": lambda: tiny_config("Pusher-v5", learning_starts=100, crossq=True, obs_norm=True),
    # bf16 matmuls in the 32x32 hidden layer (and in Pusher's 23x32 input layer, its batch renormalisation
    # then kept apart from the weights): the export rounds as JAX does
    "sac-bf16": lambda: tiny_config(DRIFT, learning_starts=100, obs_norm=True, matmul_dtype="bfloat16"),
    "crossq-bf16": lambda: tiny_config("Pusher-v5", learning_starts=100, crossq=True, matmul_dtype="bfloat16"),
    # the deployed policy is the actor's moving average (and its batch statistics'), not the actor
    "crossq-averaged": lambda: tiny_config("Pusher-v5", learning_starts=100, crossq=True, policy_average_tau=0.05),
    # the actor outputs the mean alone, clipped to [-2, 2] before tanh (issue 43)
    "gsde": lambda: tiny_config(DRIFT, learning_starts=100, exploration_noise="gsde"),
    # SimBa actors: an embedding, pre-LayerNorm residual blocks, a final LayerNorm (issue 42)
    "simba": lambda: tiny_config(DRIFT, learning_starts=100, network="simba", hidden_sizes=[16],
                                 critic_hidden_sizes=[32, 32], obs_norm=True),
    # bf16 in Pusher's 23x32 embedding and the blocks' 32x128 and 128x32 layers, not in the 32x14 output layer
    "simba-bf16": lambda: tiny_config("Pusher-v5", learning_starts=100, network="simba", critic_hidden_sizes=[32],
                                      matmul_dtype="bfloat16"),
    # XQC's actor (issue 66): batch normalisation on the input and before each activation, kernels at unit norm
    "bn_mlp": lambda: tiny_config("Pusher-v5", learning_starts=100, crossq=True, network="bn_mlp", weight_norm=True,
                                  target_critics="on", n_atoms=11, reward_scale="std"),
    "bn_mlp-bf16": lambda: tiny_config("Pusher-v5", learning_starts=100, crossq=True, network="bn_mlp",
                                       weight_norm=True, matmul_dtype="bfloat16"),
    # FlashSAC's actor: input batch norm, an embedding, inverted residual blocks with batch norm, an RMSNorm
    "flashsac": lambda: tiny_config("Pusher-v5", learning_starts=100, crossq=True, network="flashsac",
                                    hidden_sizes=[16, 16], weight_norm=True, target_critics="on", n_atoms=11,
                                    batch_norm_eps=1e-5, reward_scale="std_max"),
    "flashsac-bf16": lambda: tiny_config("Pusher-v5", learning_starts=100, crossq=True, network="flashsac",
                                         hidden_sizes=[32], weight_norm=True, matmul_dtype="bfloat16"),
    # FastSAC's actor (issue 67): LayerNorm (no scale or bias) before each SiLU, a zero-initialised output layer
    "fastsac": lambda: tiny_config("Pusher-v5", learning_starts=100, activation="silu", actor_layer_norm=True,
                                   zero_actor_head=True, log_std_mode="tanh", log_std_min=-5.0, log_std_max=0.0),
    # Brax's MLP: LayerNorm (with its learned scale and bias) after each hidden activation, LeCun-uniform weights, a
    # softplus std
    "brax": lambda: tiny_config("Pusher-v5", learning_starts=100, actor_layer_norm=True, layer_norm_position="after",
                                layer_norm_affine=True, init="lecun_uniform", log_std_mode="softplus",
                                log_std_min=-6.9, warmup_actions="policy"),
}


def copied_policy_forward():
    """policy_forward loaded from numpy_forward.py's file alone, as a user who copied the file would use it."""
    spec = importlib.util.spec_from_file_location("copied_export_numpy", EXPORT_NUMPY)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.policy_forward


def numpy_actions(path: Path, obs: np.ndarray) -> np.ndarray:
    with np.load(path) as npz:
        return copied_policy_forward()(dict(npz), obs)


def onnx_actions(path: Path, obs: np.ndarray) -> np.ndarray:
    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return session.run(["action"], {"obs": obs})[0]


FAR = 20  # observations far outside the episodes' that env_observations appends


def env_observations(agent: SAC, n: int = 300) -> np.ndarray:
    """Observations of random-action episodes, plus FAR far outside them (where obs_norm clips)."""
    env = agent.make_env()
    env.action_space.seed(0)
    obs, _ = env.reset(seed=0)
    rows = []
    while len(rows) < n:
        rows.append(obs)
        obs, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            obs, _ = env.reset()
    env.close()
    rows = np.asarray(rows, np.float32)
    return np.concatenate([rows, 50.0 * rows[:FAR]])


def assert_predict_acts_as_the_network(agent: SAC, obs: np.ndarray) -> None:
    """predict()'s actions, for a batch and for one observation, within the float32 bound of the exact ones."""
    reference, bound = action_bound(agent, obs, program_matmul_dtype())
    assert_within_bound(agent.predict(obs, deterministic=True), reference, bound, "predict()")
    assert_within_bound(agent.predict(obs[0], deterministic=True), reference[0], bound[0], "predict(), one obs")


def program_matmul_dtype() -> str | None:
    """How predict() and the exports multiply: as the config says, or in float32 where this JAX's compiled bf16
    layers skip the rounding (JAX 0.4.30: networks.jit_keeps_bf16_rounding), and the export with them."""
    return None if jit_keeps_bf16_rounding() else "float32"


def assert_exports_act_as_predict(agent: SAC, directory: Path, obs: np.ndarray) -> np.ndarray:
    """The ONNX graph's and the NumPy pass's actions (for a batch, a batch of one and one observation) and
    predict()'s are each within the float32 bound of the exact ones, so within twice the bound of each other
    whatever order each program sums in; returns the bound."""
    reference, bound = action_bound(agent, obs, program_matmul_dtype())
    assert_predict_acts_as_the_network(agent, obs)
    onnx_path = export_policy(agent, directory / "policy.onnx", "onnx")
    numpy_path = export_policy(agent, directory / "policy.npz", "numpy")
    for name, actions in (("onnx", onnx_actions(onnx_path, obs)), ("numpy", numpy_actions(numpy_path, obs))):
        assert actions.dtype == np.float32 and actions.shape == reference.shape
        assert_within_bound(actions, reference, bound, name)
    assert_within_bound(onnx_actions(onnx_path, obs[:1]), reference[:1], bound[:1], "onnx, a batch of one")
    assert_within_bound(numpy_actions(numpy_path, obs[0]), reference[0], bound[0], "numpy, one observation")
    return bound


def assert_bound_is_tight(agent: SAC, bound: np.ndarray, bf16: bool) -> None:
    """The bound is far below what a wrong export is off by (a dropped normalisation or fold, a wrong clip or
    layer order: 1e-2 of the action range and more). In float32: below 1e-4 of the range on 95% of the
    observations. With bf16 layers an observation whose input to one lies within its error bound of a bf16
    rounding boundary may round to the neighbouring bf16 value, and its bound grows by that bf16 step; how many
    do depends on the trained weights, so on the CPU that trained them (CI's AVX2 run: 89% below 1e-4, the
    95th percentile 2e-4): below 1e-4 at the median and below 1e-3 on 95%. A SimBa actor's bound is ten times
    looser (its worst case carries each error through both layers of a residual block at full weight, where
    real errors partly cancel: bounds ~5e-4 of the range for errors of ~2e-7): below 1e-3. So is an actor with
    LayerNorm after each activation (Brax's): the norm divides each ReLU layer's error by its outputs' spread, small
    where most units are off (bounds 2e-4 to 9e-4 of the range)."""
    width = (agent.learner.scaler.high - agent.learner.scaler.low).astype(np.float64)
    relative = np.max(bound / width, axis=1)
    summary = np.quantile(relative, [0.5, 0.95, 1.0])
    if bf16:
        assert np.median(relative) <= 1e-4 and np.mean(relative <= 1e-3) >= 0.95, summary
    else:
        loose = agent.config.network == "simba" or agent.learner.functions.policy.layer_norm == "after"
        limit = 1e-3 if loose else 1e-4
        assert np.mean(relative <= limit) >= 0.95, summary


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """trained(kind) -> (agent, its run directory), trained once per kind for this module."""
    cache = {}

    def get(kind: str) -> tuple[SAC, Path]:
        if kind not in cache:
            run = tmp_path_factory.mktemp("export") / kind
            agent = SAC(TRAINED[kind]())
            agent.learn(300, run_dir=run, progress=False)
            cache[kind] = agent, run
        return cache[kind]

    return get


@pytest.mark.parametrize("kind", list(TRAINED))
@pytest.mark.numerics
def test_exports_of_trained_agents_act_as_predict(trained, kind, tmp_path):
    agent, _ = trained(kind)
    if kind == "crossq":  # the running statistics folded into the weights are not the initial ones
        for stats in agent.learner.state.variants.actor_stats:
            assert np.abs(np.asarray(stats["mean"])).max() > 1e-2
            assert np.abs(np.asarray(stats["var"]) - 1.0).max() > 1e-2
    if kind == "crossq-averaged":  # what is exported is the average, which has drifted apart from the actor
        averaged, online = agent.learner.deployed_policy()[0], agent.learner.state.actor
        assert np.abs(np.asarray(averaged[0]["w"]) - np.asarray(online[0]["w"])).max() > 1e-3
    if kind == "brax":  # the LayerNorms' learned affine the export carries is not the initial one
        assert np.abs(np.asarray(agent.learner.state.actor[0]["ln_scale"]) - 1.0).max() > 1e-3
    obs = env_observations(agent)
    if agent.learner.obs_norm is not None:
        assert np.abs(agent.learner.normalize_obs(obs)).max() == agent.config.obs_norm_clip  # the clip is exercised
    bound = assert_exports_act_as_predict(agent, tmp_path, obs)
    if kind in ("simba-bf16", "flashsac", "flashsac-bf16"):
        assert_exports_agree_with_predict_on_most(agent, tmp_path, obs[:-FAR])
    else:  # on the episodes' observations (the FAR ones have outsized values, and bounds to match)
        assert_bound_is_tight(agent, bound[:-FAR], bf16=kind.endswith("bf16"))


def assert_exports_agree_with_predict_on_most(agent: SAC, directory: Path, obs: np.ndarray) -> None:
    """For a SimBa actor with bf16 layers the bound is too loose to tell a wrong export (five layers round
    their inputs to bf16: where a bound reaches a rounding boundary it grows by a bf16 step, and the residual
    blocks carry that on; median 4e-2 of the range). Yet an input lands within float32's error of a boundary
    rarely, so on most observations every program rounds alike: the exports agree with predict() to 1e-5 of
    the range on 90% of them (a wrong layer, normalisation or rounding is off by 1e-3 and more on all). So for a
    FlashSAC actor, float32 too: a batch normalisation after each matmul multiplies the worst case of the sum's
    rounding by scale / std, large where a unit's variance is small against its inputs' magnitudes (median bound
    2e-3 of the range, where the programs differ by ~1e-7)."""
    width = (agent.learner.scaler.high - agent.learner.scaler.low).astype(np.float64)
    expected = agent.predict(obs, deterministic=True)
    for name, actions in (("onnx", onnx_actions(directory / "policy.onnx", obs)),
                          ("numpy", numpy_actions(directory / "policy.npz", obs))):
        relative = np.max(np.abs(actions - expected) / width, axis=1)
        assert np.mean(relative <= 1e-5) >= 0.9, (name, np.quantile(relative, [0.5, 0.9, 1.0]))


@pytest.mark.numerics
def test_bf16_layers_are_marked_and_float32_runs_have_no_marks(tmp_path):
    def arrays(**extra):
        path = export_policy(SAC(tiny_config("Pusher-v5", **extra)), tmp_path / "policy.npz", "numpy")
        with np.load(path) as npz:
            return dict(npz)

    assert "bf16" not in arrays()
    if not jit_keeps_bf16_rounding():  # JAX 0.4.30: the compiled bf16 layers multiply in float32, the export too
        assert "bf16" not in arrays(matmul_dtype="bfloat16")
        assert "bf16" not in arrays(matmul_dtype="bfloat16", network="simba", critic_hidden_sizes=[32])
        return
    # layers 23x32, 32x32, 32x14: the thin output layer stays in float32, as networks.dense keeps it
    assert arrays(matmul_dtype="bfloat16")["bf16"].tolist() == [1, 1, 0]
    # SimBa: the embedding 23x32, each block's 32x128 and 128x32, the output layer 32x14
    simba = arrays(matmul_dtype="bfloat16", network="simba", critic_hidden_sizes=[32])
    assert simba["bf16"].tolist() == [1, 1, 1, 1, 1, 0] and "w0" not in simba
    assert simba["head_w"].shape == (32, 7) and not np.any(simba["block1_2_w"].view(np.uint32) & 0xFFFF)
    assert "bf16" not in arrays(network="simba", critic_hidden_sizes=[32])
    crossq = arrays(matmul_dtype="bfloat16", crossq=True)
    assert {"n0_mean", "n1_inv_std", "n1_scale", "n1_bias"} <= set(crossq) and "n2_mean" not in crossq
    w = crossq["w1"].view(np.uint32)
    assert not np.any(w & 0xFFFF)  # bf16 weights: the low 16 bits of each float32 are zero


@pytest.mark.parametrize("activation", ["relu", "tanh", "elu", "gelu", "silu"])
@pytest.mark.numerics
def test_every_activation_matches_jax(activation, tmp_path):
    """Untrained agents (PyTorch's default init: outputs well away from zero); gelu is JAX's tanh form."""
    agent = SAC(tiny_config(DRIFT, activation=activation))
    obs = np.random.default_rng(0).normal(scale=3.0, size=(300, 2)).astype(np.float32)
    assert_bound_is_tight(agent, assert_exports_act_as_predict(agent, tmp_path, obs), bf16=False)


def _checkpoint_digests(run: Path) -> dict[str, str]:
    return {str(p.relative_to(run)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted((run / "checkpoints").rglob("*")) if p.is_file()}


@pytest.mark.numerics
def test_cli_exports_a_run_to_its_export_folder_and_leaves_checkpoints_alone(trained, tmp_path):
    agent, run = trained("obs_norm")
    before = _checkpoint_digests(run)
    obs = env_observations(agent)
    reference, bound = action_bound(agent, obs, program_matmul_dtype())
    assert_predict_acts_as_the_network(agent, obs)

    r = run_cli("export", str(run))
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == str(run / "export" / "policy.onnx")
    assert_within_bound(onnx_actions(run / "export" / "policy.onnx", obs), reference, bound, "onnx")

    out = tmp_path / "elsewhere" / "policy-copy.npz"
    r = run_cli("export", str(run / "checkpoints" / "last"), "--format", "numpy", "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == str(out)
    assert_within_bound(numpy_actions(out, obs), reference, bound, "numpy")
    with np.load(out) as npz:
        assert str(npz["env_id"]) == DRIFT and int(npz["step"]) == agent.num_steps
    assert _checkpoint_digests(run) == before


def test_bad_inputs_are_one_line_errors(trained, tmp_path):
    _, run = trained("sac")  # trained without evaluations: it has no best checkpoint
    (tmp_path / "empty").mkdir()
    shim = tmp_path / "shim" / "onnx"  # an environment without the onnx package
    shim.mkdir(parents=True)
    (shim / "__init__.py").write_text("raise ImportError(\"No module named 'onnx'\")\n")
    without_onnx = {"PYTHONPATH": child_env(shim.parent)["PYTHONPATH"]}

    assert_clean_error(run_cli("export", str(tmp_path / "missing")), "no such run or checkpoint")
    assert_clean_error(run_cli("export", str(tmp_path / "empty")), "holds no checkpoint")
    assert_clean_error(run_cli("export", str(run), "--checkpoint", "best"), "has no best checkpoint")
    assert_clean_error(run_cli("export", str(run), "--format", "tflite"), "invalid choice: 'tflite'")
    assert_clean_error(run_cli("export", str(run), "--out", str(tmp_path / "policy.npz")), "writes a .onnx file")
    assert_clean_error(run_cli("export", str(run), "--format", "numpy", "--out",
                               str(run / "checkpoints" / "last" / "policy.npz")), "inside the checkpoint")
    assert_clean_error(run_cli("export", str(run), env_extra=without_onnx), "pip install 'softac[export]'")
    assert not (run / "export").exists()


def test_api_errors(trained, tmp_path):
    agent, _ = trained("sac")
    with pytest.raises(SoftacError, match="unknown export format 'tflite'"):
        export_policy(agent, tmp_path / "policy.tflite", "tflite")
    with pytest.raises(SoftacError, match="needs a path"):
        export_policy(agent, format="numpy")


def test_the_numpy_forward_pass_imports_only_numpy():
    tree = ast.parse(EXPORT_NUMPY.read_text())
    imported = {alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names}
    imported |= {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
    assert imported == {"numpy", "__future__"}


@pytest.mark.numerics
def test_the_export_guides_forward_pass_is_the_modules(tmp_path):
    section = (TESTS.parent / "docs" / "guides" / "export.md").read_text()
    code = next(block for block in section.split("```python\n") if "def policy_forward" in block).split("```")[0]
    readme_module = {}
    exec(code, readme_module)
    from softac.learner.numpy_forward import ACTIVATIONS

    x = np.linspace(-6.0, 6.0, 1001, dtype=np.float32)
    assert set(readme_module["ACTIVATIONS"]) == set(ACTIVATIONS)
    for name, activation in ACTIVATIONS.items():
        np.testing.assert_array_equal(readme_module["ACTIVATIONS"][name](x), activation(x), err_msg=name)

    agent = SAC(tiny_config(DRIFT, activation="gelu", obs_norm=True))
    rng = np.random.default_rng(0)
    agent.learner.obs_norm.update(rng.normal(loc=[0.1, 10.0], scale=[0.1, 5.0], size=(100, 2)))
    obs = rng.normal(loc=[0.1, 10.0], scale=[0.3, 15.0], size=(300, 2)).astype(np.float32)
    with np.load(export_policy(agent, tmp_path / "policy.npz", "numpy")) as npz:
        actions = readme_module["policy_forward"](dict(npz), obs)
    assert_within_bound(actions, *action_bound(agent, obs), "the export guide's forward pass")
    assert_predict_acts_as_the_network(agent, obs)

    # bf16 layers and CrossQ's kept-apart normalisation: the guide's pass is the module's to the bit
    from softac.learner.numpy_forward import policy_forward

    agent = SAC(tiny_config("Pusher-v5", crossq=True, obs_norm=True, matmul_dtype="bfloat16"))
    obs = rng.normal(scale=2.0, size=(100, agent.spaces.obs_dim)).astype(np.float32)
    with np.load(export_policy(agent, tmp_path / "bf16.npz", "numpy")) as npz:
        params = dict(npz)
    if jit_keeps_bf16_rounding():
        assert "bf16" in params and "n0_mean" in params
    else:  # JAX 0.4.30: float32 layers, the batch renormalisation folded into them
        assert "bf16" not in params and "n0_mean" not in params
    np.testing.assert_array_equal(readme_module["policy_forward"](params, obs), policy_forward(params, obs))
