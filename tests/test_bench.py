"""`softac bench`: argument checking and a tiny softac-only run (speed itself is never asserted)."""

import importlib.util
import json

import pytest

from conftest import assert_clean_error, run_cli


def test_bench_rejects_unknown_frameworks():
    assert_clean_error(run_cli("bench", "--frameworks", "softac,rllib"), "--frameworks")


def test_bench_rejects_bad_overrides():
    assert_clean_error(run_cli("bench", "--frameworks", "softac", "--set", "batch_szie=3"), "batch_szie")


@pytest.mark.skipif(importlib.util.find_spec("stable_baselines3") is not None, reason="the [bench] extra is installed")
def test_bench_without_peers_says_how_to_install():
    assert_clean_error(run_cli("bench", "--frameworks", "softac,sb3"), "make bench")


@pytest.mark.bench
def test_bench_softac_only_reports_json():
    r = run_cli("bench", "--frameworks", "softac", "--steps", "60", "--warmup", "300", "--repeats", "1", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["env"] == "InvertedPendulum-v5"
    assert out["throughput"]["softac"]["median_steps_per_s"] > 0
    assert "softac" in r.stderr  # the human-readable table goes to stderr with --json


@pytest.mark.bench
def test_bench_runs_the_bf16_variant_beside_softac():
    r = run_cli("bench", "--frameworks", "softac,softac-bf16", "--steps", "40", "--warmup", "300", "--repeats", "1",
                "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)["throughput"]
    assert out["softac"]["median_steps_per_s"] > 0 and out["softac-bf16"]["median_steps_per_s"] > 0
    assert "softac-bf16" in r.stderr
    progress = [line.split() for line in r.stderr.splitlines() if line.strip().startswith("run ")]
    assert [words[:3] for words in progress] == [["run", "1/1", "softac"], ["run", "1/1", "softac-bf16"]]


def test_update_time_script_times_a_preset_with_overrides():
    """benchmarks/update_time.py (docs/performance.md): the milliseconds of an update call, as it prints them."""
    import re
    import subprocess
    import sys

    from conftest import TESTS

    script = TESTS.parent / "benchmarks" / "update_time.py"
    r = subprocess.run([sys.executable, str(script), "--preset", "crossq", "--set", "hidden_sizes=8,8", "batch_size=8",
                        "matmul_dtype=float32", "--rounds", "2", "--updates", "3"], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    assert re.fullmatch(r"crossq hidden_sizes=8,8 batch_size=8 matmul_dtype=float32 \(float32\): [0-9.]+ ms per "
                        r"update call \(rounds: [0-9.]+ [0-9.]+\); first call \(compiling\) [0-9.]+ s\n", r.stdout), r.stdout


def test_update_time_script_times_a_peers_gradient_step():
    """`update_time.py --peer` times a peer's train(gradient_steps=1) after filling its buffer (the stand-in
    SBX: tests/fake_peers; it refuses a train() on a buffer smaller than a batch)."""
    import re
    import subprocess
    import sys

    from conftest import TESTS, child_env

    script = TESTS.parent / "benchmarks" / "update_time.py"
    r = subprocess.run([sys.executable, str(script), "--peer", "sbx-crossq-softac", "--env", "softac_test_envs:Drift-v0",
                        "--rounds", "2", "--updates", "3"], capture_output=True, text=True, timeout=300,
                       env=child_env(TESTS / "fake_peers"))
    assert r.returncode == 0, r.stderr
    assert re.fullmatch(r"sbx-crossq-softac on softac_test_envs:Drift-v0: [0-9.]+ ms per train\(gradient_steps=1\) "
                        r"\(rounds: [0-9.]+ [0-9.]+\)\n", r.stdout), r.stdout


def test_env_workers_script_reports_every_setting():
    """benchmarks/env_workers.py (docs/performance.md, "Env worker processes"): one JSON row per env and
    env_workers setting; the figures themselves are not checked."""
    import subprocess
    import sys

    from conftest import TESTS

    script = TESTS.parent / "benchmarks" / "env_workers.py"
    r = subprocess.run([sys.executable, str(script), "--steps", "8", "--warmup", "8", "--n-envs", "2", "--workers",
                        "0,2", "--sleep-ms", "1", "--envs", "SlowInvertedPendulum-v5", "--set", "hidden_sizes=8,8",
                        "batch_size=8", "learning_starts=4", "--json"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    rows = json.loads(r.stdout)
    assert [(row["env"], row["env_workers"]) for row in rows] == [("SlowInvertedPendulum-v5", 0),
                                                                  ("SlowInvertedPendulum-v5", 2)]
    assert all(row["steps_per_s"] > 0 for row in rows)
    assert "| SlowInvertedPendulum-v5 (1 ms a step) | 2 |" in r.stderr


def test_bench_refuses_a_warmup_too_short_for_any_framework():
    """`--frameworks sb3 --warmup 0` passed the checks, then the peer's clock never started and it crashed."""
    for frameworks in ("sb3", "sbx", "softac", "softac,sbx"):
        assert_clean_error(run_cli("bench", "--frameworks", frameworks, "--warmup", "0"), "--warmup must be >= 300")


@pytest.mark.parametrize("module", ["softac.peers", "softac.peers.bench"])  # the peers' entry point, and the older form
def test_a_peer_process_is_started_through_the_peers_entry_point(module):
    """`python -m softac.peers` runs a peer (the sweep's peer trials and softac bench start it); the older
    `python -m softac.peers.bench run|throughput|solve sb3|sbx` goes to the same parser."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", module, "run", "sbx", "--env", "Pendulum-v1"], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2 and "run needs --out" in r.stderr, r.stderr
    r = subprocess.run([sys.executable, "-m", module, "throughput", "rllib"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2 and "invalid choice: 'rllib'" in r.stderr, r.stderr


def test_bench_compares_like_with_like():
    """Each --algorithm has its own peers: SAC's are SB3's and SBX's SAC, CrossQ's are SBX's CrossQ."""
    assert_clean_error(run_cli("bench", "--algorithm", "crossq", "--frameworks", "softac,sb3"),
                       "sb3", "another algorithm than --algorithm crossq")
    assert_clean_error(run_cli("bench", "--frameworks", "softac,sbx-crossq"), "sbx-crossq", "--algorithm sac")
    assert_clean_error(run_cli("bench", "--algorithm", "td3"), "--algorithm")


@pytest.mark.bench
def test_bench_crossq_runs_the_crossq_preset_beside_sbx_crossq_at_its_settings():
    """softac's crossq preset and the (stand-in) SBX CrossQ at the same settings, each in its own process;
    both learn from step 100 in a throughput run, whatever their learning_starts for whole runs."""
    from conftest import TESTS, child_env

    stand_ins = {"PYTHONPATH": child_env(TESTS / "fake_peers")["PYTHONPATH"]}
    r = run_cli("bench", "--algorithm", "crossq", "--frameworks", "softac,sbx-crossq-softac", "--env",
                "softac_test_envs:Drift-v0", "--steps", "40", "--warmup", "300", "--repeats", "1",
                "--set", "hidden_sizes=16,16", "--json", env_extra=stand_ins)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert (out["algorithm"], out["softac_preset"]) == ("crossq", "crossq")
    assert out["throughput"]["softac"]["median_steps_per_s"] > 0
    assert out["throughput"]["sbx-crossq-softac"]["median_steps_per_s"] > 0
    assert "softac_ratio" in out["throughput"]["sbx-crossq-softac"]
    assert "SBX's CrossQ at softac's crossq preset settings" in r.stderr


def test_suite_time_script_counts_each_tests_compiles_processes_and_markers(tmp_path):
    """benchmarks/suite_time.py (docs/development.md, issue 64): a pytest session of its own (one xdist worker)
    with the probe in every process; the tables count per file and per marker the tests, the XLA compiles (the
    test's own and its child process's) and the processes started, and per compiled function its compiles; --report
    prints them again from what it kept."""
    import subprocess
    import sys

    from conftest import TESTS

    tests = tmp_path / "tests"
    tests.mkdir()
    (tests / "test_probed.py").write_text(
        "import subprocess, sys\nimport jax\nimport pytest\n\n\n@pytest.mark.numerics\ndef test_compiles():\n"
        "    assert float(jax.jit(lambda x: x * 2.0)(3.0)) == 6.0\n\n\ndef test_starts_a_jax_process():\n"
        "    subprocess.run([sys.executable, '-c', 'import jax; jax.jit(lambda x: x + 1)(1)'], check=True)\n")
    script, out = TESTS.parent / "benchmarks" / "suite_time.py", tmp_path / "record"
    r = subprocess.run([sys.executable, str(script), "--out", str(out), "--workers", "1", "--", "-c", "pyproject.toml",
                        "--rootdir", str(tests), "-p", "no:randomly", str(tests / "test_probed.py")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "tests: 2," in r.stdout and "processes the tests started (with JAX): 1," in r.stdout
    # each test's seconds once: from the worker that ran it (pytest-xdist's controller hears its reports again)
    assert sorted(p.name for p in (out / "events").glob("durations-*")) == ["durations-gw0.json"]
    rows = {line.split(" | ")[0].lstrip("| "): [cell.strip() for cell in line.strip(" |").split(" | ")[1:]]
            for line in r.stdout.splitlines() if line.startswith("| ") and "---" not in line}
    # tests, seconds, compile, backend, compiles, over 1 s, cache saved, processes, ...
    assert rows["test_probed.py"][0] == "2" and int(rows["test_probed.py"][4]) >= 2 and rows["test_probed.py"][7] == "1"
    assert rows["numerics"][0] == "1" and rows["(no marker)"][0] == "1" and rows["(no marker)"][7] == "1"
    # per compiled function (JAX's name for it): the test's jit(<lambda>) and the child process's, 2 compiles
    assert int(rows["jit(<lambda>)"][1]) == 2, r.stdout
    again = subprocess.run([sys.executable, str(script), "--report", str(out)], capture_output=True, text=True,
                           timeout=60)
    assert again.returncode == 0 and again.stdout.strip() == r.stdout[r.stdout.index("session: "):].strip(), again.stderr
    refused = subprocess.run([sys.executable, str(script), "--out", str(out)], capture_output=True, text=True, timeout=60)
    assert refused.returncode == 2 and "is not empty" in refused.stderr
