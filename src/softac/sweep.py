"""`softac sweep`: many runs at once on Ray Tune (seeds x a grid, or a Tune search), locally or on a cluster.

Each trial is an ordinary run directory DIR/<trial>, trained by its own `softac train` process that the
Ray trial starts and watches; each new row of its eval.csv is reported to Tune, which is what a scheduler
such as ASHA acts on. Nothing about a trial lives only in Ray: whether it is finished is read from its run
directory (RUN/summary.json), so running the same command again, or `softac sweep --resume DIR`, trains
only what is missing and continues interrupted trials from their last checkpoint.

When the trials are done, DIR/summary.csv (a row per trial), DIR/summary.md (mean +- std and 95% CI per
configuration) and DIR/plots/ are written from the run directories.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from softac.config import ConfigError, SACConfig, override_key
from softac.cpus import claim_cpus
from softac.errors import SoftacError
from softac.stats import summarize

SPEC_FILE = "sweep.json"
RAY_DIR = "_ray"
LOG_DIR = "_logs"
PLOT_DIR = "plots"
FRAMEWORKS = ("softac", "sb3", "sbx")
SEARCHES = ("random", "optuna")
METRIC = "eval_mean_return"
INSTALL_RAY = "softac sweep needs Ray Tune: pip install 'softac[ray]' (from a checkout: pip install -e '.[ray]')"

# The documented SAC search space (docs/sweeps.md); `--space FILE` replaces it. Each key is a config key,
# each value one of: {loguniform: [lo, hi]}, {uniform: [lo, hi]}, {randint: [lo, hi]} (hi excluded),
# {choice: [v1, v2, ...]}.
DEFAULT_SPACE: dict[str, dict[str, list[Any]]] = {
    "actor_lr": {"loguniform": [1e-4, 3e-3]},
    "critic_lr": {"loguniform": [1e-4, 3e-3]},
    "tau": {"loguniform": [0.002, 0.1]},
    "gamma": {"choice": [0.95, 0.98, 0.99, 0.995]},
    "batch_size": {"choice": [64, 128, 256]},
    "hidden_sizes": {"choice": [[64, 64], [128, 128], [256, 256]]},
    "gradient_steps": {"choice": [1, 2]},
}
SPACE_KINDS = ("loguniform", "uniform", "randint", "choice")


# ---- what a sweep is --------------------------------------------------------------------

@dataclasses.dataclass
class SweepSpec:
    """Everything that defines a sweep's trials (stored as DIR/sweep.json; a rerun must match it)."""

    env_id: str
    steps: int
    seeds: list[int]
    preset: str | None = None
    overrides: list[str] = dataclasses.field(default_factory=list)
    grid: dict[str, list[Any]] = dataclasses.field(default_factory=dict)
    framework: str = "softac"
    search: str | None = None
    samples: int = 0
    space: dict[str, dict[str, list[Any]]] | None = None
    asha: bool = False

    def preset_config(self) -> SACConfig:
        """The preset (or the env's own) with the overrides, before the sweep's step budget."""
        config = SACConfig.preset(self.preset, env_id=self.env_id) if self.preset else SACConfig.for_env(self.env_id)
        return config.with_overrides(self.overrides)

    def base_config(self) -> SACConfig:
        return self.preset_config().replace(total_steps=self.steps)

    def swept_keys(self) -> list[str]:
        return list(self.space or {}) if self.search else list(self.grid)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "SweepSpec":
        known = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in known})


def parse_seeds(text: str, first: int = 0) -> list[int]:
    """`N` means seeds first..first+N-1; `a,b,c` lists them."""
    try:
        if "," in text:
            seeds = [int(s) for s in text.split(",") if s.strip()]
        else:
            count = int(text)
            if count < 1:
                raise ValueError
            seeds = list(range(first, first + count))
    except ValueError:
        raise SoftacError(f"--seeds takes a count N or a comma list of seeds, got {text!r}") from None
    if not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0:
        raise SoftacError(f"--seeds needs distinct seeds >= 0, got {text!r}")
    return seeds


