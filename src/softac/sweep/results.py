"""A sweep's results, read from its run directories: a row per trial, a row per configuration, and
DIR/summary.csv, DIR/summary.md and DIR/plots/."""

from __future__ import annotations

import contextlib
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from softac.config.sac_config import override_key
from softac.errors import RunFailed, SoftacError
from softac.outputs.seed_stats import summarize_seeds
from softac.sweep.spec import PLOT_DIR, SPEC_FILE, SweepSpec, grid_trials, planned_trials, value_text
from softac.sweep.trial import read_evals, trial_state


def trial_dirs(out: Path) -> list[Path]:
    return sorted(p for p in out.iterdir()
                  if p.is_dir() and not p.name.startswith("_") and p.name != PLOT_DIR and ".incomplete-" not in p.name
                  and (p / "config.yaml").exists())


def _threshold_crossing(evals: list[tuple[int, float]], progress: list[dict[str, str]],
                        threshold: float) -> tuple[int | None, float | None]:
    """First eval step whose mean reaches the threshold, and the run's elapsed seconds at that step (from
    progress rows that have their time_s, as trial_rows keeps them)."""
    for step, value in evals:
        if value >= threshold:
            times = [(float(r["step"]), float(r["time_s"])) for r in progress]
            seconds = float(np.interp(step, *zip(*times))) if times else None
            return step, seconds
    return None, None


SUCCESS_THRESHOLD = 0.9  # steps to a success rate of at least this, for envs that report success (goal envs)


def trial_rows(out: Path, spec: SweepSpec, threshold: float | None = None,
               success_threshold: float = SUCCESS_THRESHOLD) -> list[dict[str, Any]]:
    from softac.run.csv_logs import read_csv

    rows = []
    for run in trial_dirs(out):
        config = yaml.safe_load((run / "config.yaml").read_text()) or {}
        evals = read_evals(run)
        try:
            summary = json.loads((run / "summary.json").read_text())
        except (OSError, ValueError):
            summary = {}
        # a running trial may be writing its last row (the summary so far is read while trials run)
        progress = [line for line in read_csv(run / "progress.csv") if line.get("time_s")]
        row: dict[str, Any] = {"trial": run.name, "seed": config.get("seed")}
        for key in spec.swept_keys():
            row[key] = config.get(key)
        row["final_eval_mean"] = evals[-1][1] if evals else None
        row["best_eval_mean"] = max(v for _, v in evals) if evals else None
        row["steps"] = summary.get("steps", int(float(progress[-1]["step"])) if progress else 0)
        row["wall_s"] = round(summary.get("train_time_s", float(progress[-1]["time_s"]) if progress else 0.0), 1)
        # a trial ASHA stops at its last milestone can miss its summary.json: its evals show it is complete
        complete = trial_state(run, spec.steps) == "done" or (bool(evals) and evals[-1][0] >= spec.steps)
        row["status"] = "done" if complete else ("stopped early" if spec.asha else "incomplete")
        if threshold is not None:
            step, seconds = _threshold_crossing(evals, progress, threshold)
            row["steps_to_threshold"] = step
            row["seconds_to_threshold"] = None if seconds is None else round(seconds, 1)
            after = [v for st, v in evals if step is not None and st >= step]
            # holding matters as much as reaching (a policy that falls over again is not solved)
            row["held_threshold"] = round(sum(v >= threshold for v in after) / len(after), 3) if after else None
        successes = read_evals(run, "success_rate")
        if successes:  # a goal env: its success rates beside the returns
            row["final_success"] = successes[-1][1]
            row["best_success"] = max(v for _, v in successes)
            step, seconds = _threshold_crossing(successes, progress, success_threshold)
            row["steps_to_success"] = step
            row["seconds_to_success"] = None if seconds is None else round(seconds, 1)
        rows.append(row)
    return rows


