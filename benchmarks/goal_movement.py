"""How often training moved the achieved goal of a goal env (FetchPush: the object), read from a run's replay buffer.

    python benchmarks/goal_movement.py RUN_DIR                     # its checkpoints/last (which holds the buffer)
    python benchmarks/goal_movement.py RUN_DIR --block 500 --thresholds 0.01 0.05 --json

Hindsight relabelling (HER) teaches a policy to reach goals it achieved. On FetchPush the achieved goal is the
object's position: in an episode where the arm never touches the object, every relabelled goal is "leave it where
it is", which an idle arm achieves, and HER teaches nothing about pushing. The share of training episodes in which
the object moved at all is therefore the signal to watch while the success rate is still flat (docs/results-notes.md).

For each block of `--block` training episodes (oldest first) it prints the share of episodes in which the achieved
goal got farther than each threshold (in the env's units: metres for Fetch) from where it was at the episode's
first step. Episodes whose first steps the buffer has already overwritten are left out, and so is an episode still
running when the checkpoint was written.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np


def movement_by_episode(buffer: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Episode ids (ascending) and, for each, the farthest its achieved goal got from its position at the episode's
    first step: from a HER buffer's state (softac.replay.collector.buffer_state of a checkpoint's arrays)."""
    size = int(buffer["pos_size"][1])
    episode, t, done = buffer["episode"][:size], buffer["t"][:size], buffer["done"][:size]
    start, moved_to = buffer["obs.achieved_goal"][:size], buffer["next_obs.achieved_goal"][:size]
    order = np.lexsort((t, episode))  # each episode's rows in step order
    ids, first, lengths = np.unique(episode[order], return_index=True, return_counts=True)
    complete = (t[order[first]] == 0) & done[order[first + lengths - 1]]
    distance = np.linalg.norm(moved_to[order] - np.repeat(start[order[first]], lengths, axis=0), axis=1)
    farthest = np.maximum.reduceat(distance, first)
    return ids[complete], farthest[complete]


def shares_by_block(farthest: np.ndarray, ids: np.ndarray, block: int, thresholds: list[float]) -> list[dict]:
    rows = []
    for lo in range(0, len(farthest), block):
        part = farthest[lo:lo + block]
        rows.append({"first_episode": int(ids[lo]), "last_episode": int(ids[lo:lo + block][-1]), "episodes": len(part),
                     **{f"moved_over_{th:g}": float(np.mean(part > th)) for th in thresholds}})
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", help="a run directory (its last checkpoint) or a checkpoint directory")
    p.add_argument("--block", type=int, default=1000, help="training episodes per printed row")
    p.add_argument("--thresholds", type=float, nargs="+", default=[0.01, 0.05])
    p.add_argument("--json", action="store_true", help="print the rows as one JSON list")
    a = p.parse_args(argv)
    if a.block < 1 or any(th < 0 for th in a.thresholds):
        p.error("--block must be at least 1 and --thresholds at least 0")

    from softac.run import checkpoint
    from softac.replay.collector import buffer_state
    from softac.errors import SoftacError

    try:
        _, arrays = checkpoint.load(checkpoint.resolve(a.run, "last"))
    except SoftacError as e:
        print(f"goal_movement.py: error: {e}", file=sys.stderr)
        return 2
    buffer = buffer_state(arrays)
    if "obs.achieved_goal" not in buffer:
        print(f"goal_movement.py: error: {a.run}'s checkpoint holds no goal env's replay buffer (a HER run's last "
              "checkpoint with its buffer)", file=sys.stderr)
        return 2
    ids, farthest = movement_by_episode(buffer)
    rows = shares_by_block(farthest, ids, a.block, a.thresholds)
    if a.json:
        print(json.dumps(rows))
        return 0
    for row in rows:
        shares = "  ".join(f"moved > {th:g}: {row[f'moved_over_{th:g}']:.3f}" for th in a.thresholds)
        print(f"episodes {row['first_episode']}-{row['last_episode']} ({row['episodes']}): {shares}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
