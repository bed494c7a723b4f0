"""Writes the old-checkpoint fixtures of tests/test_old_checkpoints.py (issue 65): run directories whose
`last` checkpoint (step 250, mid-episode, the buffer in it) was written by the code of one commit, and that
commit's own continuation of each run to step 400 (`expected/`, the learner and run state without the buffer).
A later commit that restructures the code must load these and resume them to the same state.

    cd tests && python data/old_checkpoints/make.py    # only to add a case: the committed files are the fixture

The make test flags are set as the tests set them (XLA at optimisation level 0), so that on a machine like the
one that wrote them the continuation is compared bit for bit (machine.json says which).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
TESTS = HERE.parent.parent
IMAGE = dict(encoder_channels=8, encoder_features=16, augment_pad=2, frame_stack=2)
# name: (env, config); each case exercises other learner and run-state slots of the checkpoint
CASES = {
    "sac": ("softac_test_envs:Drift-v0", dict(n_envs=2, obs_norm=True, n_step=3, buffer_obs_once=True)),
    "crossq-avg": ("softac_test_envs:Drift-v0", dict(crossq=True, policy_average_tau=0.01)),
    "her": ("softac_test_envs:PointGoal-v0", dict(her=True)),
    "drq": ("softac_test_envs:DotImage-v0", dict(**IMAGE, learning_starts=100)),
}
CHECKPOINT_AT, CONTINUED_TO = 250, 400


def machine() -> dict[str, str]:
    """What decides whether XLA here computes what it computed where the fixture was written: the CPU's
    vector instruction sets, the XLA flags and JAX's version."""
    import jax

    from softac.base.cpus import cpu_flags

    flags = {flag for flag in cpu_flags() if re.fullmatch(r"avx512\w*|amx\w*|avx2|fma", flag)}
    return {"isa": " ".join(sorted(flags)), "xla_flags": os.environ.get("XLA_FLAGS", ""), "jax": jax.__version__}


def make(name: str) -> None:
    from conftest import tiny_config
    from softac import SAC

    env_id, extra = CASES[name]
    out = HERE / name
    shutil.rmtree(out, ignore_errors=True)
    agent = SAC(tiny_config(env_id, **extra, seed=3, loggers="none"))
    agent.learn(CHECKPOINT_AT, run_dir=out / "run", progress=False)
    agent.learn(CONTINUED_TO - CHECKPOINT_AT, run_dir=out / "continued", progress=False)
    agent.save(out / "expected")
    shutil.rmtree(out / "continued")
    (out / "run" / ".lock").unlink(missing_ok=True)


if __name__ == "__main__":
    if len(sys.argv) == 2:  # one case, in a process of its own (the env flags below set)
        sys.path.insert(0, str(TESTS))
        make(sys.argv[1])
    else:
        env = {**os.environ, "XLA_FLAGS": "--xla_backend_optimization_level=0", "JAX_PLATFORMS": "cpu",
               "PYTHONPATH": str(TESTS)}
        for case in CASES:
            subprocess.run([sys.executable, __file__, case], env=env, check=True, cwd=TESTS)
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                cwd=HERE).stdout.strip()
        os.environ["XLA_FLAGS"] = env["XLA_FLAGS"]
        (HERE / "machine.json").write_text(json.dumps({"commit": commit, **machine()}, indent=1) + "\n")