def _split_top_level(text: str) -> list[str]:
    """Split on commas outside brackets: `hidden_sizes=[64,64],[256,256]` has two values."""
    parts, depth, current = [], 0, ""
    for ch in text:
        depth += ch in "[{("
        depth -= ch in "]})"
        if ch == "," and depth == 0:
            parts.append(current)
            current = ""
        else:
            current += ch
    parts.append(current)
    return [p.strip() for p in parts]


def parse_grid(items: list[str]) -> dict[str, list[Any]]:
    grid: dict[str, list[Any]] = {}
    for item in items:
        if "=" not in item:
            raise SoftacError(f"--grid expects KEY=V1,V2,..., got {item!r}")
        key, raw = item.split("=", 1)
        key = override_key(key)
        values = []
        for part in _split_top_level(raw):
            if not part:
                raise SoftacError(f"--grid {key}: empty value in {raw!r}")
            try:
                values.append(yaml.safe_load(part))
            except yaml.YAMLError:
                values.append(part)
        if key in grid:
            raise SoftacError(f"--grid {key} given twice")
        if len({json.dumps(v) for v in values}) != len(values):
            raise SoftacError(f"--grid {key} repeats a value: {raw!r}")
        grid[key] = values
    return grid


def _value_text(value: Any) -> str:
    """A value as a `--set` accepts it (JSON is YAML) and as a short directory-name part."""
    return json.dumps(value, separators=(",", ":"))  # no spaces: the summary's --set line pastes into a shell


def _name_part(value: Any) -> str:
    if isinstance(value, list):
        return "x".join(str(v) for v in value)
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value).replace("/", "_").replace(" ", "")


def grid_points(grid: dict[str, list[Any]]) -> list[dict[str, Any]]:
    keys = list(grid)
    return [dict(zip(keys, combo)) for combo in itertools.product(*(grid[k] for k in keys))]


def trial_name(values: dict[str, Any], seed: int) -> str:
    return ",".join([f"{k}={_name_part(v)}" for k, v in values.items()] + [f"seed={seed}"])


def grid_trials(spec: SweepSpec) -> list[dict[str, Any]]:
    return [{"name": trial_name(values, seed), "seed": seed, "values": values}
            for values in grid_points(spec.grid) for seed in spec.seeds]


def load_space(path: str | None) -> dict[str, dict[str, list[Any]]]:
    if path is None:
        return json.loads(json.dumps(DEFAULT_SPACE))
    try:
        data = yaml.safe_load(Path(path).read_text())
    except OSError as exc:
        raise SoftacError(f"cannot read search space {path}: {exc.strerror or exc}") from None
    except yaml.YAMLError as exc:
        raise SoftacError(f"search space {path} is not valid YAML: {str(exc).splitlines()[0]}") from None
    if not isinstance(data, dict) or not data:
        raise SoftacError(f"search space {path} must map config keys to {{kind: values}}")
    return data


def check_space(space: dict[str, Any], base: SACConfig) -> None:
    for key, dist in space.items():
        if not (isinstance(dist, dict) and len(dist) == 1 and next(iter(dist)) in SPACE_KINDS):
            raise SoftacError(f"search space key {key}: expected one of {', '.join(SPACE_KINDS)} "
                              f"with a list, got {dist!r}")
        kind, values = next(iter(dist.items()))
        if not isinstance(values, list) or not values:
            raise SoftacError(f"search space key {key}: {kind} needs a list")
        if kind != "choice":
            if len(values) != 2 or not all(isinstance(v, (int, float)) for v in values) or values[0] >= values[1]:
                raise SoftacError(f"search space key {key}: {kind} needs [low, high] with low < high")
            if kind == "loguniform" and values[0] <= 0:
                raise SoftacError(f"search space key {key}: loguniform needs low > 0")
        probes = values if kind == "choice" else [values[0]]
        for value in probes:  # unknown keys and impossible values fail here, before Ray starts
            base.with_overrides([f"{key}={_value_text(value)}"])


