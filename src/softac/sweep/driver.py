"""The Ray driver: starts (or joins) Ray, runs the grid or the search with Tune, prints progress lines."""

from __future__ import annotations

import contextlib
import os
import sys
import time
from pathlib import Path
from typing import Any, Iterator

from softac.errors import SoftacError
from softac.rundir import run_lock, wait_released
from softac.sweep.results import SUCCESS_THRESHOLD, unfinished_trials, write_summaries
from softac.sweep.spec import (INSTALL_RAY, METRIC, RAY_DIR, SweepSpec, grid_trials, planned_trials, prepare_out_dir,
                               validate)
from softac.sweep.trial import run_trial, trial_state


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
    # Ray's workers SIGKILL their child processes when they exit, which cut a stopped trial's checkpoint short
    # (measured: a peer trial killed while writing it, its last 8k steps lost). Without that, a trial whose worker
    # ends gets SIGTERM (trial.py's PR_SET_PDEATHSIG), checkpoints and exits, and the driver waits for it
    # (_wait_for_trials). The workers of a local Ray inherit this; a cluster's take it from where `ray start` ran.
    os.environ.setdefault("RAY_kill_child_processes_on_worker_exit", "false")
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


@contextlib.contextmanager
def _sigterm_as_ctrl_c() -> Iterator[None]:
    """SIGTERM (a scheduler's stop, `kill`) stops the sweep as Ctrl-C does: Tune stops the trials, they
    checkpoint, the driver exits 130 with the resume command. Ray's driver otherwise dies on it (exit 1)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: os.kill(os.getpid(), signal.SIGINT))
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


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
              success_threshold: float = SUCCESS_THRESHOLD, log=lambda *a: print(*a, file=sys.stderr, flush=True)) -> dict[str, Any]:
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
    with run_lock(out, "sweep"):  # one driver per sweep directory; each trial's run has its own lock
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
            log(f"sweep {out}: {len(trials)} trial{'s' * (len(trials) != 1)} ({len(trials) - len(todo)} already "
                f"finished), {spec.framework} on {spec.env_id}, {spec.steps} steps each")
            if todo:
                failed = _run_grid(spec, todo, len(trials), out, address, resources, max_concurrent, log)
        files = write_summaries(out, spec, threshold, success_threshold)
    for path in files:
        log(f"wrote {path}")
    unfinished = unfinished_trials(out, spec)
    return {"trials": planned_trials(spec), "unfinished": unfinished, "failed": failed, "files": files}


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
        with _sigterm_as_ctrl_c():
            return _failures(tuner.fit())
    finally:
        ray.shutdown()
        _wait_for_trials([out / t["name"] for t in todo], log)


def _wait_for_trials(runs: list[Path], log, timeout_s: float = 300.0) -> None:
    """After Ray has stopped: wait while a stopped trial's process still writes its checkpoint (it holds its
    run's lock until it exits), so that the driver ends after its trials and a resume finds their checkpoints."""
    deadline = time.monotonic() + timeout_s
    for run in runs:
        if not wait_released(run, max(deadline - time.monotonic(), 0.0)):
            log(f"softac: {run} is still being written by its trial's process after {timeout_s:.0f} s; "
                "leaving it to finish")


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
        with _sigterm_as_ctrl_c():
            return _failures(tuner.fit())
    finally:
        ray.shutdown()
        _wait_for_trials(sorted(p.parent for p in out.glob("*/config.yaml")), log)


def _tune_space(space: dict[str, dict[str, list[Any]]]) -> dict[str, Any]:
    from ray import tune

    out = {}
    for key, dist in space.items():
        kind, values = next(iter(dist.items()))
        out[key] = {"loguniform": lambda v: tune.loguniform(*v), "uniform": lambda v: tune.uniform(*v),
                    "randint": lambda v: tune.randint(*v), "choice": tune.choice}[kind](values)
    return out
