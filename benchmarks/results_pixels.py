"""docs/results.md's section on learning from pixels: softac's DrQ runs beside SB3's CnnPolicy and the published
DrQ."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from softac.sweep import load_spec, trial_rows, value_text

from results_common import departures, ENVS, machines_of, short_machines


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