def _tune_space(space: dict[str, dict[str, list[Any]]]) -> dict[str, Any]:
    from ray import tune

    out = {}
    for key, dist in space.items():
        kind, values = next(iter(dist.items()))
        out[key] = {"loguniform": lambda v: tune.loguniform(*v), "uniform": lambda v: tune.uniform(*v),
                    "randint": lambda v: tune.randint(*v), "choice": tune.choice}[kind](values)
    return out


def default_threshold(env_id: str) -> float | None:
    """The env's registered reward_threshold (InvertedPendulum: 950), if it has one."""
    import gymnasium as gym

    try:
        threshold = gym.spec(env_id).reward_threshold
    except Exception:  # unknown ids are reported by validate()
        return None
    return None if threshold is None else float(threshold)


def validate(spec: SweepSpec) -> SACConfig:
    """Every trial's config, checked before Ray starts (bad input fails in a second, with one line)."""
    from softac.envs import resolve_env_id

    if spec.framework not in FRAMEWORKS:
        raise SoftacError(f"--framework must be one of {', '.join(FRAMEWORKS)}")
    resolve_env_id(spec.env_id)
    base = spec.base_config()
    if spec.framework != "softac":
        allowed = {"eval_interval", "eval_episodes", "log_interval"}
        own = [pair for pair in spec.overrides if override_key(pair.split("=", 1)[0]) not in allowed]
        if spec.grid or spec.search or spec.preset or own:
            raise SoftacError(f"--framework {spec.framework} runs its SAC at its own defaults; --grid, --search, "
                              f"--preset and --set (other than eval_interval/eval_episodes/log_interval) "
                              f"are for softac")
        from softac.bench import available_frameworks

        if available_frameworks([spec.framework])[1]:
            raise SoftacError(f"--framework {spec.framework} needs the [bench] extra: `make bench` "
                              "(or: pip install torch==2.13.0 && pip install -e '.[bench]')")
    if spec.search:
        if spec.grid:
            raise SoftacError("--grid and --search are alternatives: a grid sweeps listed values, a search samples")
        if spec.samples < 1:
            raise SoftacError("--samples must be >= 1")
        if len(spec.seeds) != 1:
            raise SoftacError("a search runs each sampled configuration on one seed (--seeds 1); run the best "
                              "configurations again with --grid and several seeds")
        check_space(spec.space or {}, base)
    elif spec.asha:
        raise SoftacError("--asha stops trials early and needs --search (random or optuna)")
    for values in grid_points(spec.grid):
        try:
            base.with_overrides([f"{k}={_value_text(v)}" for k, v in values.items()])
        except ConfigError as exc:
            raise SoftacError(f"--grid: {exc}") from None
    return base


def prepare_out_dir(out: Path, spec: SweepSpec) -> None:
    """A new sweep takes an empty or missing DIR; an existing sweep continues only with the same spec."""
    spec_path = out / SPEC_FILE
    if spec_path.exists():
        try:
            stored = json.loads(spec_path.read_text())
        except (OSError, ValueError) as exc:
            raise SoftacError(f"cannot read {spec_path}: {exc}") from None
        mine = spec.to_dict()
        differs = sorted(k for k in set(stored) | set(mine) if stored.get(k) != mine.get(k))
        if differs:
            raise SoftacError(f"{out} holds a different sweep (differs in {', '.join(differs)}); continue it with "
                              f"`softac sweep --resume {out}` or pick another --out")
        return
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise SoftacError(f"{out} exists and is not a sweep directory; pick another --out")
    from softac.checkpoint import write_atomic

    try:
        out.mkdir(parents=True, exist_ok=True)
        write_atomic(spec_path, (json.dumps(spec.to_dict(), indent=1) + "\n").encode())
    except OSError as exc:
        raise SoftacError(f"cannot create sweep directory {out}: {exc.strerror or exc}") from None


