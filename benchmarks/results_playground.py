"""docs/results.md's section on MuJoCo Playground's envs collected on the device (issue 67): softac's device loop
beside Brax's own SAC trainer (`--framework brax-sac`) at the same settings, from the sweeps of
benchmarks/playground_cpu.sh (SWEEPS/playground-ENV-FRAMEWORK-NAME)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import yaml

from results_common import machines_of, short_machines

PLAYGROUND = "MuJoCo Playground on the device"
PREFIX = "playground-"


def steady_steps_per_s(run: Path, total_steps: int) -> float | None:
    """The median of progress.csv's env steps per second over its rows in the run's second half: past the
    replay's prefill and the compiles, for softac's rows (one per log_interval) and Brax's (one per epoch) alike."""
    try:
        with open(run / "progress.csv", newline="") as f:
            rows = [r for r in csv.DictReader(f) if r.get("fps") and int(float(r["step"])) > total_steps / 2]
    except OSError:
        return None
    return float(np.median([float(r["fps"]) for r in rows])) if rows else None


def softac_settings(config: dict) -> str:
    """What a softac trial of the brax-sac preset ran: Brax's networks and warm-up (the preset from 7c51039 on), or
    the preset before them (uniform warm-up, PyTorch's init, a clamped log std, LayerNorm before each ReLU)."""
    if config.get("framework", "softac") != "softac":
        return "Brax's own"
    brax_like = config.get("init") == "lecun_uniform" and config.get("warmup_actions") == "policy"
    return "Brax's networks and warm-up" if brax_like else "before 7c51039"


def playground_runs(d: Path) -> dict | None:
    """One sweep's finished trials: framework, settings, env, envs, seeds' final evaluations, wall seconds, steady
    steps/s."""
    trials = sorted(p.parent for p in d.glob("*/summary.json"))
    if not trials:
        return None
    finals, walls, speeds, envs, framework, env_id = [], [], [], set(), "softac", ""
    for run in trials:
        summary = json.loads((run / "summary.json").read_text())
        config = yaml.safe_load((run / "config.yaml").read_text()) or {}
        framework = config.get("framework", "softac")
        env_id = config["env_id"]
        envs.add(config["brax"]["num_envs"] if framework == "brax-sac" else config["n_envs"])
        finals.append(summary["last_eval"])
        walls.append(summary["wall_s"])
        speeds.append(steady_steps_per_s(run, int(config["total_steps"])))
    return {"framework": framework, "settings": softac_settings(config), "env": env_id, "envs": sorted(envs),
            "finals": finals, "walls": walls,
            "speeds": [s for s in speeds if s is not None], "steps": int(config["total_steps"]),
            "machines": machines_of(trials)}


def playground_section(sweeps: Path) -> list[str]:
    dirs = sorted(d for d in sweeps.glob(PREFIX + "*") if d.is_dir())
    runs = [(d.name, r) for d in dirs if (r := playground_runs(d)) is not None]
    if not runs:
        return []
    lines = [f"## {PLAYGROUND}", "",
             "softac's device loop (envs, replay and updates in one jitted scan a chunk) beside Brax's own SAC trainer "
             "(`--framework brax-sac`, brax 0.14.2) at the same settings, the `brax-sac` preset (Playground's settings "
             "for its DeepMind Control ports: batch 512, 8 updates per vector step, 256x256, LayerNorm critics), on "
             "one pinned CPU per trial (`bash benchmarks/playground_cpu.sh`). Env steps per second: the median of "
             "each trial's progress rows in its second half (past the prefill and the compiles); the final "
             "evaluation is each framework's own, `eval_episodes` deterministic episodes at once (softac's from the "
             "same starts each time, Brax's from fresh ones). The throughput sweeps' evaluations come after a few "
             "hundred updates and say little about learning. Settings: softac's trials at the preset from 7c51039 "
             "on (Brax's LeCun-uniform init, softplus std, LayerNorm after each activation and a warm-up from the "
             "initial policy) or before it. Sweeps of the same settings are pooled in a row of their own (+). Two "
             "sweeps of 2026-12-07, brax-sac-500k-s3 and softac-500k-s0, shared the machine with test runs on the "
             "other core: their env steps per second and wall times are below what they run alone, and so are the "
             "pooled rows'. Speeds compare on brax-sac-500k beside softac-500k-s3 (each alone on the machine but "
             "for one other pinned trial); returns on all six seeds.", "",
             "| sweep | framework | settings | env | envs | steps | seeds | env steps/s (median) | "
             "final eval (mean ± sd) | wall s (median) | machine |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    groups: dict[tuple, list[tuple[str, dict]]] = {}
    for name, r in runs:
        lines.append(_row(name, r))
        groups.setdefault((r["framework"], r["settings"], r["env"], tuple(r["envs"]), r["steps"]), []).append((name, r))
    for members in groups.values():
        if len(members) > 1:
            pooled = {**members[0][1], **{k: sum((r[k] for _, r in members), []) for k in ("finals", "walls", "speeds")},
                      "machines": " and ".join(sorted({m for _, r in members for m in r["machines"].split(" and ")}))}
            lines.append(_row(" + ".join(name for name, _ in members), pooled))
    return lines + [""]


def _row(name: str, r: dict) -> str:
    finals = np.asarray(r["finals"], float)
    speed = f"{np.median(r['speeds']):,.0f}" if r["speeds"] else "-"
    spread = finals.std(ddof=1) if len(finals) > 1 else 0.0
    return (f"| {name} | {r['framework']} | {r['settings']} | {r['env']} | {', '.join(map(str, r['envs']))} | "
            f"{r['steps']:,} | {len(finals)} | {speed} | {finals.mean():.1f} ± {spread:.1f} | "
            f"{np.median(r['walls']):,.0f} | {short_machines(r['machines'])} |")
