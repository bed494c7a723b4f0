"""The network registry (issue 65): a network kind is one module with one `Network` entry, named in NETWORKS and,
for the config, in config/names.py's NETWORK_NAMES. The learner, the policy, the critics, the optimisers and the
memory check reach every kind through its entry, so a new one trains, checkpoints and acts with nothing else
changed: the test below adds one."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softac import SAC
from softac.config import names
from softac.config.sac_config import ConfigError, SACConfig
from softac.learner.networks import NETWORKS, Network, network_kind
from softac.learner.networks.layers import dense
from softac.learner.networks.mlp import MLP


def test_the_config_names_every_network_kind_it_can_pick():
    """Every name a config may give is in the registry, and every kind in it is reachable from a config (the
    batch-renormalised MLP through `crossq`)."""
    assert set(names.NETWORK_NAMES) | {"batch_renorm_mlp"} == set(NETWORKS)
    assert network_kind("mlp", batch_renorm=True) is NETWORKS["batch_renorm_mlp"]
    assert network_kind("simba", batch_renorm=False) is NETWORKS["simba"]


def test_an_unknown_network_is_refused_by_the_config():
    with pytest.raises(ConfigError, match="network='resnet': must be one of mlp, simba"):
        SACConfig().replace(network="resnet")


def _sine_features(params, stats, x, activation, matmul_dtype, normalize=False, masks=None, batch_renorm=None,
                   train=False, renorm=False):
    for layer in params[:-1]:
        x = jnp.sin(dense(x, layer, matmul_dtype))
    return x, stats


# a network kind of its own: an MLP's layers with sine activations (SIREN-like), nothing else of softac changed
SINE = Network(init=MLP.init, features=_sine_features, head=lambda params: params[-1], output_mask=MLP.output_mask,
               parameters=MLP.parameters)


def test_a_network_added_to_the_registry_trains_checkpoints_and_acts(tiny, tmp_path, monkeypatch):
    monkeypatch.setitem(NETWORKS, "sine", SINE)  # the registry line
    monkeypatch.setattr("softac.config.checks.NETWORK_NAMES", (*names.NETWORK_NAMES, "sine"))  # the config's name
    agent = SAC(tiny(network="sine"))
    agent.learn(300, run_dir=tmp_path / "run", progress=False)
    obs = np.random.default_rng(0).normal(size=(8, 2)).astype(np.float32)
    loaded = SAC.load(tmp_path / "run", which="last")
    np.testing.assert_array_equal(agent.predict(obs), loaded.predict(obs))
    # the policy runs the sine network: its features are those of sin(dense(x)) layer after layer
    actor = loaded.learner.state.actor
    x = jnp.asarray(obs)
    for layer in actor[:-1]:
        x = jnp.sin(x @ layer["w"] + layer["b"])
    mean = np.asarray(jnp.split(x @ actor[-1]["w"] + actor[-1]["b"], 2, axis=-1)[0])
    scaled = loaded.learner.scaler.to_normalised(loaded.predict(obs))
    np.testing.assert_allclose(scaled, np.tanh(mean), rtol=1e-5, atol=1e-6)
    assert int(jax.device_get(loaded.learner.state.n_updates)) > 0


def test_the_export_refuses_a_network_it_has_no_layout_for(tiny, tmp_path, monkeypatch):
    from softac.errors import SoftacError
    from softac.outputs.export import export_policy

    monkeypatch.setitem(NETWORKS, "sine", SINE)
    monkeypatch.setattr("softac.config.checks.NETWORK_NAMES", (*names.NETWORK_NAMES, "sine"))
    agent = SAC(tiny(network="sine"))
    with pytest.raises(SoftacError, match="export writes the networks mlp, simba, bn_mlp, flashsac; this agent's network is sine"):
        export_policy(agent, tmp_path / "policy.npz", "numpy")


def _sine_export_arrays(actor, actor_stats, batch_renorm, matmul_dtype, act_dim):
    arrays = {"network": np.asarray("sine_exported")}
    for i, layer in enumerate(actor):
        w, b = np.asarray(layer["w"], np.float32), np.asarray(layer["b"], np.float32)
        if i == len(actor) - 1:
            w, b = np.ascontiguousarray(w[:, :act_dim]), np.ascontiguousarray(b[:act_dim])
        arrays[f"w{i}"], arrays[f"b{i}"] = w, b
    return arrays


def _sine_onnx(g, arrays, x):
    from softac.learner.networks import onnx_layers
    from softac.learner.numpy_forward import layer_count

    n = layer_count(arrays)
    for i in range(n):
        x = onnx_layers.dense(g, arrays, x, f"w{i}", f"b{i}", False)
        if i < n - 1:
            x = g.op("Sin", x)
    return x


def test_a_network_with_an_export_in_its_entry_is_exported_through_it(tiny, tmp_path, monkeypatch):
    """The export reaches a kind through its entry's ActorExport alone: its arrays go into the file and its ONNX
    nodes into the graph, which then acts as predict() does (float32: the ONNX runtime's sums in other orders)."""
    ort = pytest.importorskip("onnxruntime")
    from softac.learner.networks.entry import ActorExport
    from softac.outputs.export import export_policy

    exported = Network(init=MLP.init, features=_sine_features, head=lambda params: params[-1],
                       output_mask=MLP.output_mask, parameters=MLP.parameters,
                       export=ActorExport(arrays=_sine_export_arrays, onnx=_sine_onnx,
                                          input_size=lambda arrays: arrays["w0"].shape[0]))
    monkeypatch.setitem(NETWORKS, "sine_exported", exported)
    monkeypatch.setattr("softac.config.checks.NETWORK_NAMES", (*names.NETWORK_NAMES, "sine_exported"))
    agent = SAC(tiny(network="sine_exported", matmul_dtype="float32"))
    agent.learn(300, progress=False)
    path = export_policy(agent, tmp_path / "policy.onnx", "onnx")
    assert str(np.load(export_policy(agent, tmp_path / "policy.npz", "numpy"))["network"]) == "sine_exported"
    obs = np.random.default_rng(1).normal(size=(16, 2)).astype(np.float32)
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    actions = session.run(["action"], {"obs": obs})[0]
    np.testing.assert_allclose(actions, agent.predict(obs), rtol=1e-5, atol=1e-5)
    assert not np.allclose(actions, 0.0)