def load_spec(out: Path) -> SweepSpec:
    path = out / SPEC_FILE
    if not path.exists():
        raise SoftacError(f"{out} is not a sweep directory (no {SPEC_FILE})")
    try:
        return SweepSpec.from_dict(json.loads(path.read_text()))
    except (OSError, ValueError, TypeError) as exc:
        raise SoftacError(f"cannot read {path}: {exc}") from None


# ---- one trial -----------------------------------------------------------------------------

def trial_state(run: Path) -> str:
    """'done', 'partial' (a checkpoint to continue from) or 'new', from the run directory alone."""
    try:
        summary = json.loads((run / "summary.json").read_text())
        if summary.get("stopped_early") or summary["steps"] >= summary["total_steps"]:
            return "done"
    except (OSError, ValueError, KeyError, TypeError):
        pass
    return "partial" if (run / "checkpoints" / "last").exists() else "new"


def trial_command(spec: SweepSpec, base: SACConfig, trial: dict[str, Any], run: Path) -> list[str]:
    if spec.framework != "softac":
        return [sys.executable, "-m", "softac.bench", "run", spec.framework, "--env", spec.env_id,
                "--seed", str(trial["seed"]), "--steps", str(spec.steps), "--out", str(run),
                "--eval-interval", str(base.eval_interval), "--eval-episodes", str(base.eval_episodes),
                "--log-interval", str(base.log_interval)]
    if trial_state(run) == "partial":
        return [sys.executable, "-m", "softac", "train", "--resume", str(run), "--no-progress"]
    pairs = list(spec.overrides) + [f"{k}={_value_text(v)}" for k, v in trial["values"].items()]
    cmd = [sys.executable, "-m", "softac", "train", "--env", spec.env_id, "--seed", str(trial["seed"]),
           "--steps", str(spec.steps), "--out", str(run), "--no-progress"]
    if spec.preset:
        cmd += ["--preset", spec.preset]
    if pairs:
        cmd += ["--set", *pairs]
    return cmd


def _thread_env(threads: int) -> dict[str, str]:
    """Thread counts for the libraries that read them (PyTorch for the peers, OpenMP, MKL); XLA takes
    its own from the CPUs of `claim_cpus`."""
    env = dict(os.environ)
    env["SOFTAC_THREADS"] = env["OMP_NUM_THREADS"] = env["MKL_NUM_THREADS"] = str(threads)
    return env


def trial_process_setup(cpus: list[int]):
    """What the trial's process runs before `exec`: pinned to its CPUs; SIGTERM when the Ray worker dies."""
    def setup() -> None:
        if cpus:
            os.sched_setaffinity(0, cpus)
        with contextlib.suppress(Exception):
            import ctypes

            ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG (Linux)
    return setup


def _read_evals(run: Path) -> list[tuple[int, float]]:
    from softac.logs import read_csv

    out = []
    for row in read_csv(run / "eval.csv"):
        with contextlib.suppress(ValueError, TypeError):
            out.append((int(float(row["step"])), float(row["mean_return"])))
    return out