def aggregate(rows: list[dict[str, Any]], keys: list[str], threshold: float | None,
              name: str = "all") -> list[dict[str, Any]]:
    """One row per configuration (the swept keys' values), over its seeds."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault(json.dumps([row.get(k) for k in keys], default=str), []).append(row)
    table = []
    for members in groups.values():
        finals = [r["final_eval_mean"] for r in members if r["final_eval_mean"] is not None]
        bests = [r["best_eval_mean"] for r in members if r["best_eval_mean"] is not None]
        entry: dict[str, Any] = {"configuration": ", ".join(f"{k}={members[0].get(k)}" for k in keys) or name,
                                 "seeds": len(members), "done": sum(r["status"] == "done" for r in members)}
        if finals:
            entry["final"] = summarize_seeds(finals)
        if bests:
            entry["best"] = summarize_seeds(bests)
        entry["wall_s"] = float(np.median([r["wall_s"] for r in members]))
        entry["steps"] = int(np.median([r["steps"] for r in members]))
        rates = [r["steps"] / r["wall_s"] for r in members if r["wall_s"]]
        entry["steps_per_s"] = float(np.median(rates)) if rates else None
        if threshold is not None:
            reached = [r for r in members if r.get("steps_to_threshold") is not None]
            entry["reached"] = len(reached)
            if reached:
                entry["steps_to_threshold"] = float(np.median([r["steps_to_threshold"] for r in reached]))
                secs = [r["seconds_to_threshold"] for r in reached if r["seconds_to_threshold"] is not None]
                entry["seconds_to_threshold"] = float(np.median(secs)) if secs else None
                entry["held_threshold"] = float(np.mean([r["held_threshold"] for r in reached]))
        successes = [r["final_success"] for r in members if r.get("final_success") is not None]
        if successes:
            entry["final_success"] = float(np.mean(successes))
            reached = [r for r in members if r.get("steps_to_success") is not None]
            entry["success_reached"] = len(reached)
            entry["steps_to_success"] = float(np.median([r["steps_to_success"] for r in reached])) if reached else None
        table.append(entry)
    table.sort(key=lambda e: -(e["final"].mean if "final" in e else -math.inf))
    return table


def _fmt(x: float | None, digits: int = 1) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def markdown_table(table: list[dict[str, Any]], threshold: float | None,
                   success_threshold: float = SUCCESS_THRESHOLD) -> str:
    head = ["configuration", "seeds", "final eval (mean ± std)", "final 95% CI", "final IQM", "best eval (mean ± std)",
            "median steps", "median wall s", "steps/s"]
    success = any("final_success" in e for e in table)
    if success:
        head += ["final success rate (mean)", f"reached success {success_threshold:g}", "median steps to it"]
    if threshold is not None:
        head += [f"reached {threshold:g}", "median steps to it", "median s to it", "evals held after"]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    for e in table:
        final, best = e.get("final"), e.get("best")
        cells = [e["configuration"], f"{e['seeds']}" + ("" if e["done"] == e["seeds"] else f" ({e['done']} done)"),
                 f"{final.mean:.1f} ± {final.std:.1f}" if final else "-",
                 f"[{final.mean - final.ci_half:.1f}, {final.mean + final.ci_half:.1f}]" if final else "-",
                 f"{final.iqm:.1f}" if final else "-",
                 f"{best.mean:.1f} ± {best.std:.1f}" if best else "-", f"{e['steps']}", _fmt(e["wall_s"]),
                 _fmt(e.get("steps_per_s"))]
        if success:
            cells += [_fmt(e.get("final_success"), 2),
                      f"{e['success_reached']}/{e['seeds']}" if "final_success" in e else "-",
                      _fmt(e.get("steps_to_success"), 0)]
        if threshold is not None:
            cells += [f"{e['reached']}/{e['seeds']}", _fmt(e.get("steps_to_threshold"), 0),
                      _fmt(e.get("seconds_to_threshold")),
                      "-" if e.get("held_threshold") is None else f"{100 * e['held_threshold']:.0f}%"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def check_command(spec: SweepSpec, values: dict[str, Any], seeds: int = 5, out: str = "DIR") -> str:
    """The `softac sweep` line that trains the configuration `values` of a search on more seeds: the search's
    preset and --set overrides, then the sampled values (which replace an override of the same key)."""
    import shlex

    pairs = [pair for pair in spec.overrides if override_key(pair.split("=", 1)[0]) not in values]
    pairs += [f"{k}={value_text(v)}" for k, v in values.items()]
    cmd = ["softac", "sweep", "--env", spec.env_id, "--seeds", str(seeds), "--steps", str(spec.steps)]
    if spec.preset:
        cmd += ["--preset", spec.preset]
    if pairs:
        cmd += ["--set", *pairs]
    return " ".join(shlex.quote(part) for part in [*cmd, "--out", out])


def write_summaries(out: Path, spec: SweepSpec, threshold: float | None = None,
                    success_threshold: float = SUCCESS_THRESHOLD) -> list[Path]:
    """DIR/summary.csv, DIR/summary.md and DIR/plots/ from the trial run directories. A sweep directory removed
    or moved while its sweep ran (its SPEC_FILE gone) is a failed sweep (RunFailed, exit 3), not a crash."""
    import csv

    from softac.run.run_dir import write_atomic

    if not (out / SPEC_FILE).exists():
        raise RunFailed(f"the sweep directory {out} was removed or moved while the sweep ran (no {SPEC_FILE} "
                        f"there): its trials' results are not where the sweep wrote them")
    rows = trial_rows(out, spec, threshold, success_threshold)
    if not rows:
        return []
    columns = list(dict.fromkeys(key for row in rows for key in row))  # success columns where any trial has them
    csv_path = out / "summary.csv"
    with open(csv_path.with_suffix(".csv.tmp"), "w", newline="") as f:
        writer = csv.DictWriter(f, columns)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: json.dumps(v) if isinstance(v, list) else ("" if v is None else v)
                             for k, v in row.items()})
    os.replace(csv_path.with_suffix(".csv.tmp"), csv_path)
    keys = spec.swept_keys()
    table = aggregate(rows, keys, threshold, name=spec.framework)
    what = spec.framework if spec.framework != "softac" else f"softac ({spec.preset or 'the env preset'})"
    text = [f"# Sweep on {spec.env_id}: {what}, {spec.steps} steps per trial", "",
            f"{len(rows)} of {planned_trials(spec)} trials with results, seeds {spec.seeds}" + (f"; overrides: {' '.join(spec.overrides)}"
                                                        if spec.overrides else "") + ".",
            "Final eval: the last deterministic evaluation of each trial; 95% CI: Student t over seeds; IQM: the "
            "interquartile mean over seeds (rliable's; the plain mean below 4 seeds)."
            + ("" if spec.target_return is None else
               f" Each trial stops at the first evaluation that reaches {spec.target_return:g} (its final eval).")
            + ("" if spec.target_success is None else
               f" Each trial stops at the first evaluation whose success rate reaches {spec.target_success:g}."), "",
            markdown_table(table, threshold, success_threshold), ""]
    if spec.search and table:
        best = max((r for r in rows if r["final_eval_mean"] is not None), key=lambda r: r["final_eval_mean"],
                   default=None)
        if best is not None:
            text += [f"Best trial: {best['trial']} (final eval {best['final_eval_mean']:.1f}). Check it on more "
                     f"seeds: `{check_command(spec, {k: best[k] for k in keys})}`", ""]
    md_path = out / "summary.md"
    write_atomic(md_path, "\n".join(text).encode())
    written = [csv_path, md_path]
    with contextlib.suppress(SoftacError):
        from softac.outputs.plots import plot_comparison, plot_final_returns

        (out / PLOT_DIR).mkdir(exist_ok=True)
        runs = trial_dirs(out)
        written.append(plot_comparison(runs, out / PLOT_DIR / "comparison.png"))
        written.append(plot_final_returns(runs, out / PLOT_DIR / "final_returns.png"))
        if any(r.get("final_success") is not None for r in rows):
            written.append(plot_comparison(runs, out / PLOT_DIR / "success_comparison.png", column="success_rate"))
    return written


def ended_trials(out: Path, spec: SweepSpec) -> set[str]:
    """Names of the trials whose runs in `out` have ended (finished, or stopped early by ASHA): what a resumed
    sweep's progress lines count as ended before it started."""
    if spec.search:
        return {r["trial"] for r in trial_rows(out, spec) if r["status"] != "incomplete"}
    return {t["name"] for t in grid_trials(spec) if trial_state(out / t["name"], spec.steps) == "done"}


def unfinished_trials(out: Path, spec: SweepSpec) -> list[str]:
    """Trials still to train: not started or interrupted (a trial ASHA stopped early is finished)."""
    if spec.search:
        rows = trial_rows(out, spec)
        missing = [f"(not started {i + 1})" for i in range(max(0, spec.samples - len(rows)))]
        return [r["trial"] for r in rows if r["status"] == "incomplete"] + missing
    return [t["name"] for t in grid_trials(spec) if trial_state(out / t["name"], spec.steps) != "done"]
