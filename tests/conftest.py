import os
import subprocess
import sys
from pathlib import Path

# JAX on the CPU for the whole session, this process and the CLI subprocesses the tests start (they inherit
# os.environ): the tests assume a CPU (bit-exact comparisons between runs, CPU pinning of sweep trials), so a
# machine with a GPU and jax[cuda] must not move them onto it. Set here, at the top of the first conftest, so
# that it is in place before any test module imports JAX (the JAX_PLATFORMS variable is read when JAX is
# imported; were it imported already, its config is set too, which works until a backend has started).
os.environ["JAX_PLATFORMS"] = "cpu"
if "jax" in sys.modules:
    sys.modules["jax"].config.update("jax_platforms", "cpu")

import pytest  # noqa: E402

TESTS = Path(__file__).parent
sys.path.insert(0, str(TESTS))

import softac_test_envs  # noqa: E402,F401  (registers the test envs)

from softac.config import SACConfig  # noqa: E402

TINY = dict(hidden_sizes=[32, 32], batch_size=32, learning_starts=200, buffer_size=5000,
            eval_interval=0, log_interval=100, checkpoint_interval=0, eval_episodes=2)


def tiny_config(env_id: str = "softac_test_envs:Drift-v0", **extra) -> SACConfig:
    return SACConfig.for_env(env_id).replace(**{**TINY, **extra})


def run_cli(*args: str, timeout: float = 300, cwd: Path | None = None, env_extra: dict | None = None,
            **popen) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(TESTS) + os.pathsep + os.environ.get("PYTHONPATH", ""), **(env_extra or {})}
    return subprocess.run([sys.executable, "-m", "softac", *args], capture_output=True, text=True,
                          timeout=timeout, env=env, cwd=cwd, **popen)


def assert_clean_error(result: subprocess.CompletedProcess, *fragments: str) -> None:
    """Exit 2, one line on stderr, no traceback, naming each fragment."""
    assert result.returncode == 2, (result.returncode, result.stderr)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    for fragment in fragments:
        assert fragment in lines[0], (fragment, lines[0])


@pytest.fixture
def tiny():
    return tiny_config


@pytest.fixture(scope="session", autouse=True)
def own_compile_cache(tmp_path_factory):
    """The JAX compile cache (softac.device.compile_cache_dir) of this test session alone, under pytest's
    basetemp: the suite neither reads the user's ~/.cache/softac/jax (it runs as on a fresh machine,
    whatever earlier runs left there) nor fills it with the tests' tiny networks. A session-scoped autouse
    fixture runs before every other fixture and test; the CLI subprocesses inherit os.environ."""
    previous = os.environ.get("SOFTAC_COMPILE_CACHE")
    cache = tmp_path_factory.mktemp("jax-compile-cache")
    os.environ["SOFTAC_COMPILE_CACHE"] = str(cache)
    yield cache
    if previous is None:
        os.environ.pop("SOFTAC_COMPILE_CACHE", None)
    else:
        os.environ["SOFTAC_COMPILE_CACHE"] = previous


@pytest.fixture(scope="session")
def trained_run(tmp_path_factory):
    """One short InvertedPendulum-v5 run (800 steps, evaluations, checkpoints, baselines.json), trained once
    for the tests that only read a run or add outputs to it (plots, videos, reports)."""
    run = tmp_path_factory.mktemp("runs") / "pendulum"
    r = run_cli("train", "--steps", "800", "--out", str(run), "--no-progress", "--set", "hidden_sizes=32,32",
                "batch_size=32", "learning_starts=200", "buffer_size=5000", "log_interval=100", "eval_interval=200",
                "eval_episodes=2")
    assert r.returncode == 0, r.stderr
    r = run_cli("baselines", "--env", "InvertedPendulum-v5", "--episodes", "3", "--out", str(run))
    assert r.returncode == 0, r.stderr
    return run


def assert_training_error(result: subprocess.CompletedProcess, *fragments: str) -> None:
    """A run that started and then failed: exit 3, no traceback, the error as the last line (after progress
    lines)."""
    assert result.returncode == 3, (result.returncode, result.stderr)
    assert "Traceback" not in result.stderr
    last = [line for line in result.stderr.splitlines() if line.strip()][-1]
    assert last.startswith("softac: error: "), last
    for fragment in fragments:
        assert fragment in last, (fragment, last)


def state_arrays(agent) -> list:
    """The agent's parameter and optimiser leaves, copied (a view of a donated buffer would change under us)."""
    import jax
    import numpy as np

    return [np.array(x, copy=True) for x in jax.tree_util.tree_leaves(agent.state)]


def assert_same_training(a, b) -> None:
    """Two agents that trained the same steps are bit-identical: parameters, keys, RNG, buffer, episodes."""
    import numpy as np

    for x, y in zip(state_arrays(a), state_arrays(b)):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(np.asarray(a.act_key), np.asarray(b.act_key))
    assert a.rng.bit_generator.state == b.rng.bit_generator.state
    np.testing.assert_array_equal(a.buffer.obs, b.buffer.obs)
    assert a.num_episodes == b.num_episodes
