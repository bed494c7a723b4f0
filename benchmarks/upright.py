"""Whether a HalfCheetah dataset's policy runs upright (issue 68): the torso's pitch (observation 1, rooty) of its
first episodes, |pitch| averaged. A flipped HalfCheetah runs on its back at |pitch| ~3 rad and earns a few thousand
(crossq-avg's seed 1000 source made such a "medium" dataset, 2,128 on its back; docs/results-notes.md); an upright
one stays within ~0.5 rad. Exit 0 and say so when upright, 1 when flipped, 2 on a bad argument.
Usage: python benchmarks/upright.py DATASET_DIR [--episodes 5] [--max-pitch 1.0]"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def mean_abs_pitch(dataset_dir: Path, episodes: int) -> float:
    from minari.dataset.minari_dataset import MinariDataset

    data = MinariDataset(dataset_dir / "data")
    pitches = [np.abs(np.asarray(ep.observations)[:, 1]) for _, ep in zip(range(episodes), data.iterate_episodes())]
    return float(np.mean(np.concatenate(pitches)))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--episodes", type=int, default=5)
    parser.add_argument("--max-pitch", type=float, default=1.0)
    args = parser.parse_args()
    if not (args.dataset / "data").is_dir():
        print(f"upright.py: {args.dataset} is not a dataset written by `softac dataset` (no data/)", file=sys.stderr)
        return 2
    pitch = mean_abs_pitch(args.dataset, args.episodes)
    upright = pitch <= args.max_pitch
    print(f"{args.dataset}: mean |pitch| {pitch:.2f} rad over its first {args.episodes} episodes: "
          f"{'upright' if upright else 'flipped'} (limit {args.max_pitch} rad)")
    return 0 if upright else 1


if __name__ == "__main__":
    sys.exit(main())
