import contextlib
import functools
import os
import subprocess
import sys
import time
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
from fast_compile import fast_compile_in_effect, users_xla_flags  # noqa: E402

from softac.config.sac_config import SACConfig  # noqa: E402

TINY = dict(hidden_sizes=[32, 32], batch_size=32, learning_starts=200, buffer_size=5000,
            eval_interval=0, log_interval=100, checkpoint_interval=0, eval_episodes=2)


def tiny_config(env_id: str = "softac_test_envs:Drift-v0", **extra) -> SACConfig:
    return SACConfig.for_env(env_id).replace(**{**TINY, **extra})


SLOW_MARKERS = ("slow", "faults", "bench")  # the learning test, the kill/signal campaigns, the bench runs


def run_order(item) -> int:
    """0: the Ray sweeps, 1: the fast tests, 2: the slow ones. The Ray sweeps run one after another on one worker
    (a group, below), the suite's longest chain: handed out first, it starts at once (issue 64). The other tests
    follow the fast ones first, so that a failure among them shows in minutes (and, with CI's --maxfail=1, ends
    the run there) instead of after the learning test and the kill campaigns."""
    if item.get_closest_marker("ray") is not None:
        return 0
    return 2 if any(item.get_closest_marker(m) is not None for m in SLOW_MARKERS) else 1


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist's own hook reads the groups
def pytest_collection_modifyitems(config, items):
    # `make test` runs the suite on two pytest-xdist workers (--dist loadgroup); the Ray sweeps go to one
    # worker, one after another: each starts a local Ray that takes the machine's CPUs for its trials
    for item in items:
        if item.get_closest_marker("ray") is not None:
            item.add_marker(pytest.mark.xdist_group("ray"))
        if item.get_closest_marker("users_xla") is not None and fast_compile_in_effect():
            item.runtest = functools.partial(run_with_users_xla, item)
    # a stable sort: pytest-randomly's order (it shuffles before any other plugin's hook) within each rank
    items.sort(key=run_order)


def run_with_users_xla(item) -> None:
    """A `users_xla` test (tests/fast_compile.py) under make test's fast-compile XLA flags: the test, alone, in a
    pytest process of its own whose XLA_FLAGS are the user's (this one's, less those flags); its output on failure.
    Its fixtures are set up again there (this process's go unused)."""
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:randomly", "-p", "no:cacheprovider", "-p", "no:xdist",
               "--rootdir", str(TESTS.parent), item.nodeid]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600, cwd=TESTS.parent,
                            env=child_env(XLA_FLAGS=users_xla_flags()))
    if result.returncode != 0:
        pytest.fail(f"{item.nodeid} with XLA_FLAGS={users_xla_flags()!r} (the user's):\n{result.stdout[-6000:]}"
                    f"{result.stderr[-2000:]}", pytrace=False)


def pytest_terminal_summary(terminalreporter, config):
    # pytest-randomly (the test extra) runs the tests in a random order; its seed is in the header, which -q
    # hides: say it at the end too, so that a failure that depends on the order can be repeated
    if config.pluginmanager.hasplugin("randomly"):
        seed = config.getoption("randomly_seed")
        terminalreporter.write_line(f"random test order: repeat it with -p randomly --randomly-seed={seed}")


def child_env(*paths: str | Path, **variables: str) -> dict[str, str]:
    """The environment of a process a test starts: os.environ, with `paths` and tests/ (the test envs) put
    ahead on PYTHONPATH (never in place of it: the suite's own PYTHONPATH may point at a checkout's src),
    and `variables` set."""
    pythonpath = os.pathsep.join([*map(str, paths), str(TESTS), os.environ.get("PYTHONPATH", "")])
    return {**os.environ, "PYTHONPATH": pythonpath, **variables}


