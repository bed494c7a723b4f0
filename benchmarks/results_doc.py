"""Write docs/results.md and docs/results/*.png from the sweeps made by benchmarks/results.sh.

    python benchmarks/results_doc.py sweeps        # SWEEPS directory of results.sh

Each env has a sweep directory per configuration: ENV-softac (softac's preset), ENV-softac-NAME (another preset or
options), ENV-PEER (a peer of softac.peers.PEERS: ENV-sbx, ENV-sb3, ENV-sbx-crossq, ENV-sbx-crossq-softac); the
threshold of each is the one given to its sweep command (kept in results.sh). Tables and figures come from the
trial run directories alone, and name each configuration by its preset and framework. The MuJoCo suite also gets
one aggregate over its five envs: the interquartile mean of normalised final scores with stratified-bootstrap 95%
intervals (rliable's). An env none of whose sweeps is in SWEEPS keeps its section of the current
docs/results.md (the aggregate too), so the classic and the MuJoCo sets can be regenerated apart.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from softac.cpus import machine_description
from softac.peers import PEERS
from softac.plots import plot_aggregate, plot_comparison, plot_front
from softac.stats import stratified_bootstrap_iqm
from softac.sweep import aggregate, load_spec, markdown_table, trial_dirs, trial_rows, value_text

# env -> the threshold its sweeps were given (None: no threshold columns)
ENVS: dict[str, float | None] = {"InvertedPendulum-v5": 1000.0, "InvertedPendulum-v4": 1000.0, "Pusher-v5": -40.0,
                                 "Pendulum-v1": -200.0, "MountainCarContinuous-v0": 90.0,
                                 "LunarLanderContinuous-v3": 200.0, "BipedalWalker-v3": 300.0,
                                 "HalfCheetah-v5": None, "Hopper-v5": None, "Walker2d-v5": None, "Ant-v5": None,
                                 "Humanoid-v5": None, "Swimmer-v5": None, "Reacher-v5": None,
                                 "InvertedDoublePendulum-v5": None, "FetchReach-v4": None, "FetchPush-v4": None,
                                 "PointMaze_UMaze-v3": None, "HalfCheetah-v4": None, "Hopper-v4": None,
                                 "Walker2d-v4": None, "Ant-v4": None, "Humanoid-v4": None}
SUITE = ["HalfCheetah-v5", "Hopper-v5", "Walker2d-v5", "Ant-v5", "Humanoid-v5"]
# the published tables' version of the suite (issue 42): the front of return against one-core wall time
SUITE_V4 = [env.replace("-v5", "-v4") for env in SUITE]
FRONT = "MuJoCo v4 at 100k steps: return against one-core wall time"
AGAINST_BEST = "Against the best published result per env"
PUBLISHED = Path(__file__).resolve().parent / "published-100k.yaml"
AGGREGATE = "MuJoCo suite: one aggregate"
# issue 43: the DeepMind Control Suite at 100k frames (action repeat 2: 50k agent steps), beside the published means
DMC = "DeepMind Control Suite at 100k frames"
DMC_TASKS = ["cheetah-run", "walker-walk", "walker-run", "hopper-hop", "finger-spin", "quadruped-run", "reacher-hard",
             "cartpole-swingup"]
PUBLISHED_DMC = Path(__file__).resolve().parent / "published-dmc-100k.yaml"
PUBLISHED_DMC_RUNS = PUBLISHED_DMC.with_name("published-dmc-100k-runs.yaml")  # per seed, for the aggregate
DMC_500K = "Continued to 500k frames"  # a subsection of DMC's
PUBLISHED_DMC_500K = PUBLISHED_DMC.with_name("published-dmc-500k.yaml")
# issue 43's columns: SAC, SimBa and BRO from the SimBa paper's files (10 seeds), SimBaV2 and TD-MPC2 from SimbaV2's
DMC_SHOWN = ["SAC (SimBa paper)", "SimBa", "SimBaV2 UTD 2", "BRO (SimBa paper)", "TD-MPC2"]
OURS = "softac, crossq preset"  # the suite's env presets (extends: crossq); the aggregate's reference for wall time
# ENV-softac-NAME: another preset or options on the env (benchmarks/results.sh's `options` and `fallback`, #18)

INTRO = """# Results: softac beside SBX and Stable-Baselines3 on the same machine

Made with `softac sweep` (Ray Tune, one trial per CPU, two trials at a time, each trial's process pinned
to its CPU); each env's section names the machine its sweeps ran on (this page was last written on
{machine}). Every framework is evaluated the same way: every `eval_interval` steps, 10 episodes with
deterministic actions, episode i seeded `seed + 1000000 + i`.

