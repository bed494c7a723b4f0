"""Write benchmarks/published-dmc-100k-runs.yaml: each seed's return at 100k frames of the methods in
published-dmc-100k.yaml, on issue 43's eight DMC tasks, from the two repositories' result files, so the DMC
aggregate in docs/results.md bootstraps the published methods as it does softac's runs (per-run scores; the
means and standard deviations in published-dmc-100k.yaml come from the same rows).

    python benchmarks/published_runs.py SIMBA_GIT_DIR SIMBAV2_GIT_DIR

Each argument is a git directory (e.g. the `fetch` tool's snapshot of SonyResearch/simba and dojeon-ai/SimbaV2);
the files are read at the commits published-dmc-100k.yaml names.
"""

from __future__ import annotations

import csv
import io
import subprocess
import sys
from pathlib import Path

import yaml

HERE = Path(__file__).resolve().parent
TASKS = ["cheetah-run", "walker-walk", "walker-run", "hopper-hop", "finger-spin", "quadruped-run", "reacher-hard",
         "cartpole-swingup"]
FRAMES = 100_000.0


def seed_returns(git_dir: str, commit: str, path: str) -> dict[str, list[float]]:
    """{task: [return at 100k frames per seed, in seed order]} of one result CSV."""
    text = subprocess.run(["git", "--git-dir", git_dir, "show", f"{commit}:{path}"], check=True,
                          capture_output=True, text=True).stdout
    found: dict[str, dict[str, float]] = {}
    for row in csv.DictReader(io.StringIO(text)):
        task = row["env_name"].replace("_", "-")
        if task in TASKS and row["metric"] == "avg_return" and float(row["env_step"]) == FRAMES:
            found.setdefault(task, {})[row["seed"]] = float(row["value"])
    return {task: [round(v, 1) for _, v in sorted(seeds.items(), key=lambda kv: int(float(kv[0])))]
            for task, seeds in sorted(found.items(), key=lambda kv: TASKS.index(kv[0]))}


def main(argv: list[str]) -> int:
    simba, simba_v2 = argv
    published = yaml.safe_load((HERE / "published-dmc-100k.yaml").read_text())
    v2_commit = published["source"].rsplit("/tree/", 1)[1].split("/")[0]
    runs = {}
    for method, entry in published["methods"].items():
        source = entry.get("source", published["source"])
        commit = source.rsplit("/tree/", 1)[1].split("/")[0]
        git_dir, path = (simba, f"results/{entry['file']}") if "SonyResearch" in source else (simba_v2, f"results/{entry['file']}")
        assert "SonyResearch" in source or commit == v2_commit
        runs[method] = seed_returns(git_dir, commit, path)
    header = ("# Each seed's return at 100k frames (action repeat counted) on issue 43's DMC tasks, per method of\n"
              "# published-dmc-100k.yaml (same files and commits), written by benchmarks/published_runs.py.\n")
    (HERE / "published-dmc-100k-runs.yaml").write_text(header + yaml.safe_dump({"runs": runs}, sort_keys=False,
                                                                               default_flow_style=None, width=120))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