def load_benchmark_script(name: str):
    """A script of benchmarks/ (not a package) as a module, to call its functions."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, TESTS.parent / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run_cli(*args: str, timeout: float = 300, cwd: Path | None = None, env_extra: dict | None = None,
            **popen) -> subprocess.CompletedProcess:
    env = {**child_env(), **(env_extra or {})}
    return subprocess.run([sys.executable, "-m", "softac", *args], capture_output=True, text=True,
                          timeout=timeout, env=env, cwd=cwd, **popen)


def filmed_frames(run: Path, out: Path, frames: tuple[int, ...] = (0,)) -> list:
    """`softac video RUN --out OUT --max-steps 20` as a user runs it, and those frames of the MP4 it wrote; the test
    is skipped where headless rendering has neither EGL nor OSMesa."""
    video = run_cli("video", str(run), "--out", str(out), "--max-steps", "20")
    if video.returncode != 0 and "headless rendering found neither" in video.stderr:
        pytest.skip("no EGL or OSMesa here (make system-deps installs libosmesa6)")
    assert video.returncode == 0, video.stderr
    import imageio.v2 as imageio

    with imageio.get_reader(out, format="FFMPEG") as reader:
        return [reader.get_data(i) for i in frames]


def run_cli_in_process(*args: str) -> subprocess.CompletedProcess:
    """`softac ARGS` as softac.cli.main.main runs it in this process (a notebook's or a script's call), its exit code
    and its stdout and stderr captured: for tests of what a command does with many configurations (every preset
    trains), which would otherwise pay a process, its `import jax` and its compile-cache reads each (issue 64:
    about 3 s of CPU a run). The tests of how a command behaves as a process of its own (exit codes as a shell
    sees them, signals, one-line errors) run it through run_cli."""
    import io

    from softac.cli.main import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(list(args))
    return subprocess.CompletedProcess(["softac", *args], code, out.getvalue(), err.getvalue())


@contextlib.contextmanager
def ray_test_cluster(**head_node_args):
    """Ray's test cluster (ray.cluster_utils.Cluster), its head started with `head_node_args` (no dashboard). While
    it runs, this process's environment, which its nodes' processes (started now or added later) inherit, has
    the test envs' module on PYTHONPATH and Ray's workers leaving their child processes alive on exit, as
    docs/cluster.md's `ray start` and a sweep's local Ray have them."""
    from ray.cluster_utils import Cluster

    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("PYTHONPATH", os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]))
        patch.setenv("RAY_kill_child_processes_on_worker_exit", "false")
        cluster = Cluster(initialize_head=True, head_node_args={"include_dashboard": False, **head_node_args})
        try:
            yield cluster
        finally:
            cluster.shutdown()


def signal_when(proc: subprocess.Popen, ready, sig: int, within_s: float = 600) -> str:
    """Wait until `ready()` holds (the process still running: a hang guard, not a timing), send `sig`, and
    return the process's stderr once it has exited; a process still running when anything fails is killed."""
    try:
        deadline = time.monotonic() + within_s
        while not ready():
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, f"not ready within {within_s} s"
            time.sleep(0.05)
        proc.send_signal(sig)
        return proc.communicate(timeout=120)[1]
    finally:
        if proc.poll() is None:
            proc.kill()


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
    """The JAX compile cache (softac.base.device.compile_cache_dir) of this test session alone, under pytest's
    basetemp: the suite neither reads the user's ~/.cache/softac/jax (it runs as on a fresh machine,
    whatever earlier runs left there) nor fills it with the tests' tiny networks. pytest-xdist's workers share
    one (under the session's base directory, the parent of each worker's): a program one compiled, the other
    loads, as runs beside each other do (softac.base.device locks each entry's read and write). A session-scoped
    autouse fixture runs before every other fixture and test; the CLI subprocesses inherit os.environ."""
    previous = os.environ.get("SOFTAC_COMPILE_CACHE")
    if os.environ.get("PYTEST_XDIST_WORKER"):
        cache = tmp_path_factory.getbasetemp().parent / "jax-compile-cache"
        cache.mkdir(exist_ok=True)
    else:
        cache = tmp_path_factory.mktemp("jax-compile-cache")
    os.environ["SOFTAC_COMPILE_CACHE"] = str(cache)
    yield cache
    if previous is None:
        os.environ.pop("SOFTAC_COMPILE_CACHE", None)
    else:
        os.environ["SOFTAC_COMPILE_CACHE"] = previous


@pytest.fixture(autouse=True)
def compiled_programs_within_the_map_limit():
    """One pytest-xdist worker runs hundreds of tests in one process, each compiling programs whose code XLA
    maps into regions of their own: past vm.max_map_count (65,530) the next compile fails and the worker dies
    of a segmentation fault (issue 66's tests took a one-worker run there, in test_export). After each test, as
    softac does before it builds an agent, JAX's compiled programs are dropped once half the limit is used."""
    yield
    from softac.base.device import release_compiled_programs_near_map_limit

    release_compiled_programs_near_map_limit()


@pytest.fixture(scope="session")
def trained_run(tmp_path_factory):
    """One short InvertedPendulum-v5 run (800 steps, evaluations, checkpoints, baselines.json), trained once
    for the tests that read a run or add outputs to it (plots, videos, reports). Shared by the whole session:
    a test that writes into it works on a copy (test_outputs' pendulum_run), so no test sees another's files."""
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


def assert_same_learner(a, b, skip: tuple[str, ...] = ()) -> None:
    """Every leaf of the two agents' learner states (networks, targets, optimisers, alpha, key, counters) is
    bit-identical, and the two trees have the same structure; the SACState fields in `skip` (SAC's, or those in
    SACState.variants) are left out. Leaves are copied first: a view of a donated buffer would change under us."""
    import jax
    import numpy as np

    def kept(state):
        own = {name: () for name in skip if name in state._fields}
        return state._replace(**own).with_variants(**{name: () for name in skip if name not in own})

    paths_a, tree_a = jax.tree_util.tree_flatten_with_path(kept(a.learner.state))
    paths_b, tree_b = jax.tree_util.tree_flatten_with_path(kept(b.learner.state))
    assert tree_a == tree_b
    for (path, x), (_, y) in zip(paths_a, paths_b, strict=True):
        np.testing.assert_array_equal(np.array(x, copy=True), np.array(y, copy=True),
                                      err_msg="state" + jax.tree_util.keystr(path))


