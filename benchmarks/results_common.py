"""What benchmarks/results_doc.py's page sections share: the envs and their thresholds, the suites, the
published tables' files, finding an env's sweeps, their finished trials, wall-time ratios, random returns and the
machines a set of runs ran on."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from softac.peers import PEERS
from softac.sweep import load_spec, trial_rows


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


# trials whose wall time is not comparable (their returns are): sweep/trial -> why, kept beside the sweeps
TIMING_EXCLUDED = "timing-excluded.yaml"


def timing_excluded(sweeps: Path) -> dict[str, str]:
    import yaml

    path = sweeps / TIMING_EXCLUDED
    return (yaml.safe_load(path.read_text()) or {}) if path.exists() else {}


def finished_trials(d: Path, excluded: dict[str, str] | None = None) -> list[dict]:
    """The sweep's finished trials' rows, each with the day it started (None for runs from before
    config.yaml recorded it), the env frames it ran (agent steps times action repeat), `gpu` (it trained on a GPU:
    device gpu or cuda) and `timed`: False for a
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
        row["gpu"] = str(config.get("device", "cpu")) in ("gpu", "cuda")  # its seconds are a GPU's
        # a trial pinned to CPUs another pinned softac process held (softac.base.cpus.cpus_shared) ran disturbed too
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

    from softac.outputs.reference import run_baselines

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


def departures(record: dict, today: Any) -> dict[str, Any]:
    """The settings a trial's config.yaml (`record`) holds that differ from the SACConfig `today`, seed and budget
    aside: {key: the value the trial ran with}. The record, not the sweep's preset name: a preset's file can change
    after its runs. A key the record lacks predates it, so the trial ran at that key's default (what the code did
    then), save pixel_range: pixels were at [-0.5, 0.5] before it (`centered`, as softac.run.checkpoint_contents reads old
    checkpoints)."""
    import dataclasses

    from softac.config.sac_config import SACConfig

    names = {f.name for f in dataclasses.fields(SACConfig)}
    before = {"pixel_range": "centered"} if record.get("pixels") else {}
    ran = SACConfig().replace(**{**before, **{k: v for k, v in record.items() if k in names}})
    expected = today.replace(seed=ran.seed, total_steps=ran.total_steps)
    return {f: getattr(ran, f) for f in sorted(names) if getattr(ran, f) != getattr(expected, f)}


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
