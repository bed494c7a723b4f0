"""Write docs/results.md and docs/results/*.png from the sweeps made by benchmarks/results.sh.

    python benchmarks/results_doc.py sweeps        # SWEEPS directory of results.sh

Each env has two sweep directories, ENV-softac and ENV-sb3; the threshold of each is the one given to its
sweep command (kept in results.sh). Tables and figures come from the trial run directories alone.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from softac.bench import machine_description
from softac.plots import plot_comparison
from softac.sweep import aggregate, load_spec, markdown_table, trial_dirs, trial_rows

ENVS = {"InvertedPendulum-v5": 1000.0, "InvertedPendulum-v4": 1000.0, "Pusher-v5": -40.0}

INTRO = """# Results: softac and Stable-Baselines3 on the same machine

Made with `softac sweep` (Ray Tune, one trial per CPU, two trials at a time) on {machine}.
softac runs each env's preset on 5 seeds; Stable-Baselines3's SAC runs at its defaults on 3 seeds
(`softac sweep --framework sb3`), with the same step budget and the same evaluation: every
`eval_interval` steps, 10 episodes with deterministic actions, episode i seeded `seed + 1000000 + i`.
Each trial's process is pinned to one CPU, so both frameworks train on one CPU per trial and wall times
compare like with like.

- final eval: the last evaluation of each trial (mean ± std over seeds, and the 95% Student-t interval);
- best eval: the best evaluation of each trial;
- reached R: trials whose evaluation reached the threshold R at least once, with the median steps and
  seconds (training wall time, evaluations included) until the first time;
- wall s: the whole trial's training time.

Regenerate everything (about an hour on a 2-core machine; rerunning continues where it stopped):

```sh
make bench && .venv/bin/pip install -e '.[ray]'
SOFTAC=.venv/bin/softac SWEEPS=sweeps bash benchmarks/results.sh
.venv/bin/python benchmarks/results_doc.py sweeps
```

The sweep commands, from `benchmarks/results.sh`:

```sh
{commands}
```
"""


def section(env: str, threshold: float, sweeps: Path, figures: Path) -> list[str]:
    dirs = {fw: sweeps / f"{env}-{fw}" for fw in ("softac", "sb3")}
    present = {fw: d for fw, d in dirs.items() if (d / "sweep.json").exists()}
    if not present:
        return [f"## {env}", "", "Not run yet.", ""]
    rows, runs, steps = [], [], set()
    for fw, d in present.items():
        spec = load_spec(d)
        steps.add(spec.steps)
        table = aggregate(trial_rows(d, spec, threshold), [], threshold, name=fw)
        rows.extend(table)
        runs.extend(trial_dirs(d))
    figure = figures / f"{env}.png"
    plot_comparison(runs, figure)
    budget = ", ".join(f"{s:,}" for s in sorted(steps))
    return [f"## {env}", "", f"{budget} env steps per trial. ![{env}](results/{figure.name})", "",
            markdown_table(rows, threshold), ""]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("sweeps", type=Path)
    p.add_argument("--docs", type=Path, default=Path(__file__).resolve().parent.parent / "docs")
    a = p.parse_args(argv)
    figures = a.docs / "results"
    figures.mkdir(parents=True, exist_ok=True)
    script = (Path(__file__).parent / "results.sh").read_text().splitlines()
    commands = "\n".join(line.strip() for line in script if "$SOFTAC sweep" in line or line.startswith("  --"))
    text = [INTRO.format(machine=machine_description(), commands=commands)]
    for env, threshold in ENVS.items():
        text.extend(section(env, threshold, a.sweeps, figures))
    notes = a.docs / "results-notes.md"
    if notes.exists():
        text.append(notes.read_text())
    (a.docs / "results.md").write_text("\n".join(text))
    print(json.dumps({"wrote": str(a.docs / "results.md")}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
