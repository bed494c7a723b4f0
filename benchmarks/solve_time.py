"""Seconds to solve: the whole `softac train --target-return R` command, process start to exit, per seed.

    python benchmarks/solve_time.py --seeds 0 1 2 3 4 [--target 1000] [-- extra softac train args]

Prints one line per seed (wall seconds, steps, solved?) and the median.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--target", type=float, default=1000.0)
    parser.add_argument("extra", nargs="*", help="more `softac train` arguments (after --)")
    args = parser.parse_args()
    rows = []
    for seed in args.seeds:
        with tempfile.TemporaryDirectory() as tmp:
            run = Path(tmp) / "run"
            t0 = time.perf_counter()
            r = subprocess.run([sys.executable, "-m", "softac", "train", "--seed", str(seed), "--target-return",
                                str(args.target), "--out", str(run), "--no-progress", *args.extra],
                               capture_output=True, text=True)
            wall = time.perf_counter() - t0
            evals = (run / "eval.csv").read_text().splitlines()[1:] if (run / "eval.csv").exists() else []
            last = evals[-1].split(",") if evals else ["0", "nan"]
            solved = r.returncode == 0 and float(last[1]) >= args.target
            rows.append({"seed": seed, "wall_s": round(wall, 2), "steps": int(last[0]), "solved": solved,
                         "last_eval": float(last[1])})
            print(json.dumps(rows[-1]), flush=True)
    walls = [r["wall_s"] for r in rows]
    print(f"median wall {statistics.median(walls):.1f}s, median steps {statistics.median(r['steps'] for r in rows):.0f}, "
          f"solved {sum(r['solved'] for r in rows)}/{len(rows)}")


if __name__ == "__main__":
    main()
