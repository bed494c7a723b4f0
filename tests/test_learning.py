"""Learning: the default preset solves InvertedPendulum-v5 (the command a new user types)."""

import json

import pytest

from conftest import run_cli
from fast_compile import users_xla_flags


@pytest.mark.slow
def test_default_preset_solves_inverted_pendulum(tmp_path):
    run = tmp_path / "run"
    r = run_cli("train", "--target-return", "1000", "--out", str(run), "--no-progress", timeout=900,
                env_extra={"XLA_FLAGS": users_xla_flags()})  # as users compile
    assert r.returncode == 0, r.stderr
    r = run_cli("eval", str(run), "--episodes", "10", "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["mean_return"] >= 950