- Classic set (InvertedPendulum-v5/v4, Pusher-v5): softac's env presets on 5 seeds, Stable-Baselines3's
  SAC at its defaults on 3 seeds (`softac sweep --framework sb3`), the same step budget. Issue 43's classic
  set (Pendulum-v1, MountainCarContinuous-v0, LunarLanderContinuous-v3, BipedalWalker-v3): softac's env
  presets on seeds 0-4 (their settings were chosen on seeds 100 and up) beside Stable-Baselines3's SAC at RL
  Zoo's tuned settings for each env (`--framework sb3-zoo`, 3 seeds), RL Zoo's step budget; "reached R" is
  the solved return (-200, 90, 200, 300).
- MuJoCo suite (HalfCheetah, Hopper, Walker2d, Ant, Humanoid, all v5): 100k env steps. "softac, crossq
  preset" is softac's env preset (each extends `crossq` and changes nothing else), on 5 seeds; beside it,
  like for like, "SBX CrossQ, crossq preset's settings" (`softac sweep --framework sbx-crossq-softac`: SBX's
  CrossQ at the same settings, 2 seeds); "SBX CrossQ, its defaults" (`--framework sbx-crossq`: 1024-wide
  critics, batch 256; hours a run on one CPU, so only where finished); "SBX SAC, its defaults" (2 seeds).
  softac multiplies in bf16 where the CPU has it (`matmul_dtype: auto`), SBX in float32. Stable-Baselines3
  trains ~3x slower than SBX and is left out of this budget. The aggregate section puts the five envs
  together.
- Goal envs (FetchReach-v4, FetchPush-v4, PointMaze_UMaze-v3; the `[robotics]` extra): softac's env presets
  (SAC with hindsight experience replay) beside Stable-Baselines3's and SBX's SAC with SB3's HerReplayBuffer at
  their defaults (`--framework sb3-her`, `sbx-her`: future, 4 goals, learning_starts 1000), 20 deterministic
  episodes an evaluation; their tables add the final success rate and the steps until it first reached 0.9, and a second
  figure draws the success rates.
- Other rows, on the same seeds and budget: "softac, NAME preset" is another preset on the env (`results.sh
  options`: plain SAC, `sac-100k`, beside the CrossQ presets; `results.sh fallback`: `default` and
  `crossq` on envs with no preset of their own); "... + KEY=VALUE" adds options to it.
- Wall times are comparable between trials run at the same time on the same machine (its speed drifts by
  up to 2x between days): each trial's `config.yaml` records when it started (`segments`), and the notes
  below say which trials ran side by side.