def run_trial(params: dict[str, Any], spec: dict[str, Any], out: str, cpus: float) -> None:
    """A Ray Tune function trainable: one trial = one `softac train` process, its evals reported to Tune."""
    from ray import tune

    sweep = SweepSpec.from_dict(spec)
    base = sweep.base_config()
    if sweep.search:
        trial = {"name": f"trial={tune.get_context().get_trial_id()},seed={sweep.seeds[0]}", "seed": sweep.seeds[0],
                 "values": {k: params[k] for k in sweep.space or {}}}
    else:
        trial = params["trial"]
    root = Path(out)
    run = root / trial["name"]
    if trial_state(run) == "done":
        return
    if sweep.framework != "softac" and run.exists():  # peers cannot resume: keep the partial run aside
        n = 1
        while run.with_name(f"{run.name}.incomplete-{n}").exists():
            n += 1
        os.replace(run, run.with_name(f"{run.name}.incomplete-{n}"))
    (root / LOG_DIR).mkdir(parents=True, exist_ok=True)
    log_path = root / LOG_DIR / f"{trial['name']}.log"
    previous = _read_evals(run)  # a resumed trial has reported these already
    reported = {step for step, _ in previous}
    best = max((v for _, v in previous), default=-math.inf)
    cmd = trial_command(sweep, base, trial, run)
    threads = max(1, int(cpus))
    pinned, locks = claim_cpus(threads)
    with open(log_path, "a") as log, contextlib.ExitStack() as held:
        for lock in locks:
            held.callback(lock.close)
        log.write(f"$ {' '.join(cmd)}" + (f"  (CPUs {pinned})" if pinned else "") + "\n")
        log.flush()
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=_thread_env(threads),
                                preexec_fn=trial_process_setup(pinned) if os.name == "posix" else None)
        try:
            while True:
                code = proc.poll()
                for step, value in _read_evals(run):
                    if step not in reported:
                        reported.add(step)
                        best = max(best, value)
                        tune.report({METRIC: value, "best_eval_mean_return": best, "step": step})
                if code is not None:
                    break
                time.sleep(1.0)
        finally:
            if proc.poll() is None:  # the trial was stopped (ASHA, Ctrl-C): the run checkpoints and exits 130
                proc.terminate()
                try:
                    proc.wait(60)
                except subprocess.TimeoutExpired:
                    proc.kill()
    if code not in (0, 130):  # 130: stopped by a signal, with a checkpoint; it resumes later
        # reported, not raised: a raised error makes Tune print a traceback; this way the user gets one line
        lines = [ln for ln in log_path.read_text().splitlines() if ln.strip()]
        tune.report({METRIC: best, "step": max(reported, default=0),
                     "trial_error": f"{trial['name']} exited {code}: {lines[-1] if lines else ''} (log: {log_path})"})


# ---- the driver ----------------------------------------------------------------------------

def _require_ray() -> None:
    try:
        import ray  # noqa: F401
        from ray import tune  # noqa: F401  (Tune ships in ray[tune])
    except ImportError:
        raise SoftacError(INSTALL_RAY) from None


def _check_reachable(address: str) -> None:
    """Ray retries an unreachable address for minutes: fail in seconds instead."""
    import socket

    hostport = address.split("://", 1)[-1]
    if address == "auto" or ":" not in hostport:
        return
    host, _, port = hostport.rpartition(":")
    try:
        with socket.create_connection((host, int(port)), timeout=5):
            pass
    except (OSError, ValueError) as exc:
        raise SoftacError(f"cannot reach the Ray cluster at {address}: {getattr(exc, 'strerror', None) or exc}; "
                          "is `ray start --head` running there?") from None


def _start_ray(address: str | None) -> Any:
    import logging

    import ray

    os.environ.setdefault("RAY_AIR_NEW_OUTPUT", "0")
    os.environ.setdefault("TUNE_DISABLE_AUTO_CALLBACK_LOGGERS", "1")
    kwargs: dict[str, Any] = {"include_dashboard": False, "logging_level": logging.ERROR, "log_to_driver": False}
    try:
        if address:
            ray.init(address=address, **kwargs)
        else:
            ray.init(num_cpus=os.cpu_count() or 1, **kwargs)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        where = f"the Ray cluster at {address}" if address else "a local Ray"
        raise SoftacError(f"cannot start {where}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}"
                          ) from None
    return ray


