"""docs/results.md's per-env sections, the MuJoCo suite's aggregate, the return-against-wall-time front with the
best published results, and the weight-averaging pairs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from softac.outputs.plots import FrontPoint, plot_aggregate, plot_comparison, plot_front
from softac.outputs.seed_stats import stratified_bootstrap_iqm
from softac.sweep import aggregate, load_spec, markdown_table, trial_dirs, trial_rows

from results_common import (AGAINST_BEST, AGGREGATE, env_sweeps, finished_trials, FRONT, machines_of, OURS, PUBLISHED,
                            random_returns, short_machines, SUITE, SUITE_V4, TIMING_EXCLUDED, timing_excluded,
                            wall_ratio)


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
    points: dict[str, dict[str, FrontPoint]] = {}
    labels: dict[str, str] = {}  # configuration -> its short label in the figure
    machines: dict[str, set[str]] = {}  # configuration -> the machines its points ran on
    seeds: dict[str, dict[str, int]] = {}  # configuration -> env -> seeds run
    scores: dict[str, dict[str, tuple[float, float | None]]] = {}  # configuration -> env -> (mean final, seconds)
    lines = [f"## {FRONT}", "",
             "Gym MuJoCo v4 (the published tables' version), 100k env steps, final deterministic evaluation (10 "
             "episodes), one pinned CPU per trial. Each configuration is a point: the mean final return over its "
             "seeds (± their standard deviation) against its median wall seconds per run on one CPU, from the "
             "trials whose wall time is comparable (benchmarks/sweeps/timing-excluded.yaml lists the others; their "
             "returns count); a configuration with none comparable shows its disturbed trials' median, an upper "
             "estimate, in parentheses (hollow in the figure). One-core seconds compare only between rows of one machine "
             "(the machine column, from the trials' config.yaml; the figure tells machines apart by the markers' "
             "fill): the AMD EPYC's update runs about 2x as fast as the Xeon's at the small networks of most rows "
             "(docs/results-notes.md), as fast at FlashSAC's and XQC's (docs/performance.md); a GPU's "
             "point (a black rim) is a run's seconds on one GPU. "
             "Published: the mean (± sd, seeds) at 100k steps of the result files of "
             "dojeon-ai/SimbaV2 and Holiday-Robot/FlashSAC (benchmarks/published-100k.yaml), run on GPUs; best "
             "published per env in bold.", ""]
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
            gpu = any(r["gpu"] for r in trials)
            machine = short_machines(machines_of([d / r["trial"] for r in trials])) + (" + GPU" if gpu else "")
            label = short_label(env, d, name)
            labels[name] = min(labels.get(name, label), label, key=len)
            machines.setdefault(name, set()).add(machine)
            seeds.setdefault(name, {})[env] = len(finals)
            points.setdefault(env, {})[name] = FrontPoint(float(np.mean(finals)), sd, seconds, bool(timed), machine,
                                                          gpu)
            scores.setdefault(name, {})[env] = (float(np.mean(finals)), seconds)
            shown_seconds = "-" if seconds is None else f"{seconds:.0f}" if timed else f"({seconds:.0f}: disturbed)"
            rows.append(f"| {name} | {len(finals)} | {np.mean(finals):.0f} ± {sd:.0f} | "
                        f"{', '.join(f'{v:.0f}' for v in finals)} | {shown_seconds} | {machine} |")
        if not rows:
            continue
        best = best_published(published, env)
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
    lines += against_best_published({**scores, **per_env_choices(scores)}, published)
    labels = unique_labels(labels)
    drawn = {env: {labels[name]: point for name, point in envs.items()} for env, envs in points.items()}
    shown = {env: {*FRONT_METHODS, best_published(published, env)} for env in points}
    lines_drawn = {env: {m: published[m][env][0] for m in published if m in shown[env]} for env in points}
    figure = plot_front(drawn, lines_drawn, figures / "front-v4.png",
                        "Gym MuJoCo v4, 100k steps: final return against wall time per run")
    envs = [env for env in SUITE_V4 if env in points]
    key = ["", "The figure's key: each label, the configuration it stands for, its seeds per env (a point without "
           "an error bar is one seed: a screen, not a result) and the machines its points ran on (every panel draws "
           + ", ".join(FRONT_METHODS) + " and the best published result of its env).", "",
           f"| label | configuration | seeds ({', '.join(env.split('-')[0] for env in envs)}) | machine |",
           "|---|---|---|---|"]
    key += [f"| {labels[name]} | {name} | {', '.join(str(seeds[name].get(env, '-')) for env in envs)} | "
            f"{'; '.join(sorted(machines[name]))} |" for name in sorted(labels, key=lambda n: labels[n])]
    return lines + [f"![front](results/{figure.name})", *key, ""]


# the published methods drawn on every panel of the front (issue 66), beside each env's best
FRONT_METHODS = ("SAC", "CrossQ", "FlashSAC", "XQC", "MR.Q")


def best_published(published: dict[str, dict[str, tuple[float, float, int]]], env: str) -> str:
    """The published method with the highest mean on `env`."""
    return max((m for m in published if env in published[m]), key=lambda m: published[m][env][0])


def short_label(env: str, sweep: Path, name: str) -> str:
    """A configuration's label in the front's figure: its sweep directory's name after the env (softac's own
    without the "softac-"; softac's preset sweep by its preset's name), e.g. "crossq-avg", "tqc-2x256",
    "sbx-simba-softac"."""
    suffix = sweep.name[len(env) + 1:]
    if suffix == "softac":
        return name.split(", ", 1)[-1].split(" preset")[0]
    return suffix[len("softac-"):] if suffix.startswith("softac-") else suffix


def unique_labels(labels: dict[str, str]) -> dict[str, str]:
    """Labels made unique: a label two configurations share gets a number after it."""
    counts: dict[str, int] = {}
    out = {}
    for name in sorted(labels):
        label = labels[name]
        counts[label] = counts.get(label, 0) + 1
        out[name] = label if counts[label] == 1 else f"{label} ({counts[label]})"
    return out


def against_best_published(scores: dict[str, dict[str, tuple[float, float | None]]],
                           published: dict[str, dict[str, tuple[float, float, int]]]) -> list[str]:
    """Issue 42's goal for each configuration run on all five v4 envs: its mean final return over the best
    published 100k-step mean per env, the average of those fractions, the envs where it is at or above published
    CrossQ, and what its five runs cost (the sum of the envs' median one-core seconds)."""
    best = {env: published[best_published(published, env)][env][0] for env in SUITE_V4}
    full = {name: envs for name, envs in scores.items() if all(env in envs for env in SUITE_V4)}
    if not full:
        return []
    lines = [f"### {AGAINST_BEST}", "",
             "Each configuration run on all five envs: its mean final return over the best published mean per env ("
             + ", ".join(f"{env.split('-')[0]} {best[env]:.0f}" for env in SUITE_V4) + "), the mean of those "
             "fractions (issue 42's goal: >= 0.85, and at or above published CrossQ on all five; issue 66's: >= 0.85, "
             "above published FlashSAC on at least 3 of 5, at <= 3x `crossq-avg`'s one-core time), the sum over "
             "the five envs of the median one-core seconds of a run (machines as in the tables above), and that sum "
             "over `crossq-avg`'s.", "",
             "| configuration | " + " | ".join(env.split("-")[0] for env in SUITE_V4)
             + " | mean fraction | envs >= published CrossQ | envs > published FlashSAC | one-core s, five envs "
             "| time / crossq-avg's |",
             "|---|" + "---|" * (len(SUITE_V4) + 5)]
    costs = {name: _five_env_seconds(envs) for name, envs in full.items()}
    for name, envs in full.items():
        fractions = [envs[env][0] / best[env] for env in SUITE_V4]
        at_crossq = sum(envs[env][0] >= published["CrossQ"][env][0] for env in SUITE_V4)
        above_flashsac = sum(envs[env][0] > published["FlashSAC"][env][0] for env in SUITE_V4)
        cost, reference = costs[name], costs.get(CPU_PRESET)
        ratio = f"{cost / reference:.2f}" if cost is not None and reference else "-"
        lines.append(f"| {name} | " + " | ".join(f"{f:.2f}" for f in fractions)
                     + f" | {np.mean(fractions):.2f} | {at_crossq} of {len(SUITE_V4)} | {above_flashsac} of "
                     f"{len(SUITE_V4)} | {'-' if cost is None else f'{cost:.0f}'} | {ratio} |")
    return [*lines, ""]


# options chosen per env on tuning seeds (benchmarks/screens, docs/results-notes.md), scored as one configuration
# in the table against the best published: name -> (the configuration on every env, {env: the one used there})
PER_ENV_CHOICES = {
    "softac, crossq-avg preset + gradient_steps=2, and weight_norm=true on Humanoid (per env, from tuning seeds)": (
        "softac, crossq-avg preset + gradient_steps=2",
        {"Humanoid-v4": "softac, crossq-avg preset + gradient_steps=2 weight_norm=true"}),
}


def per_env_choices(scores: dict[str, dict[str, tuple[float, float | None]]],
                    choices: dict[str, tuple[str, dict[str, str]]] | None = None
                    ) -> dict[str, dict[str, tuple[float, float | None]]]:
    """Each per-env choice whose configurations ran on their envs, as one configuration's scores."""
    combined = {}
    for name, (default, per_env) in (PER_ENV_CHOICES if choices is None else choices).items():
        picks = {env: per_env.get(env, default) for env in SUITE_V4}
        if all(env in scores.get(config, {}) for env, config in picks.items()):
            combined[name] = {env: scores[config][env] for env, config in picks.items()}
    return combined


CPU_PRESET = "softac, crossq-avg preset"  # the preset for CPU users (issue 66), the moonshot's time unit


def _five_env_seconds(envs: dict[str, tuple[float, float | None]]) -> float | None:
    seconds = [envs[env][1] for env in SUITE_V4]
    return float(sum(seconds)) if all(s is not None for s in seconds) else None


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
