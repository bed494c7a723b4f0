"""docs/results.md's DeepMind Control Suite section: softac's presets beside the published tables at 100k and
500k frames, and their aggregate."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from softac.outputs.plots import plot_aggregate
from softac.outputs.seed_stats import stratified_bootstrap_iqm
from softac.sweep import load_spec

from results_common import (departures, DMC, DMC_500K, DMC_SHOWN, DMC_TASKS, env_sweeps, finished_trials, machines_of,
                            PUBLISHED_DMC, PUBLISHED_DMC_500K, PUBLISHED_DMC_RUNS, timing_excluded)


def dmc_aggregate(finals: dict[str, dict[str, list[float]]], seconds: dict[str, dict[str, float]],
                  figure: Path) -> list[str]:
    """The DMC aggregate: per configuration, the IQM of every run's final return / 1000 (DMC's returns lie in
    [0, 1000], so no random-policy or best-run normalisation is needed) with its stratified-bootstrap 95%
    interval, beside each published method's over the same tasks from its per-seed results
    (benchmarks/published-dmc-100k-runs.yaml); and the summed median one-core time of a run per task."""
    import yaml

    published = yaml.safe_load(PUBLISHED_DMC_RUNS.read_text())["runs"]
    lines = ["### One aggregate", "",
             "The interquartile mean (IQM) of every run's final return / 1000 over the tasks a configuration ran, "
             "with a stratified-bootstrap 95% interval (runs resampled within each task, 20,000 resamples: "
             "rliable's method, Agarwal et al. 2021); each published method over the same tasks from its per-seed "
             "results (benchmarks/published-dmc-100k-runs.yaml). One-core time: the sum over the tasks of the "
             "median wall seconds of a run (the comparable trials), so what one seed of the whole set costs.", "",
             "| configuration | tasks | runs | IQM of return / 1000 [95% CI] | one-core s for the tasks |",
             "|---|---|---|---|---|"]
    scores: dict[str, tuple[float, float, float]] = {}

    def add_row(name: str, runs: dict[str, list[float]], tasks: list[str], seconds_cell: str) -> None:
        scope = tasks[0] if len(tasks) == 1 else f"{len(tasks)} tasks"
        label = name if len(tasks) == len(DMC_TASKS) else f"{name} ({scope})"
        scores[label] = stratified_bootstrap_iqm([[v / 1000 for v in runs[t]] for t in tasks])
        point, low, high = scores[label]
        lines.append(f"| {label} | {len(tasks)} | {sum(len(runs[t]) for t in tasks)} | "
                     f"{point:.2f} [{low:.2f}, {high:.2f}] | {seconds_cell} |")

    tasks_of_first: list[str] | None = None
    for name, per_task in finals.items():
        tasks = [t for t in DMC_TASKS if t in per_task]
        tasks_of_first = tasks_of_first or tasks
        timed = [seconds[name][t] for t in tasks if t in seconds.get(name, {})]
        total = f"{sum(timed):.0f}" + ("" if len(timed) == len(tasks) else f" ({len(timed)} tasks timed)") if timed else "-"
        add_row(name, per_task, tasks, total)
    for method in DMC_SHOWN:
        runs = published.get(method, {})
        tasks = [t for t in (tasks_of_first or []) if t in runs]
        if tasks:
            add_row(f"published {method}", runs, tasks, "GPU")
    plot_aggregate(scores, figure, "DeepMind Control Suite, 100k frames: IQM of final return / 1000",
                   "return / 1000\nerror bar: 95% stratified-bootstrap interval")
    return lines + ["", f"![DMC aggregate](results/{figure.name})", ""]


def dmc_rows(sweeps: Path, tasks: list[str], frames: int, published: dict, shown: list[str]) -> tuple[list[str], dict, dict, dict]:
    """The DMC table's rows for the sweeps that ran `frames` frames on `tasks` (each configuration's final return:
    mean ± sd over seeds, each seed, median one-core wall seconds of the comparable trials, the published means),
    and {configuration: {task: finals}}, {configuration: {task: seconds}}, {configuration: trial directories}."""
    excluded = timing_excluded(sweeps)
    rows: list[str] = []
    all_finals: dict[str, dict[str, list[float]]] = {}
    seconds: dict[str, dict[str, float]] = {}
    runs_of: dict[str, list[Path]] = {}
    for task in tasks:
        for name, d in env_sweeps(f"dmc-{task}", sweeps).items():
            trials = finished_trials(d, excluded)
            if not trials or trials[0]["frames"] != frames:
                continue
            runs_of.setdefault(name, []).extend(d / r["trial"] for r in trials)
            finals = [r["final_eval_mean"] for r in trials]
            timed = [r["wall_s"] for r in trials if r["timed"] and r["wall_s"]]
            all_finals.setdefault(name, {})[task] = finals
            if timed:
                seconds.setdefault(name, {})[task] = float(np.median(timed))
            sd = float(np.std(finals, ddof=1)) if len(finals) > 1 else 0.0
            others = " | ".join(f"{published[m][task][0]:.0f}" if task in published[m] else "-" for m in shown)
            rows.append(f"| {task} | {name} | {len(finals)} | {np.mean(finals):.0f} ± {sd:.0f} | "
                        f"{', '.join(f'{v:.0f}' for v in finals)} | "
                        f"{f'{np.median(timed):.0f}' if timed else '-'} | {others} |")
    return rows, all_finals, seconds, runs_of


def dmc_table(rows: list[str], shown: list[str], runs_of: dict[str, list[Path]]) -> list[str]:
    return [f"| task | configuration | seeds | final return (mean ± sd) | each seed | one-core s | "
            f"{' | '.join(f'published {m}' for m in shown)} |",
            "|" + "---|" * (6 + len(shown)), *rows, "",
            "Machines (from the trials' config.yaml; one-core seconds compare only on one machine): "
            + "; ".join(f"{name}: {machines_of(runs)}" for name, runs in runs_of.items()) + ".", ""]


def dmc_section(sweeps: Path, kept: dict[str, list[str]], figures: Path) -> list[str]:
    """Per DMC task, each configuration's final return at 100k frames beside the published means (DMC_SHOWN, from
    benchmarks/published-dmc-100k.yaml), and the aggregate; then the tasks continued to 500k frames."""
    import yaml

    published = {name: envs for name, envs in yaml.safe_load(PUBLISHED_DMC.read_text())["methods"].items()}
    shown = [m for m in DMC_SHOWN if m in published]
    rows, all_finals, seconds, runs_of = dmc_rows(sweeps, DMC_TASKS, 100_000, published, shown)
    own_finals, own_seconds, used = own_preset_runs(sweeps, all_finals, seconds)
    if len(used) > 1:  # first in the aggregate: what `--env dmc:TASK` trains on each task (one configuration: its row)
        all_finals, seconds = {OWN_PRESETS: own_finals, **all_finals}, {OWN_PRESETS: own_seconds, **seconds}
    longer = dmc_500k_section(sweeps)
    if not rows and not longer:
        return kept.get(DMC, [])
    table = ([*dmc_table(rows, shown, runs_of), *dmc_aggregate(all_finals, seconds, figures / "dmc-aggregate.png")]
             if rows else ["No run of 100k frames here.", ""])
    return [f"## {DMC}", "",
            "The DeepMind Control Suite through the `[dmc]` extra (`--env dmc:TASK`), action repeat 2, 100k frames "
            "(50k agent steps), final deterministic evaluation (10 episodes of 1000 frames), one pinned CPU per "
            "trial. Published: the mean at 100k frames of SonyResearch/simba's result files (SAC, SimBa, BRO; 10 "
            "seeds) and dojeon-ai/SimbaV2's (SimBaV2, TD-MPC2; benchmarks/published-dmc-100k.yaml has their "
            "commits, standard deviations and SimbaV2's own SAC and BRO baselines), run on GPUs.", "",
            *table, *longer]


OWN_PRESETS = "softac, each task's preset (dmc-TASK where there is one, else dmc)"


def own_preset_runs(sweeps: Path, finals: dict[str, dict[str, list[float]]],
                    seconds: dict[str, dict[str, float]]) -> tuple[dict[str, list[float]], dict[str, float], set[str]]:
    """Per task, the finals (and median seconds) of the first configuration in `finals` whose sweep trained what
    `softac train --env dmc:TASK` trains with today's presets (the task's own dmc-TASK preset where there is one,
    else dmc), read from its trials' config.yaml (trained_as_today): the DMC presets' own score; and the
    configurations it drew on."""
    own_finals: dict[str, list[float]] = {}
    own_seconds: dict[str, float] = {}
    used: set[str] = set()
    for task in DMC_TASKS:
        for name, d in env_sweeps(f"dmc-{task}", sweeps).items():
            spec = load_spec(d)
            if (task in finals.get(name, {}) and spec.framework == "softac" and not spec.grid and not spec.search
                    and trained_as_today(d, spec.env_id)):
                own_finals[task] = finals[name][task]
                used.add(name)
                if task in seconds.get(name, {}):
                    own_seconds[task] = seconds[name][task]
                break
    return own_finals, own_seconds, used


def trained_as_today(sweep: Path, env_id: str) -> bool:
    """Whether every finished trial of `sweep` trained with what SACConfig.for_env(env_id) holds today, seed and
    budget aside (the frames filter is the caller's), as its config.yaml records it (`departures`)."""
    import yaml

    from softac.config.sac_config import SACConfig

    today = SACConfig.for_env(env_id)
    trials = [t for t in sorted(sweep.glob("*/config.yaml")) if (t.parent / "summary.json").exists()]
    return bool(trials) and not any(departures(yaml.safe_load(t.read_text()) or {}, today) for t in trials)


def dmc_500k_section(sweeps: Path) -> list[str]:
    """The tasks continued to 500k frames beside the published means at 500k (benchmarks/published-dmc-500k.yaml)."""
    import yaml

    published = yaml.safe_load(PUBLISHED_DMC_500K.read_text())["methods"]
    shown = [m for m in DMC_SHOWN if m in published]
    tasks = [t for t in DMC_TASKS if any(t in envs for envs in published.values())]
    rows, _, _, runs_of = dmc_rows(sweeps, tasks, 500_000, published, shown)
    if not rows:
        return []
    return [f"### {DMC_500K}", "",
            "The same protocol continued to 500k frames (250k agent steps; evaluations every 20k frames), beside the "
            "published means at 500k frames of the same result files (benchmarks/published-dmc-500k.yaml).", "",
            *dmc_table(rows, shown, runs_of)]