class _Lines:
    """Plain progress lines from Tune's callback hooks (Ray's own tables are switched off)."""

    def __init__(self, total: int, done: int):
        self.total, self.done = total, done

    def make(self):
        from ray.tune import Callback

        lines = self

        class Printer(Callback):
            def on_trial_result(self, iteration, trials, trial, result, **info):
                if "trial_error" not in result:
                    print(f"  {_trial_label(trial)}: step {result.get('step')}, "
                          f"eval {result.get(METRIC, float('nan')):.1f}", file=sys.stderr, flush=True)

            def on_trial_complete(self, iteration, trials, trial, **info):
                lines.done += 1
                error = (trial.last_result or {}).get("trial_error")
                what = f"FAILED {error}" if error else f"finished {_trial_label(trial)}"
                print(f"[{lines.done}/{lines.total}] {what}", file=sys.stderr, flush=True)

            def on_trial_error(self, iteration, trials, trial, **info):  # a bug of ours or Ray's, not the run's
                lines.done += 1
                print(f"[{lines.done}/{lines.total}] FAILED {_trial_label(trial)} (Ray: {trial.error_file})",
                      file=sys.stderr, flush=True)

        return Printer()


def _trial_label(trial: Any) -> str:
    config = trial.config or {}
    return config["trial"]["name"] if "trial" in config else f"trial={trial.trial_id}"


def run_sweep(spec: SweepSpec, out: Path, address: str | None = None, cpus_per_trial: float = 1.0,
              max_concurrent: int | None = None, threshold: float | None = None, gpus_per_trial: float = 0.0,
              log=lambda *a: print(*a, file=sys.stderr, flush=True)) -> dict[str, Any]:
    """Run (or continue) a sweep; returns {'trials', 'unfinished', 'failed', 'files'}."""
    validate(spec)
    if cpus_per_trial <= 0:
        raise SoftacError("--cpus-per-trial must be > 0")
    if gpus_per_trial < 0:
        raise SoftacError("--gpus-per-trial must be >= 0")
    resources = {"cpu": cpus_per_trial, **({"gpu": gpus_per_trial} if gpus_per_trial else {})}
    _require_ray()
    if address:
        _check_reachable(address)
    prepare_out_dir(out, spec)
    out = out.resolve()
    failed: list[str] = []
    if spec.search:
        if unfinished_trials(out, spec):
            failed = _run_search(spec, out, address, resources, max_concurrent, log)
        else:
            log(f"sweep {out}: all {spec.samples} sampled trials are finished")
    else:
        trials = grid_trials(spec)
        todo = [t for t in trials if trial_state(out / t["name"]) != "done"]
        log(f"sweep {out}: {len(trials)} trial{'s' * (len(trials) != 1)} ({len(trials) - len(todo)} already finished), {spec.framework} on "
            f"{spec.env_id}, {spec.steps} steps each")
        if todo:
            failed = _run_grid(spec, todo, len(trials), out, address, resources, max_concurrent, log)
    files = write_summaries(out, spec, threshold)
    for path in files:
        log(f"wrote {path}")
    unfinished = unfinished_trials(out, spec)
    return {"trials": planned_trials(spec), "unfinished": unfinished, "failed": failed, "files": files}


def planned_trials(spec: SweepSpec) -> int:
    return spec.samples if spec.search else len(spec.seeds) * len(grid_points(spec.grid))


def unfinished_trials(out: Path, spec: SweepSpec) -> list[str]:
    """Trials still to train: not started or interrupted (a trial ASHA stopped early is finished)."""
    if spec.search:
        rows = trial_rows(out, spec)
        missing = [f"(not started {i + 1})" for i in range(max(0, spec.samples - len(rows)))]
        return [r["trial"] for r in rows if r["status"] == "incomplete"] + missing
    return [t["name"] for t in grid_trials(spec) if trial_state(out / t["name"]) != "done"]


def _run_config(out: Path, name: str, callbacks: list) -> Any:
    from ray import tune

    return tune.RunConfig(name=name, storage_path=str(out / RAY_DIR), verbose=0, callbacks=callbacks,
                          failure_config=tune.FailureConfig(max_failures=0))