def assert_same_run_state(a, b) -> None:
    """The two agents' run states are equal: counters, keys, NumPy RNG, best and last evaluation and their
    steps, recent returns, exploration noise; only the fields a resumed run has of its own may differ."""
    import dataclasses

    import numpy as np

    from softac.run.run_state import RunState

    for f in dataclasses.fields(RunState):
        if f.name in RUN_STATE_NOT_COMPARED:
            continue
        x, y = getattr(a.run_state, f.name), getattr(b.run_state, f.name)
        if f.name == "rng":
            assert x.bit_generator.state == y.bit_generator.state, f.name
        elif f.name.endswith("_key"):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y), err_msg=f.name)
        elif f.name == "noise" and x is not None and y is not None:  # exploration_noise pink
            (meta_x, arrays_x), (meta_y, arrays_y) = x.checkpoint_parts(), y.checkpoint_parts()
            assert meta_x == meta_y, f.name
            for name in arrays_x:
                np.testing.assert_array_equal(arrays_x[name], arrays_y[name], err_msg=f"noise {name}")
        else:
            assert x == y, (f.name, x, y)


def assert_same_last_checkpoint(a: Path, b: Path) -> tuple[dict, dict]:
    """Two run directories whose last checkpoints are bit-identical: the same arrays (weights, optimisers,
    buffer, keys), each equal, the same NumPy RNG state and the same saved training envs. Any difference would
    make their next steps differ. Returns a's (meta, arrays), for a test's further checks."""
    import numpy as np

    from softac.run import checkpoint as ckpt

    (meta_a, arrays_a), (meta_b, arrays_b) = (ckpt.load(Path(run) / "checkpoints" / "last") for run in (a, b))
    assert sorted(arrays_a) == sorted(arrays_b) and any(k.startswith("state") for k in arrays_a)
    for key in arrays_a:
        np.testing.assert_array_equal(arrays_a[key], arrays_b[key], err_msg=key)
    assert meta_a["numpy_rng"] == meta_b["numpy_rng"] and meta_a.get("envs") == meta_b.get("envs")
    return meta_a, arrays_a


# RunState fields that differ between a straight run and a resumed one by design, so not compared:
# run_dir (the directory each agent trained into), restored_from (the checkpoint a resumed agent was loaded
# from; None for one never loaded) and train_time_s (wall-clock seconds).
RUN_STATE_NOT_COMPARED = {"run_dir", "restored_from", "train_time_s"}


def straight_and_resumed(cfg, tmp_path: Path, first: int, then: int):
    """(an agent trained first + then steps in one go into tmp_path/straight, one trained `first` steps into
    tmp_path/split, loaded from its last checkpoint and trained `then` more there): the N + M == N+M check."""
    from softac import SAC

    straight = SAC(cfg)
    straight.learn(first + then, run_dir=tmp_path / "straight", progress=False)
    SAC(cfg).learn(first, run_dir=tmp_path / "split", progress=False)
    resumed = SAC.load(tmp_path / "split", which="last")
    assert resumed.num_steps == first
    resumed.learn(then, run_dir=tmp_path / "split", progress=False)
    return straight, resumed


def assert_same_training(a, b, skip: tuple[str, ...] = ()) -> None:
    """Two agents that trained the same steps share their whole training state, bit for bit: the learner's
    leaves (but the SACState fields in `skip`), the run state (counters, keys, NumPy RNG, best and last
    evaluation and their steps, recent returns), every array of the replay buffer, the observation statistics
    (obs_norm) and the training envs' saved state. Any difference would make their next steps differ."""
    import numpy as np

    assert_same_learner(a, b, skip)
    assert_same_run_state(a, b)

    assert type(a.collector.buffer) is type(b.collector.buffer)
    if a.collector.buffer is not None:
        buffer_a, buffer_b = a.collector.buffer.state_dict(), b.collector.buffer.state_dict()
        assert buffer_a.keys() == buffer_b.keys()
        for name in buffer_a:
            np.testing.assert_array_equal(buffer_a[name], buffer_b[name], err_msg=f"buffer {name}")

    assert (a.learner.obs_norm is None) == (b.learner.obs_norm is None)
    if a.learner.obs_norm is not None:
        norm_a, norm_b = a.learner.obs_norm.state_dict(), b.learner.obs_norm.state_dict()
        assert norm_a.keys() == norm_b.keys()
        for name in norm_a:
            np.testing.assert_array_equal(norm_a[name], norm_b[name], err_msg=f"obs_norm {name}")

    envs_a, envs_b = a.collector.env_state(), b.collector.env_state()
    assert (envs_a is None) == (envs_b is None)
    if envs_a is not None:
        (meta_a, arrays_a), (meta_b, arrays_b) = envs_a, envs_b
        assert meta_a == meta_b
        assert arrays_a.keys() == arrays_b.keys()
        for name in arrays_a:
            np.testing.assert_array_equal(arrays_a[name], arrays_b[name], err_msg=f"envs {name}")
