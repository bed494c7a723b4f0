"""Learning: the default preset solves InvertedPendulum-v5 (the command a new user types)."""

import json
import os

import pytest

from conftest import run_cli


def xla_flags_of_users() -> str:
    """XLA_FLAGS without any --xla_backend_optimization_level (make test's, the Makefile's FAST_COMPILE, and one
    of your own alike): the learning test trains at XLA's default level, as the command a user types compiles,
    its thousands of updates at full speed."""
    flags = os.environ.get("XLA_FLAGS", "").split()
    return " ".join(f for f in flags if not f.lstrip("-").startswith("xla_backend_optimization_level="))


@pytest.mark.slow
def test_default_preset_solves_inverted_pendulum(tmp_path):
    run = tmp_path / "run"
    r = run_cli("train", "--target-return", "1000", "--out", str(run), "--no-progress", timeout=900,
                env_extra={"XLA_FLAGS": xla_flags_of_users()})
    assert r.returncode == 0, r.stderr
    r = run_cli("eval", str(run), "--episodes", "10", "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["mean_return"] >= 950