def _trainable(spec: SweepSpec, out: Path, resources: dict[str, float]):
    """Ray reserves `resources` per trial; with a GPU, Ray sets CUDA_VISIBLE_DEVICES, which the trial inherits."""
    from ray import tune

    return tune.with_resources(tune.with_parameters(run_trial, spec=spec.to_dict(), out=str(out),
                                                    cpus=resources["cpu"]), resources)


def _failures(results: Any) -> list[str]:
    failed = []
    for result in results:
        if result.error is not None:
            failed.append(str(result.error).strip().splitlines()[-1][:300])
        elif (result.metrics or {}).get("trial_error"):
            failed.append(result.metrics["trial_error"])
    return failed


def _run_grid(spec: SweepSpec, todo: list[dict[str, Any]], total: int, out: Path, address: str | None,
              resources: dict[str, float], max_concurrent: int | None, log) -> list[str]:
    _start_ray(address)
    import ray
    from ray import tune

    printer = _Lines(total, total - len(todo)).make()
    try:
        tuner = tune.Tuner(
            _trainable(spec, out, resources),
            param_space={"trial": tune.grid_search(todo)},
            tune_config=tune.TuneConfig(max_concurrent_trials=max_concurrent, reuse_actors=False),
            run_config=_run_config(out, f"grid-{time.strftime('%Y%m%d-%H%M%S')}", [printer]))
        return _failures(tuner.fit())
    finally:
        ray.shutdown()


