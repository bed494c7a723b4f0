"""Seconds to solve: the whole `softac train --target-return R` command, process start to exit, per seed.

    python benchmarks/solve_time.py --seeds 0 1 2 3 4 [--env ID] [--target 1000] [-- extra softac train args]

Prints one line per seed (wall seconds, steps, solved?) and the median. The run itself is
`softac.peers.bench.solve_softac`, the same measurement `softac bench --solve` makes.
"""

from __future__ import annotations

import argparse
import json
import statistics

from softac.peers.bench import solve_softac


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--env", default="InvertedPendulum-v5")
    parser.add_argument("--target", type=float, default=1000.0)
    parser.add_argument("--timeout", type=float, default=1800.0)
    parser.add_argument("extra", nargs="*", help="more `softac train` arguments (after --)")
    args = parser.parse_args()
    rows = []
    for seed in args.seeds:
        out, wall, err = solve_softac(args.env, seed, args.target, args.timeout, args.extra)
        row = {"seed": seed, "wall_s": round(wall, 2), **(out or {"steps": 0, "solved": False, "error": err})}
        rows.append(row)
        print(json.dumps(row), flush=True)
    walls = [r["wall_s"] for r in rows]
    print(f"median wall {statistics.median(walls):.1f}s, median steps {statistics.median(r['steps'] for r in rows):.0f}, "
          f"solved {sum(r['solved'] for r in rows)}/{len(rows)}")


if __name__ == "__main__":
    main()
