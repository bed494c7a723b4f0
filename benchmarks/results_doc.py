"""Write docs/results.md and docs/results/*.png from the sweeps made by benchmarks/results.sh.

    python benchmarks/results_doc.py sweeps        # SWEEPS directory of results.sh

Each env has a sweep directory per framework, ENV-softac, ENV-sbx and/or ENV-sb3; the threshold of each is the
one given to its sweep command (kept in results.sh). Tables and figures come from the trial run directories
alone. An env none of whose sweeps is in SWEEPS keeps its section of the current docs/results.md, so the
classic and the MuJoCo sets can be regenerated apart.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from softac.cpus import machine_description
from softac.plots import plot_comparison
from softac.sweep import aggregate, load_spec, markdown_table, trial_dirs, trial_rows

# env -> the threshold its sweeps were given (None: no threshold columns)
ENVS: dict[str, float | None] = {"InvertedPendulum-v5": 1000.0, "InvertedPendulum-v4": 1000.0, "Pusher-v5": -40.0,
                                 "HalfCheetah-v5": None, "Hopper-v5": None, "Walker2d-v5": None, "Ant-v5": None,
                                 "Humanoid-v5": None, "Swimmer-v5": None, "Reacher-v5": None,
                                 "InvertedDoublePendulum-v5": None}
FRAMEWORKS = ("softac", "sbx", "sb3")
# ENV-softac-NAME: another preset or options on the env (benchmarks/results.sh's `options` and `fallback`, #18)

INTRO = """# Results: softac beside SBX and Stable-Baselines3 on the same machine

Made with `softac sweep` (Ray Tune, one trial per CPU, two trials at a time, each trial's process pinned
to its CPU); each env's section names the machine its sweeps ran on (this page was last written on
{machine}). Every framework is evaluated the same way: every `eval_interval` steps, 10 episodes with
deterministic actions, episode i seeded `seed + 1000000 + i`.

- Classic set (InvertedPendulum-v5/v4, Pusher-v5): softac's env presets on 5 seeds, Stable-Baselines3's
  SAC at its defaults on 3 seeds (`softac sweep --framework sb3`), the same step budget.
- MuJoCo suite (HalfCheetah, Hopper, Walker2d, Ant, Humanoid, all v5): 100k env steps; softac's env
  presets (CrossQ) on 3 seeds, SBX's SAC at its defaults on 2 seeds (`softac sweep --framework sbx`;
  Stable-Baselines3 trains ~3x slower than SBX and is left out of this budget).
- Other rows, on the same seeds and budget: `softac preset=NAME` is another preset on the env (`results.sh
  options`: plain SAC, `sac-100k`, beside the CrossQ presets; `results.sh fallback`: `default` and
  `crossq` on envs with no preset of their own), `softac KEY=VALUE ...` the env's preset with options.

Columns:
- final eval: the last evaluation of each trial (mean ± std over seeds, and the 95% Student-t interval);
  final IQM: its interquartile mean over seeds (rliable's; the plain mean below 4 seeds);
- best eval: the best evaluation of each trial;
- median wall s: the whole trial's training time, evaluations included; steps/s: steps over that time;
- reached R (classic set): trials whose evaluation reached the threshold R at least once, with the
  median steps and seconds (training wall time, evaluations included) until the first time.

Regenerate (rerunning continues where it stopped; `results.sh Hopper-v5` runs one env, `results.sh mujoco`
the suite):

```sh
make bench
SOFTAC=.venv/bin/softac bash benchmarks/results.sh      # sweeps in benchmarks/sweeps
.venv/bin/python benchmarks/results_doc.py benchmarks/sweeps
```

The sweep commands, from `benchmarks/results.sh` ($1 is the env id):

```sh
{commands}
```
"""


def kept_sections(results_md: Path) -> dict[str, list[str]]:
    """The `## ENV` sections of an existing results.md, by env."""
    if not results_md.exists():
        return {}
    sections: dict[str, list[str]] = {}
    current: str | None = None
    for line in results_md.read_text().splitlines():
        if line.startswith("## "):
            current = line[3:].strip() if line[3:].strip() in ENVS else None
            if current:
                sections[current] = []
        if current:
            sections[current].append(line)
    return sections


def env_sweeps(env: str, sweeps: Path) -> dict[str, Path]:
    """The env's sweep directories by table name: softac's preset, its option variants, then the peers."""
    found = {d.name[len(env) + 1:]: d for d in sweeps.glob(f"{env}-*") if (d / "sweep.json").exists()}
    variants = sorted(name for name in found if name.startswith("softac-"))
    order = ["softac", *variants, "sbx", "sb3"]
    named = {}
    for name in order:
        if name in found:
            spec = load_spec(found[name])
            options = ([f"preset={spec.preset}"] if spec.preset else []) + list(spec.overrides)
            named[" ".join(["softac", *options]) if name in variants and options else name] = found[name]
    return named


def section(env: str, threshold: float | None, sweeps: Path, figures: Path,
            kept: dict[str, list[str]]) -> list[str]:
    present = env_sweeps(env, sweeps)
    if not present:
        return kept.get(env) or [f"## {env}", "", "Not run yet.", ""]
    rows, runs, steps = [], [], set()
    for name, d in present.items():
        spec = load_spec(d)
        steps.add(spec.steps)
        table = aggregate(trial_rows(d, spec, threshold), [], threshold, name=name)
        rows.extend(table)
        runs.extend(trial_dirs(d))
    figure = figures / f"{env}.png"
    plot_comparison(runs, figure)
    budget = ", ".join(f"{s:,}" for s in sorted(steps))
    return [f"## {env}", "", f"{budget} env steps per trial, on {machines_of(runs)}. ![{env}](results/{figure.name})", "",
            markdown_table(rows, threshold), ""]


def machines_of(runs: list[Path]) -> str:
    """The machines the trials' config.yaml name, every segment of a resumed trial's (runs made before it was
    recorded: this machine)."""
    import yaml

    names = set()
    for run in runs:
        config = (yaml.safe_load((run / "config.yaml").read_text()) if (run / "config.yaml").exists() else None) or {}
        for segment in config.get("segments") or [config]:
            names.add(segment.get("machine") or machine_description())
    return " and ".join(sorted(names))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("sweeps", type=Path)
    p.add_argument("--docs", type=Path, default=Path(__file__).resolve().parent.parent / "docs")
    a = p.parse_args(argv)
    figures = a.docs / "results"
    figures.mkdir(parents=True, exist_ok=True)
    script = (Path(__file__).parent / "results.sh").read_text().splitlines()
    commands = "\n".join(line.strip() for line in script if "$SOFTAC sweep" in line)
    kept = kept_sections(a.docs / "results.md")
    text = [INTRO.format(machine=machine_description(), commands=commands)]
    for env, threshold in ENVS.items():
        text.extend(section(env, threshold, a.sweeps, figures, kept))
    notes = a.docs / "results-notes.md"
    if notes.exists():
        text.append(notes.read_text())
    (a.docs / "results.md").write_text("\n".join(text))
    print(json.dumps({"wrote": str(a.docs / "results.md")}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