def _run_search(spec: SweepSpec, out: Path, address: str | None, resources: dict[str, float],
                max_concurrent: int | None, log) -> list[str]:
    _start_ray(address)
    import ray
    from ray import tune

    path = out / RAY_DIR / "search"
    printer = _Lines(spec.samples, 0).make()
    try:
        if tune.Tuner.can_restore(str(path)):
            log(f"sweep {out}: continuing the search ({spec.samples} samples)")
            tuner = tune.Tuner.restore(str(path), trainable=_trainable(spec, out, resources), resume_unfinished=True,
                                       resume_errored=True)
        else:
            log(f"sweep {out}: {spec.search} search, {spec.samples} samples on seed {spec.seeds[0]}"
                f"{' with ASHA' if spec.asha else ''}, {spec.steps} steps at most each")
            if spec.search == "optuna":
                try:
                    from ray.tune.search.optuna import OptunaSearch

                    search_alg = OptunaSearch(seed=spec.seeds[0])
                except (ImportError, AssertionError):
                    raise SoftacError("--search optuna needs Optuna: pip install 'softac[ray]'") from None
            else:
                from ray.tune.search.basic_variant import BasicVariantGenerator

                search_alg = BasicVariantGenerator(random_state=spec.seeds[0])
            scheduler = None
            if spec.asha:
                from ray.tune.schedulers import ASHAScheduler

                interval = max(spec.base_config().eval_interval, 1)
                scheduler = ASHAScheduler(time_attr="step", max_t=spec.steps, reduction_factor=3,
                                          grace_period=max(interval, spec.steps // 9))
            tuner = tune.Tuner(
                _trainable(spec, out, resources),
                param_space=_tune_space(spec.space or {}),
                tune_config=tune.TuneConfig(metric=METRIC, mode="max", num_samples=spec.samples,
                                            search_alg=search_alg, scheduler=scheduler,
                                            max_concurrent_trials=max_concurrent, reuse_actors=False),
                run_config=_run_config(out, "search", [printer]))
        return _failures(tuner.fit())
    finally:
        ray.shutdown()


# ---- results --------------------------------------------------------------------------------

def trial_dirs(out: Path) -> list[Path]:
    return sorted(p for p in out.iterdir()
                  if p.is_dir() and not p.name.startswith("_") and p.name != PLOT_DIR and ".incomplete-" not in p.name
                  and (p / "config.yaml").exists())


def _threshold_crossing(evals: list[tuple[int, float]], progress: list[dict[str, str]],
                        threshold: float) -> tuple[int | None, float | None]:
    """First eval step whose mean reaches the threshold, and the run's elapsed seconds at that step."""
    for step, value in evals:
        if value >= threshold:
            times = [(float(r["step"]), float(r["time_s"])) for r in progress if r.get("time_s") not in (None, "")]
            seconds = float(np.interp(step, *zip(*times))) if times else None
            return step, seconds
    return None, None


def trial_rows(out: Path, spec: SweepSpec, threshold: float | None = None) -> list[dict[str, Any]]:
    from softac.logs import read_csv

    rows = []
    for run in trial_dirs(out):
        config = yaml.safe_load((run / "config.yaml").read_text()) or {}
        evals = _read_evals(run)
        try:
            summary = json.loads((run / "summary.json").read_text())
        except (OSError, ValueError):
            summary = {}
        progress = read_csv(run / "progress.csv")
        row: dict[str, Any] = {"trial": run.name, "seed": config.get("seed")}
        for key in spec.swept_keys():
            row[key] = config.get(key)
        row["final_eval_mean"] = evals[-1][1] if evals else None
        row["best_eval_mean"] = max(v for _, v in evals) if evals else None
        row["steps"] = summary.get("steps", int(float(progress[-1]["step"])) if progress else 0)
        row["wall_s"] = round(summary.get("train_time_s", float(progress[-1]["time_s"]) if progress else 0.0), 1)
        # a trial ASHA stops at its last milestone can miss its summary.json: its evals show it is complete
        complete = trial_state(run) == "done" or (bool(evals) and evals[-1][0] >= spec.steps)
        row["status"] = "done" if complete else ("stopped early" if spec.asha else "incomplete")
        if threshold is not None:
            step, seconds = _threshold_crossing(evals, progress, threshold)
            row["steps_to_threshold"] = step
            row["seconds_to_threshold"] = None if seconds is None else round(seconds, 1)
            after = [v for st, v in evals if step is not None and st >= step]
            # holding matters as much as reaching (a policy that falls over again is not solved)
            row["held_threshold"] = round(sum(v >= threshold for v in after) / len(after), 3) if after else None
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
            entry["final"] = summarize(finals)
        if bests:
            entry["best"] = summarize(bests)
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
        table.append(entry)
    table.sort(key=lambda e: -(e["final"].mean if "final" in e else -math.inf))
    return table


def _fmt(x: float | None, digits: int = 1) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def markdown_table(table: list[dict[str, Any]], threshold: float | None) -> str:
    head = ["configuration", "seeds", "final eval (mean ± std)", "final 95% CI", "final IQM", "best eval (mean ± std)",
            "median steps", "median wall s", "steps/s"]
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
    pairs += [f"{k}={_value_text(v)}" for k, v in values.items()]
    cmd = ["softac", "sweep", "--env", spec.env_id, "--seeds", str(seeds), "--steps", str(spec.steps)]
    if spec.preset:
        cmd += ["--preset", spec.preset]
    if pairs:
        cmd += ["--set", *pairs]
    return " ".join(shlex.quote(part) for part in [*cmd, "--out", out])


def write_summaries(out: Path, spec: SweepSpec, threshold: float | None = None) -> list[Path]:
    """DIR/summary.csv, DIR/summary.md and DIR/plots/ from the trial run directories."""
    import csv

    from softac.checkpoint import write_atomic

    rows = trial_rows(out, spec, threshold)
    if not rows:
        return []
    columns = list(rows[0])
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
            "interquartile mean over seeds (rliable's; the plain mean below 4 seeds).", "",
            markdown_table(table, threshold), ""]
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
        from softac.plots import plot_comparison, plot_final_returns

        (out / PLOT_DIR).mkdir(exist_ok=True)
        runs = trial_dirs(out)
        written.append(plot_comparison(runs, out / PLOT_DIR / "comparison.png"))
        written.append(plot_final_returns(runs, out / PLOT_DIR / "final_returns.png"))
    return written

