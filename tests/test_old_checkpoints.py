"""Checkpoints written by an earlier commit load and resume exactly (issue 65: the code can move under them).

tests/data/old_checkpoints/ holds, per case, a run directory whose `last` checkpoint (step 250, mid-episode,
buffer included) the code of the commit in machine.json wrote, and that commit's own continuation of the run to
step 400 (`expected/`). Today's code must read the old files to the same arrays and, resumed, train to the same
state: bit for bit on a machine that compiles as the fixture's did (the same vector instruction sets, XLA
flags and JAX version: machine.json), within what float32 reordering allows on another CPU, and in its layout
and step count with another JAX (test-min's lowest versions, whose floats and keys are their own).
"""

import hashlib
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import assert_same_learner, assert_same_run_state
from softac import SAC
from softac.run.checkpoint import load as load_checkpoint

FIXTURES = Path(__file__).parent / "data" / "old_checkpoints"
sys.path.insert(0, str(FIXTURES))
from make import CASES, CHECKPOINT_AT, CONTINUED_TO, machine  # noqa: E402

# the largest relative difference measured on an AVX-512 EPYC with XLA limited to AVX2, at its default optimisation
# level: 0.020 (the crossq case: batch norm carries differences on; the others below 4e-6); a leaf read from the
# wrong place or not at all is off by about its own size (1)
RELATIVE = 0.2
WRITTEN_ON = json.loads((FIXTURES / "machine.json").read_text())


def _contents(directory: Path) -> list[tuple[str, str, str]]:
    """A checkpoint's arrays as (dtype, shape, digest of the bytes), sorted: equal for two checkpoints that hold
    the same numbers, whatever names a later layout gives them."""
    _, arrays = load_checkpoint(directory)
    return sorted((str(a.dtype), str(a.shape), hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest())
                  for a in arrays.values())


@pytest.mark.parametrize("case", sorted(CASES))
def test_an_old_checkpoint_loads_to_the_same_arrays(case, tmp_path):
    run = shutil.copytree(FIXTURES / case / "run", tmp_path / "run")  # never written into the repository
    agent = SAC.load(run, which="last")
    assert agent.num_steps == CHECKPOINT_AT
    # each leaf from its own old name (the variants' fields sat beside SAC's before SACState.variants): a swap of
    # two leaves of one shape (an encoder and its target) would keep the sorted contents below equal
    import jax

    _, old = load_checkpoint(run / "checkpoints" / "last")
    for path, leaf in jax.tree_util.tree_flatten_with_path(agent.learner.state)[0]:
        name = "state" + jax.tree_util.keystr(path)
        np.testing.assert_array_equal(np.asarray(leaf), old[name.replace("state.variants.", "state.", 1)],
                                      err_msg=name)
    agent.save(tmp_path / "again", include_buffer=True)
    assert _contents(tmp_path / "again") == _contents(run / "checkpoints" / "last")


@pytest.mark.exact
@pytest.mark.parametrize("case", sorted(CASES))
def test_an_old_checkpoint_resumes_to_what_its_own_code_trained(case, tmp_path):
    run = shutil.copytree(FIXTURES / case / "run", tmp_path / "run")
    resumed = SAC.load(run, which="last")
    resumed.learn(CONTINUED_TO - CHECKPOINT_AT, run_dir=run, progress=False)
    expected = SAC.load(FIXTURES / case / "expected")
    assert resumed.num_steps == expected.num_steps == CONTINUED_TO
    if machine() == {key: WRITTEN_ON[key] for key in ("isa", "xla_flags", "jax")}:
        assert_same_learner(resumed, expected)
        assert_same_run_state(resumed, expected)
        return
    # elsewhere XLA sums in other orders: 150 steps of training carry the float32 differences on, no further, and
    # what no float decides (counters, JAX keys, the NumPy RNG) stays exact. Another JAX computes other floats and
    # other keys (JAX 0.5 made threefry partitionable by default): there the state's layout, finite, and the steps
    import jax

    same_jax = machine()["jax"] == WRITTEN_ON["jax"]
    for x, y in zip(jax.tree_util.tree_leaves(resumed.learner.state), jax.tree_util.tree_leaves(expected.learner.state),
                    strict=True):
        x, y = np.asarray(x), np.asarray(y)
        assert x.shape == y.shape and x.dtype == y.dtype
        if not same_jax:
            assert np.isfinite(x).all() if np.issubdtype(x.dtype, np.floating) else True
        elif not np.issubdtype(x.dtype, np.floating):
            np.testing.assert_array_equal(x, y)
        else:  # a wrongly mapped leaf would be off by its whole size
            assert np.linalg.norm(x - y) <= RELATIVE * np.linalg.norm(y) + 1e-6, (np.linalg.norm(x - y), np.linalg.norm(y))
    a, b = resumed.run_state, expected.run_state
    if same_jax:  # (another JAX's actions end other episodes: only the layout and the step count compare)
        assert a.num_episodes == b.num_episodes and a.rng.bit_generator.state == b.rng.bit_generator.state
        for key in ("act_key", "predict_key"):
            np.testing.assert_array_equal(np.asarray(getattr(a, key)), np.asarray(getattr(b, key)))
        # the episodes' returns come from the policy these 150 steps trained, so they carry its float differences
        # as the leaves do (pinned to one CPU, XLA's other split of the sums moved the last returns by 0.1%)
        x, y = np.asarray(a.recent_returns), np.asarray(b.recent_returns)
        assert x.shape == y.shape and np.linalg.norm(x - y) <= RELATIVE * np.linalg.norm(y) + 1e-6, (x, y)