Columns:
- final eval: the last evaluation of each trial (mean ± std over seeds, and the 95% Student-t interval);
  final IQM: its interquartile mean over seeds (rliable's; the plain mean below 4 seeds);
- best eval: the best evaluation of each trial;
- median wall s: the whole trial's training time, evaluations included, over the trials whose wall time is
  comparable (those in benchmarks/sweeps/timing-excluded.yaml, listed under the aggregate, are left out of
  it; their returns count); steps/s: steps over that time;
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
    """The `## ENV` sections (and the aggregate's) of an existing results.md, by heading."""
    if not results_md.exists():
        return {}
    sections: dict[str, list[str]] = {}
    current: str | None = None
    for line in results_md.read_text().splitlines():
        if line.startswith("## "):
            heading = line[3:].strip()
            current = heading if heading in ENVS or heading in (AGGREGATE, FRONT, DMC) else None
            if current:
                sections[current] = []
        if current:
            sections[current].append(line)
    return sections


def env_sweeps(env: str, sweeps: Path) -> dict[str, Path]:
    """The env's sweep directories by configuration name: softac's preset, its variants, then the peers. Two
    sweeps of one configuration (e.g. the same settings rerun on another machine beside a peer) are both kept,
    the later named by its directory too."""
    found = {d.name[len(env) + 1:]: d for d in sweeps.glob(f"{env}-*") if (d / "sweep.json").exists()}
    order = ["softac", *sorted(n for n in found if n.startswith("softac-")), *PEERS]
    named: dict[str, Path] = {}
    for suffix in (s for s in order if s in found):
        name = load_spec(found[suffix]).describe()
        named[f"{name} ({found[suffix].name})" if name in named else name] = found[suffix]
    return named


def section(env: str, threshold: float | None, sweeps: Path, figures: Path,
            kept: dict[str, list[str]]) -> list[str]:
    present = env_sweeps(env, sweeps)
    if not present:
        return kept.get(env) or [f"## {env}", "", "Not run yet.", ""]
    rows, names, steps = [], {}, set()
    excluded = timing_excluded(sweeps)
    for name, d in present.items():
        spec = load_spec(d)
        steps.add(spec.steps)
        trials = trial_rows(d, spec, threshold)
        [entry] = aggregate(trials, [], threshold, name=name)
        timed = [r for r in trials if f"{d.name}/{r['trial']}" not in excluded and r["wall_s"]]
        if timed and len(timed) < len(trials):  # wall time from the trials whose wall time is comparable
            entry["wall_s"] = float(np.median([r["wall_s"] for r in timed]))
            entry["steps_per_s"] = float(np.median([r["steps"] / r["wall_s"] for r in timed]))
        elif not timed:  # none comparable: no figure (timing-excluded.yaml, listed under the aggregate, says why)
            entry["wall_s"] = entry["steps_per_s"] = None
        rows.append(entry)
        names.update({run: name for run in trial_dirs(d)})
    figure = figures / f"{env}.png"
    plot_comparison(list(names), figure, names=names)
    budget = ", ".join(f"{s:,}" for s in sorted(steps))
    figures_md = f"![{env}](results/{figure.name})"
    if any("final_success" in row for row in rows):  # a goal env: its success-rate curves too
        success = figures / f"{env}-success.png"
        plot_comparison(list(names), success, names=names, column="success_rate")
        figures_md += f" ![{env} success rate](results/{success.name})"
    return [f"## {env}", "", f"{budget} env steps per trial, on {machines_of(list(names))}. {figures_md}", "",
            markdown_table(rows, threshold), ""]


# trials whose wall time is not comparable (their returns are): sweep/trial -> why, kept beside the sweeps
TIMING_EXCLUDED = "timing-excluded.yaml"


def timing_excluded(sweeps: Path) -> dict[str, str]:
    import yaml

    path = sweeps / TIMING_EXCLUDED
    return (yaml.safe_load(path.read_text()) or {}) if path.exists() else {}


def finished_trials(d: Path, excluded: dict[str, str] | None = None) -> list[dict]:
    """The sweep's finished trials' rows, each with the day it started (None for runs from before
    config.yaml recorded it), the env frames it ran (agent steps times action repeat) and `timed`: False for a
    trial in `excluded` (sweep/trial -> why) or one that config.yaml says shared its CPUs with another pinned
    process."""
    import yaml

    spec = load_spec(d)
    rows = [r for r in trial_rows(d, spec) if r["status"] == "done" and r["final_eval_mean"] is not None]
    for row in rows:
        config = yaml.safe_load((d / row["trial"] / "config.yaml").read_text()) or {}
        segments = config.get("segments") or [{}]
        row["day"] = str(segments[0].get("started") or "")[:10] or None
        row["frames"] = int(config.get("total_steps", 0)) * int(config.get("action_repeat") or 1)  # env frames
        # a trial pinned to CPUs another pinned softac process held (softac.cpus.cpus_shared) ran disturbed too
        row["timed"] = (f"{d.name}/{row['trial']}" not in (excluded or {})
                        and not any(s.get("cpus_shared") for s in segments))
    return rows


def wall_ratio(theirs: list[dict], ours: list[dict]) -> tuple[float, float, float, bool] | None:
    """Median wall time of `theirs` over that of `ours`, from the trials of `ours` that ran on the days
    `theirs` ran (side by side: the machine's speed drifts by up to 2x between days) when there are any;
    returns (ratio, their median, our median, side by side), or None without timed trials on either side.
    Trials with `timed` False are left out."""
    theirs, ours = [r for r in theirs if r.get("timed", True)], [r for r in ours if r.get("timed", True)]
    days = {r["day"] for r in theirs}  # None: before config.yaml recorded it (those sweeps ran side by side too)
    beside = [r for r in ours if r["day"] in days]
    used = beside or ours
    if not theirs or not used:
        return None
    theirs_s, ours_s = float(np.median([r["wall_s"] for r in theirs])), float(np.median([r["wall_s"] for r in used]))
    return theirs_s / ours_s, theirs_s, ours_s, bool(beside)


# the random policy's returns the normalisation uses, kept beside the sweeps: they depend on the MuJoCo release
# (HalfCheetah's moved from -303.1 to -290.2 between MuJoCo 4.0.0 and 3.11.0), which should not move the aggregate
RANDOM_RETURNS = "random-returns.yaml"


def random_returns(envs: list[str], sweeps: Path | None = None) -> dict[str, float]:
    """The uniform random policy's mean return over the 10 evaluation episodes (seed 0's), per env: from
    SWEEPS/random-returns.yaml where it is there, else measured now with the installed MuJoCo and added to it."""
    import yaml

    from softac.baselines import run_baselines

    path = sweeps / RANDOM_RETURNS if sweeps is not None else None
    kept = (yaml.safe_load(path.read_text()) or {}) if path is not None and path.exists() else {}
    returns = {env: float(kept[env]["random"]) for env in envs if env in kept}
    missing = [env for env in envs if env not in returns]
    if missing:
        import mujoco

        for env in missing:
            returns[env] = run_baselines(env, episodes=10, seed=0)["baselines"]["random"]["mean_return"]
            kept[env] = {"random": returns[env], "mujoco": mujoco.__version__}
        if path is not None:
            path.write_text(yaml.safe_dump(kept, sort_keys=True))
    return returns


def suite_aggregate(sweeps: Path, figures: Path, kept: dict[str, list[str]],
                    random: dict[str, float] | None = None) -> list[str]:
    """One IQM per configuration over the suite's envs (final evaluations, normalised per env between the
    random policy and the best final evaluation of any trial shown on that env), with its stratified-bootstrap
    95% interval, as a table and a figure; and the wall time of each configuration relative to softac's preset."""
    finals: dict[str, dict[str, list[dict]]] = {}
    excluded = timing_excluded(sweeps)
    for env in SUITE:
        for name, d in env_sweeps(env, sweeps).items():
            rows = finished_trials(d, excluded)
            if rows:
                finals.setdefault(name, {})[env] = rows
    if not finals:
        return kept.get(AGGREGATE, [])
    random = random if random is not None else random_returns(SUITE, sweeps)
    best = {env: max(r["final_eval_mean"] for envs in finals.values() for r in envs.get(env, [])) for env in SUITE
            if any(env in envs for envs in finals.values())}
    ours = OURS if OURS in finals else next((name for name in finals if name.startswith("softac")), None)
    lines = [f"## {AGGREGATE}", "",
             "The interquartile mean (IQM) of normalised final scores over every trial of every env, with a "
             "stratified-bootstrap 95% interval (runs resampled within each env, 20,000 resamples: rliable's "
             "method, Agarwal et al. 2021). Normalised score = (final eval - random policy's return) / (best final "
             "eval of any trial shown on the env - random policy's return): 0 is the random policy, 1 the best "
             "run seen here. Wall time: each env's median trial time over softac's preset's (from the trials that ran "
             "on the same days: the machine's speed drifts by up to 2x between days; trials from before config.yaml "
             "recorded the day count as one day), then the geometric mean over the envs (and "
             "the range). A configuration with trials on only some envs is aggregated over those "
             "(its envs column says which) beside softac's preset over the same envs.", "",
             "| env | random policy | best final eval | by |", "|---|---|---|---|"]
    for env in best:
        who = max(((name, r["final_eval_mean"]) for name, envs in finals.items() for r in envs.get(env, [])),
                  key=lambda pair: pair[1])[0]
        lines.append(f"| {env} | {random[env]:.1f} | {best[env]:.1f} | {who} |")
    lines += ["", "| configuration | envs | trials | IQM of normalised score [95% CI] | wall time / softac's "
              "(geometric mean, range) |", "|---|---|---|---|---|"]
    scores: dict[str, tuple[float, float, float]] = {}
    beside: list[tuple[str, str, tuple[float, float, float, bool]]] = []
    for name, envs in finals.items():
        partial = set(envs) != set(best) and ours is not None and all(e in finals[ours] for e in envs)
        groups = [name, ours] if partial else [name]  # a partial one beside softac's preset on its envs
        for who in groups:
            used = [env for env in best if env in envs]
            label = who if set(used) == set(best) else f"{who} ({', '.join(e.split('-')[0] for e in used)})"
            if label in scores:
                continue
            normalised = [[(r["final_eval_mean"] - random[e]) / (best[e] - random[e]) for r in finals[who][e]]
                          for e in used]
            scores[label] = stratified_bootstrap_iqm(normalised)
            pairs = {e: wall_ratio(finals[who][e], finals[ours][e]) for e in used if ours in finals and e in finals[ours]}
            pairs = {e: pair for e, pair in pairs.items() if pair is not None}
            ratios = [pair[0] for pair in pairs.values()]
            wall = (f"{np.exp(np.mean(np.log(ratios))):.2f} ({min(ratios):.2f}-{max(ratios):.2f})"
                    + ("" if all(pair[3] for pair in pairs.values()) else " (not side by side)")
                    if ratios else "-")
            if who != ours:
                beside.extend((who, e, pair) for e, pair in pairs.items() if pair[3])
            point, low, high = scores[label]
            lines.append(f"| {label} | {len(used)} | {sum(len(finals[who][e]) for e in used)} | "
                         f"{point:.2f} [{low:.2f}, {high:.2f}] | {wall} |")
    if beside:
        lines += ["", f"Side by side: each peer's trials and {ours}'s trials that ran on the same days (one pinned "
                  "CPU each, two trials at a time), median wall seconds per 100k-step trial, evaluations included:",
                  "", "| env | configuration | its median s | softac's median s | ratio |", "|---|---|---|---|---|"]
        lines += [f"| {env} | {who} | {pair[1]:.0f} | {pair[2]:.0f} | {pair[0]:.2f} |" for who, env, pair in beside]
    if excluded:
        lines += ["", f"Wall times left out of these ratios (their returns count; benchmarks/sweeps/{TIMING_EXCLUDED}):", ""]
        lines += [f"- {trial}: {why}" for trial, why in sorted(excluded.items())]
    figure = figures / "suite-aggregate.png"
    plot_aggregate(scores, figure, "MuJoCo suite, 100k steps: IQM of normalised final scores",
                   "normalised score (0: random policy, 1: best run seen here)\nerror bar: 95% stratified-bootstrap interval")
    return lines + ["", f"![aggregate](results/{figure.name})", ""]


def published_means(path: Path = PUBLISHED) -> dict[str, dict[str, tuple[float, float, int]]]:
    """{method: {env: (mean, sd, seeds)}} of the published 100k-step returns (benchmarks/published-100k.yaml)."""
    import yaml

    methods = yaml.safe_load(path.read_text())["methods"]
    return {name: {env: tuple(v) for env, v in envs.items() if env.endswith("-v4")} for name, envs in methods.items()}


def front(sweeps: Path, figures: Path, kept: dict[str, list[str]]) -> list[str]:
    """Per v4 env, every configuration's final return (mean and spread over seeds) against its median one-core wall
    time (trials whose wall time is comparable), beside the published 100k-step means: the front users choose
    from (issue 42). A table per env and one figure."""
    excluded = timing_excluded(sweeps)
    published = published_means()
    points: dict[str, dict[str, tuple[float, float, float | None]]] = {}
    scores: dict[str, dict[str, tuple[float, float | None]]] = {}  # configuration -> env -> (mean final, seconds)
    lines = [f"## {FRONT}", "",
             "Gym MuJoCo v4 (the published tables' version), 100k env steps, final deterministic evaluation (10 "
             "episodes), one pinned CPU per trial. Each configuration is a point: the mean final return over its "
             "seeds (± their standard deviation) against its median wall seconds per run on one CPU, from the "
             "trials whose wall time is comparable (benchmarks/sweeps/timing-excluded.yaml lists the others; their "
             "returns count); a configuration with none comparable shows its disturbed trials' median, an upper "
             "estimate, in parentheses (hollow in the figure). One-core seconds compare only between rows of one machine "
             "(the machine column, from the trials' config.yaml; the figure's legend names it too): the AMD EPYC's "
             "update runs about 2x as fast as the Xeon's (docs/results-notes.md). "
             "Published: the mean (± sd, seeds) at 100k steps of the result files of "
             "dojeon-ai/SimbaV2 (benchmarks/published-100k.yaml), run on GPUs; best published per env in bold.", ""]
    for env in SUITE_V4:
        present = env_sweeps(env, sweeps)
        rows = []
        for name, d in present.items():
            trials = finished_trials(d, excluded)
            if not trials:
                continue
            finals = [r["final_eval_mean"] for r in trials]
            timed = [r["wall_s"] for r in trials if r["timed"] and r["wall_s"]]
            disturbed = [r["wall_s"] for r in trials if r["wall_s"]]
            # none timed: the disturbed trials' median, an upper estimate, drawn hollow and said so in the table
            seconds = float(np.median(timed or disturbed)) if timed or disturbed else None
            sd = float(np.std(finals, ddof=1)) if len(finals) > 1 else 0.0
            machine = short_machines(machines_of([d / r["trial"] for r in trials]))
            points.setdefault(env, {})[f"{name} [{machine}]"] = (float(np.mean(finals)), sd, seconds, bool(timed))
            scores.setdefault(name, {})[env] = (float(np.mean(finals)), seconds)
            shown_seconds = "-" if seconds is None else f"{seconds:.0f}" if timed else f"({seconds:.0f}: disturbed)"
            rows.append(f"| {name} | {len(finals)} | {np.mean(finals):.0f} ± {sd:.0f} | "
                        f"{', '.join(f'{v:.0f}' for v in finals)} | {shown_seconds} | {machine} |")
        if not rows:
            continue
        best = max(published, key=lambda m: published[m].get(env, (-np.inf,))[0])
        lines += [f"### {env}", "",
                  "| configuration | seeds | final return (mean ± sd) | each seed | one-core s | machine |",
                  "|---|---|---|---|---|---|", *rows, "", "| published | mean ± sd (seeds) |", "|---|---|"]
        for method, envs in published.items():
            if env in envs:
                mean, sd, n = envs[env]
                text = f"{mean:.0f} ± {sd:.0f} ({n})"
                lines.append(f"| {method} | {f'**{text}**' if method == best else text} |")
        lines.append("")
    if not points:
        return kept.get(FRONT, [])
    lines += against_best_published(scores, published)
    shown = ("CrossQ", "SAC", "SimBa UTD 2", "SimBaV2 UTD 2")
    figure = plot_front(points, {env: {m: published[m][env][0] for m in shown if env in published[m]} for env in points},
                        figures / "front-v4.png", "Gym MuJoCo v4, 100k steps: final return against one-core wall time")
    return lines + [f"![front](results/{figure.name})", ""]


def against_best_published(scores: dict[str, dict[str, tuple[float, float | None]]],
                           published: dict[str, dict[str, tuple[float, float, int]]]) -> list[str]:
    """Issue 42's goal for each configuration run on all five v4 envs: its mean final return over the best
    published 100k-step mean per env, the average of those fractions, the envs where it is at or above published
    CrossQ, and what its five runs cost (the sum of the envs' median one-core seconds)."""
    best = {env: max(m[env][0] for m in published.values() if env in m) for env in SUITE_V4}
    full = {name: envs for name, envs in scores.items() if all(env in envs for env in SUITE_V4)}
    if not full:
        return []
    lines = [f"### {AGAINST_BEST}", "",
             "Each configuration run on all five envs: its mean final return over the best published mean per env ("
             + ", ".join(f"{env.split('-')[0]} {best[env]:.0f}" for env in SUITE_V4) + "), the mean of those "
             "fractions (issue 42's goal: >= 0.85, and at or above published CrossQ on all five), and the sum over "
             "the five envs of the median one-core seconds of a run (machines as in the tables above).", "",
             "| configuration | " + " | ".join(env.split("-")[0] for env in SUITE_V4)
             + " | mean fraction | envs >= published CrossQ | one-core s, five envs |",
             "|---|" + "---|" * (len(SUITE_V4) + 3)]
    for name, envs in full.items():
        fractions = [envs[env][0] / best[env] for env in SUITE_V4]
        at_crossq = sum(envs[env][0] >= published["CrossQ"][env][0] for env in SUITE_V4)
        seconds = [envs[env][1] for env in SUITE_V4]
        cost = f"{sum(seconds):.0f}" if all(s is not None for s in seconds) else "-"
        lines.append(f"| {name} | " + " | ".join(f"{f:.2f}" for f in fractions)
                     + f" | {np.mean(fractions):.2f} | {at_crossq} of {len(SUITE_V4)} | {cost} |")
    return [*lines, ""]


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


def departures(record: dict, today: Any) -> dict[str, Any]:
    """The settings a trial's config.yaml (`record`) holds that differ from the SACConfig `today`, seed and budget
    aside: {key: the value the trial ran with}. The record, not the sweep's preset name: a preset's file can change
    after its runs. A key the record lacks predates it, so the trial ran at that key's default (what the code did
    then), save pixel_range: pixels were at [-0.5, 0.5] before it (`centered`, as softac.snapshot reads old
    checkpoints)."""
    import dataclasses

    from softac.config import SACConfig

    names = {f.name for f in dataclasses.fields(SACConfig)}
    before = {"pixel_range": "centered"} if record.get("pixels") else {}
    ran = SACConfig().replace(**{**before, **{k: v for k, v in record.items() if k in names}})
    expected = today.replace(seed=ran.seed, total_steps=ran.total_steps)
    return {f: getattr(ran, f) for f in sorted(names) if getattr(ran, f) != getattr(expected, f)}


def trained_as_today(sweep: Path, env_id: str) -> bool:
    """Whether every finished trial of `sweep` trained with what SACConfig.for_env(env_id) holds today, seed and
    budget aside (the frames filter is the caller's), as its config.yaml records it (`departures`)."""
    import yaml

    from softac.config import SACConfig

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


AVERAGING = "Weight averaging: the two policies of one training"
ACTOR_EVAL = "actor-eval.json"  # `softac eval TRIAL --checkpoint last --policy actor --json` (benchmarks/keep_trials.sh)


def averaging_pairs(sweeps: Path) -> list[str]:
    """Each sweep whose trials trained with policy_average_tau and carry their actor's evaluation of the last
    checkpoint (ACTOR_EVAL): per seed, the actor's final return beside the average's (the deployed policy, whose
    final evaluation is the trial's), so each pair is one training's two policies, evaluated on the same episodes."""
    rows = []
    for d in sorted(p for p in sweeps.iterdir() if (p / "sweep.json").exists()):
        pairs = [(json.loads((d / t["trial"] / ACTOR_EVAL).read_text())["mean_return"], t["final_eval_mean"])
                 for t in finished_trials(d) if (d / t["trial"] / ACTOR_EVAL).exists()]
        if not pairs:
            continue
        actor, average = np.array(pairs).T
        scale = np.maximum(np.abs(actor), 1e-9)
        higher, lower = int(np.sum(average > actor + 0.02 * scale)), int(np.sum(average < actor - 0.02 * scale))
        spec = load_spec(d)
        rows.append(f"| {spec.env_id} | {d.name} | {len(pairs)} | "
                    f"{', '.join(f'{a:.0f}' for a in actor)} ({actor.mean():.0f}) | "
                    f"{', '.join(f'{a:.0f}' for a in average)} ({average.mean():.0f}) | "
                    f"{higher} / {len(pairs) - higher - lower} / {lower} |")
    if not rows:
        return []
    return [f"## {AVERAGING}", "",
            "With `policy_average_tau` a run trains as it would without it (exploration acts with the actor) and "
            "deploys a weight average of the actor. Each trial's last checkpoint holds both: the average's final "
            "evaluation is the trial's; the actor's is `softac eval TRIAL --checkpoint last --policy actor` on the "
            "same 10 episodes (the same seeds). So each pair is what averaging changed on one training, free of "
            "seed luck.", "",
            "| env | sweep | seeds | actor's final return, each seed (mean) | average's (mean) | "
            "average higher by > 2% / within 2% / lower |",
            "|---|---|---|---|---|---|", *rows, ""]


PIXELS = "From pixels"
PIXEL_SWEEPS = "pixels"  # SWEEPS/pixels/: softac's pixel sweeps and SB3's CnnPolicy runs (benchmarks/sb3_pixels.py),
# apart from the env sections above, whose tables are of state observations
PUBLISHED_PIXELS = {"dmc:cartpole-swingup": "published DrQ (Kostrikov et al. 2021, PlaNet benchmark: 84x84 frames, "
                                            "action repeat 8, batch 512, GPU) at 100k frames: 759 ± 92; state SAC "
                                            "812"}


def pixel_runs(d: Path) -> tuple[str, str, list[dict], str] | None:
    """(env id, configuration, one dict per seed: final return, steps, wall seconds, and the step and seconds
    of its first evaluation at ENVS's threshold; the machines they ran on) of a softac pixel sweep or a directory
    of SB3 CnnPolicy runs (seed=S/summary.json and eval.csv from benchmarks/sb3_pixels.py); None for anything
    else."""
    import yaml

    if (d / "sweep.json").exists():
        spec = load_spec(d)
        threshold = ENVS.get(spec.env_id)
        rows = [r for r in trial_rows(d, spec, threshold) if r["status"] == "done"]
        seeds, then, today = [], {}, spec.base_config()
        for row in rows:
            config = yaml.safe_load((d / row["trial"] / "config.yaml").read_text()) or {}
            then.update(departures(config, today))
            seeds.append({"final": row["final_eval_mean"], "steps": row["steps"], "wall_s": row["wall_s"],
                          "at_threshold": (row.get("steps_to_threshold"), row.get("seconds_to_threshold")),
                          "frames": (f"{config['pixel_size']}x{config['pixel_size']}, {config['frame_stack']} "
                                     f"stacked, action repeat {config.get('action_repeat', 1)}, batch "
                                     f"{config['batch_size']}")})
        # a sweep run before its preset changed names what it ran with (pixel_range=centered: [-0.5, 0.5])
        ran_with = " ".join(f"{k}={value_text(v).strip(chr(34))}" for k, v in then.items())
        name = spec.describe() + (f", as run then: {ran_with}" if then else "")
        return spec.env_id, name, seeds, machines_of([d / r["trial"] for r in rows])
    summaries = sorted(d.glob("seed=*/summary.json"))
    if not summaries:
        return None
    seeds, env_id, machines = [], "", set()
    for path in summaries:
        summary = json.loads(path.read_text())
        env_id, threshold = summary["env"], ENVS.get(summary["env"])
        with open(path.parent / "eval.csv") as f:
            evals = [(int(r["step"]), float(r["return_mean"]), float(r["wall_s"])) for r in csv.DictReader(f)]
        crossing = next(((step, wall) for step, value, wall in evals if threshold is not None and value >= threshold),
                        (None, None))
        seeds.append({"final": summary["final_return"], "steps": summary.get("final_step", summary["steps"]),
                      "wall_s": summary["wall_s"],
                      "at_threshold": crossing,
                      "frames": (f"{summary['pixel_size']}x{summary['pixel_size']}, {summary['frames']} stacked, "
                                 f"action repeat {summary['action_repeat']}, batch {summary.get('batch_size', 256)}")})
        machines.add(summary.get("machine") or "a machine its summary.json does not name")
    return env_id, "SB3 SAC CnnPolicy (SB3's defaults, benchmarks/sb3_pixels.py)", seeds, " and ".join(sorted(machines))


def pixels_section(sweeps: Path) -> list[str]:
    """softac's pixel sweeps beside SB3's CnnPolicy (SWEEPS/pixels/), each seed's final return, its first
    evaluation at the env's threshold and its wall time on one core, and the published pixel figures."""
    root = sweeps / PIXEL_SWEEPS
    found = [runs for d in sorted(root.iterdir()) if d.is_dir() and (runs := pixel_runs(d))] if root.exists() else []
    rows, envs = [], []
    for env_id, name, seeds, machines in (r for r in found if r[2]):
        if env_id not in envs:
            envs.append(env_id)
        finals = [s["final"] for s in seeds]
        crossings = [f"{step / 1000:g}k ({seconds:.0f} s)" if step is not None else "-"
                     for step, seconds in (s["at_threshold"] for s in seeds)]
        steps = ", ".join(f"{s['steps'] / 1000:g}k" for s in seeds)
        walls = ", ".join(f"{s['wall_s']:.0f}" for s in seeds)
        rows.append(f"| {env_id} | {name} | {seeds[0]['frames']} | {len(seeds)} | "
                    f"{', '.join(f'{v:.0f}' for v in finals)} ({np.mean(finals):.0f}) | {', '.join(crossings)} | "
                    f"{steps} | {walls} | {short_machines(machines)} |")
    if not rows:
        return []
    thresholds = ", ".join(f"{env} {ENVS[env]:g}" for env in envs if ENVS.get(env) is not None)
    published = [f"- {env}: {PUBLISHED_PIXELS[env]}." for env in envs if env in PUBLISHED_PIXELS]
    return [f"## {PIXELS}", "",
            "Image observations through the convolutional encoder (docs/guides/pixels.md), one pinned CPU core a run, "
            "and, where run, Stable-Baselines3's SAC with its CnnPolicy on the same frames. A run's seconds include "
            "its evaluations." + (f" First evaluation at the solved mark ({thresholds}): the step and the run's "
                                   "seconds then; the runs stop there (SB3's with benchmarks/sb3_pixels.py "
                                   "--target-return)." if thresholds
                                   else ""), "",
            "| env | configuration | frames | seeds | final return, each seed (mean) | first evaluation at the mark | "
            "steps run | wall s | machine |",
            "|---|---|---|---|---|---|---|---|---|", *rows, "", *published, *([""] if published else [])]


def short_machines(machines: str) -> str:
    """machines_of's text with each machine's CPU alone: "AMD EPYC (AVX-512 BF16)", "Intel Xeon (AMX)"."""
    return " and ".join(m.split(",")[0].replace("(R)", "").replace(" Processor", "") for m in machines.split(" and "))


def machines_of(runs: list[Path]) -> str:
    """The machines the trials' config.yaml name, every segment of a resumed trial's (runs made before config.yaml
    recorded it: said so, not guessed: this page is written on whichever machine a session has)."""
    import yaml

    names = set()
    for run in runs:
        config = (yaml.safe_load((run / "config.yaml").read_text()) if (run / "config.yaml").exists() else None) or {}
        for segment in config.get("segments") or [config]:
            names.add(segment.get("machine") or "a machine its config.yaml does not name")
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
        if env == SUITE[0]:
            text.extend(suite_aggregate(a.sweeps, figures, kept))
        if env == SUITE_V4[0]:
            text.extend(front(a.sweeps, figures, kept))
        text.extend(section(env, threshold, a.sweeps, figures, kept))
    text.extend(dmc_section(a.sweeps, kept, figures))
    text.extend(averaging_pairs(a.sweeps))
    text.extend(pixels_section(a.sweeps))
    notes = a.docs / "results-notes.md"
    if notes.exists():
        text.append(notes.read_text())
    (a.docs / "results.md").write_text("\n".join(text))
    print(json.dumps({"wrote": str(a.docs / "results.md")}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
