"""Digests of what each preset trains: one short run per preset, hashed, to check that a change to the learner
leaves today's presets bit-identical (issue 42: new variants must not move the runs users already have).

    python benchmarks/preset_identity.py --out /tmp/after.json
    PYTHONPATH=/path/to/old/checkout/src python benchmarks/preset_identity.py --out /tmp/before.json
    python benchmarks/preset_identity.py --compare /tmp/before.json /tmp/after.json

Each run trains `--steps` env steps past its preset's learning_starts (so the update runs) on the preset's own
env, in-process on one CPU, and hashes every leaf of the learner's state (networks, targets, optimisers, alpha,
key, batch-renormalisation statistics) and the progress rows' metric columns. Equal digests at two commits
mean the presets compute the same numbers, bit for bit, on this machine. A second digest of the leaves alone
(sorted, without their paths) says the numbers are the same where a change only moved fields of the state.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
from pathlib import Path

# (preset, env): the env presets extend these, so each family is covered once; the goal env covers HER
CASES = [
    ("default", "InvertedPendulum-v5"),
    ("sb3", "InvertedPendulum-v5"),
    ("cleanrl", "InvertedPendulum-v5"),
    ("sac-100k", "Hopper-v5"),
    ("crossq", "Hopper-v5"),
    ("crossq-wn", "Hopper-v5"),
    ("crossq-avg", "Hopper-v5"),
    ("tqc", "Hopper-v5"),
    ("droq", "Hopper-v5"),
    ("simba", "Hopper-v5"),
    ("Humanoid-v5", "Humanoid-v5"),
    ("FetchReach-v4", "FetchReach-v4"),
    # DrQ from pixels, its networks and images made small to train in about a minute (target encoder, actor head)
    ("drq", "InvertedPendulum-v5", {"pixel_size": 48, "hidden_sizes": [64, 64], "batch_size": 32,
                                    "learning_starts": 200, "encoder_channels": 16}),
]
METRIC_COLUMNS = ("critic_loss", "actor_loss", "alpha", "alpha_loss", "q1_mean", "q2_mean", "log_prob_mean")  # fixed: the digests compare across commits


def digest(preset: str, env_id: str, steps: int, overrides: dict | None = None) -> dict[str, str]:
    import jax
    import numpy as np

    from softac import SAC, SACConfig
    from softac.run.csv_logs import read_csv

    config = SACConfig.preset(preset, env_id=env_id).replace(**(overrides or {}))
    config = config.replace(total_steps=config.learning_starts + steps, eval_interval=0, loggers="none",
                            checkpoint_interval=0, buffer_size=min(config.buffer_size, 100_000))
    with tempfile.TemporaryDirectory() as tmp:
        agent = SAC(config)
        agent.learn(config.total_steps, run_dir=Path(tmp) / "run", progress=False)
        state, leaves = hashlib.sha256(), []
        for path, leaf in jax.tree_util.tree_flatten_with_path(agent.learner.state)[0]:
            data = np.ascontiguousarray(np.array(leaf, copy=True))
            state.update(jax.tree_util.keystr(path).encode())
            state.update(data.tobytes())
            leaves.append(f"{data.dtype} {data.shape} {hashlib.sha256(data.tobytes()).hexdigest()}")
        rows = [[row.get(c, "") for c in ("step", *METRIC_COLUMNS)] for row in read_csv(Path(tmp) / "run" / "progress.csv")]
    # contents: the same leaves whatever their names and order in the state (issue 65 moves fields of SACState)
    contents = hashlib.sha256("\n".join(sorted(leaves)).encode()).hexdigest()
    return {"state": state.hexdigest(), "contents": contents, "progress": hashlib.sha256(json.dumps(rows).encode()).hexdigest(),
            "matmul_dtype": agent.learner.matmul_dtype}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", help="write the digests here (JSON)")
    p.add_argument("--steps", type=int, default=1000, help="env steps past learning_starts per preset")
    p.add_argument("--only", nargs="*", help="presets to run (default: all cases)")
    p.add_argument("--compare", nargs=2, metavar=("BEFORE", "AFTER"), help="compare two digest files")
    a = p.parse_args(argv)
    if a.compare:
        before, after = (json.loads(Path(f).read_text()) for f in a.compare)
        differ = False
        for name in sorted(set(before) & set(after)):
            same = before[name]["state"] == after[name]["state"]
            renamed = not same and before[name].get("contents", 1) == after[name].get("contents", 2)
            rows_note = "" if before[name].get("progress") == after[name].get("progress") else " (progress rows differ)"
            verdict = "identical" if same else "identical leaves, laid out otherwise in the state" if renamed else "DIFFERENT"
            print(f"{name}: {verdict}{rows_note}")
            same |= renamed
            differ |= not same
        return 1 if differ else 0
    results = {}
    for preset, env_id, *overrides in CASES:
        if a.only and preset not in a.only:
            continue
        results[f"{preset}@{env_id}"] = digest(preset, env_id, a.steps, *overrides)
        print(preset, env_id, results[f"{preset}@{env_id}"], flush=True)
    if a.out:
        Path(a.out).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
