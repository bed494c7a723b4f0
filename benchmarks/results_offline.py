"""docs/results.md's section on starting from data (issue 68): a preset with a softac-made dataset in every batch
beside the same preset from scratch, from the sweeps of benchmarks/offline_rlpd.sh and its CPU form
(SWEEPS/offline-ENV-NAME): the return at fixed online steps, the first step each seed's evaluation reaches the
from-scratch configuration's final mean, and the one-core wall time."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import yaml

from results_common import finished_trials, machines_of, short_machines, timing_excluded
from softac.sweep import load_spec

OFFLINE = "Starting from data"
PREFIX = "offline-"
CHECKPOINTS = (10_000, 25_000, 50_000, 100_000)  # issue 68's rows


def eval_curve(run: Path) -> dict[int, float]:
    """A trial's evaluations, step -> mean return."""
    with open(run / "eval.csv", newline="") as f:
        return {int(float(r["step"])): float(r["mean_return"]) for r in csv.DictReader(f)}


def offline_runs(d: Path, excluded: dict[str, str]) -> dict | None:
    """One sweep's finished trials: env, preset, the dataset (its directory's name, or None), the evaluation curves,
    wall seconds of the comparable ones, machines."""
    rows = finished_trials(d, excluded)
    if not rows:
        return None
    spec = load_spec(d)
    runs = [d / r["trial"] for r in rows]
    config = yaml.safe_load((runs[0] / "config.yaml").read_text()) or {}
    data = config.get("offline_data")
    return {"env": spec.env_id, "preset": spec.preset or "env", "data": Path(str(data)).name if data else None,
            "mode": config.get("offline_mode", "mix"), "fraction": config.get("offline_fraction"),
            "seeds": [int(r["seed"]) for r in rows], "curves": [eval_curve(run) for run in runs],
            "walls": [r["wall_s"] for r in rows if r["timed"]], "machines": machines_of(runs)}


def first_reaching(curve: dict[int, float], level: float) -> int | None:
    return next((step for step in sorted(curve) if curve[step] >= level), None)


def offline_section(sweeps: Path) -> list[str]:
    excluded = timing_excluded(sweeps)
    dirs = sorted(d for d in sweeps.glob(PREFIX + "*") if (d / "sweep.json").exists())
    runs = [(d.name, r) for d in dirs if (r := offline_runs(d, excluded)) is not None]
    if not runs:
        return []
    lines = [f"## {OFFLINE}", "",
             "A preset trained with a dataset softac made from its own runs in every batch (`--offline-data`, half "
             "of each batch from the data: `offline_fraction` 0.5, RLPD's symmetric sampling), beside the same preset "
             "from scratch, on fresh seeds, 100k online steps, evaluations every 5k (10 deterministic episodes), "
             "one pinned CPU a trial. The datasets (benchmarks/offline_rlpd.sh's `sources` and `datasets` parts; "
             "not kept in the repository, the script rebuilds them): \"medium\", 100k transitions of the "
             "deterministic policy of a `crossq-avg` run stopped at its first evaluation past a third of "
             "`crossq-avg`'s 100k-step v4 return (Hopper 927, HalfCheetah 2,135): Hopper's of seed 1000 (950); "
             "HalfCheetah's of seed 1001 (3,337 at 20k steps), the first seed whose policy runs upright "
             "(benchmarks/upright.py). Seed 1000's HalfCheetah never passed 2,135 and ran on its back at 2,132 after "
             "100k steps: the sweep offline-HalfCheetah-v5-crossq-avg-medium learned from that flipped dataset, "
             "-medium-upright from seed 1001's; \"expert\", 100k transitions of the deterministic policy of the "
             "best checkpoint of a 100k-step `crossq-avg` run of seed 1000 (Hopper: its 55k-step evaluation, 3,233; "
             "the dataset's mean return 3,232; HalfCheetah: its 95k-step one, 7,781; the dataset's 7,765, upright). "
             "The returns at 10k, 25k, 50k "
             "and 100k online steps are the means ± sd over seeds; \"reaches scratch\" is the median over seeds of "
             "the first evaluation at or above the from-scratch configuration's mean at 100k (with how many seeds "
             "got there). RLPD's own preset (`rlpd`: 20 updates of 10 critics per env step) costs 6-10 hours a "
             "100k-step run on one of these cores (docs/performance.md), a GPU's work still to do; its sweeps named "
             "-25k stop at 25k online steps, the goal's point, about 85 minutes a run on one core. Published RLPD, "
             "on other data (D4RL's datasets, 250k online steps): the authors publish a plot, not result files; read "
             "off it (ikostrikov/rlpd assets/plots.png, the mean over all D4RL locomotion tasks, normalised so that "
             "0 is a random policy and 100 D4RL's expert), about 45 at 10k steps, 55-60 at 25k, 70 at 50k and 80 "
             "at 100k. D4RL's expert returns are 3,234 on Hopper and 12,135 on HalfCheetah (v2).", ""]
    for env in sorted({r["env"] for _, r in runs}):
        mine = [(name, r) for name, r in runs if r["env"] == env]
        scratch = [r for _, r in mine if r["data"] is None and r["preset"] == "crossq-avg"]
        level = float(np.mean([c[max(c)] for c in scratch[0]["curves"]])) if scratch else None
        lines += [f"### {env}", "",
                  "| sweep | preset | data | seeds | 10k | 25k | 50k | 100k | reaches scratch"
                  + (f" ({level:,.0f})" if level is not None else "") + " | wall s (median) | machine |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        lines += [_row(name, r, level) for name, r in mine] + [""]
    return lines


def _at(curves: list[dict[int, float]], step: int) -> str:
    values = [c[step] for c in curves if step in c]
    if len(values) < len(curves):
        return "-"
    spread = np.std(values, ddof=1) if len(values) > 1 else 0.0
    return f"{np.mean(values):,.0f} ± {spread:,.0f}"


def _row(name: str, r: dict, level: float | None) -> str:
    reached = "-"
    if level is not None:
        steps = [s for c in r["curves"] if (s := first_reaching(c, level)) is not None]
        reached = f"{np.median(steps) / 1000:g}k ({len(steps)}/{len(r['curves'])})" if steps else f"0/{len(r['curves'])}"
    data = f"{r['data']} ({r['mode']}, {r['fraction']:g})" if r["data"] and r["mode"] == "mix" else (r["data"] or "none")
    wall = f"{np.median(r['walls']):,.0f}" if r["walls"] else "-"
    return (f"| {name} | {r['preset']} | {data} | {', '.join(map(str, r['seeds']))} | "
            + " | ".join(_at(r["curves"], s) for s in CHECKPOINTS)
            + f" | {reached} | {wall} | {short_machines(r['machines'])} |")
