"""The Ray driver: starts (or joins) Ray, runs the grid or the search with Tune, prints progress lines."""

from __future__ import annotations

import contextlib
import os
import sys
import time
from pathlib import Path
from typing import Any, Iterator

from softac.errors import SoftacError
from softac.run.run_dir import run_lock, wait_released
from softac.sweep.results import SUCCESS_THRESHOLD, ended_trials, unfinished_trials, write_summaries
from softac.sweep.spec import (INSTALL_RAY, METRIC, RAY_DIR, SHARED_DIR_HINT, SPEC_FILE, SweepSpec, grid_trials,
                               planned_trials, prepare_out_dir, search_trial_name, validate)
from softac.sweep.trial import run_trial, trial_state

# a trial whose process is lost (its node died, it was killed by a signal) is retried this many times, each
# retry continuing from the run's last checkpoint (Tune's FailureConfig.max_failures); `--max-retries`
MAX_RETRIES = 3
# while a sweep runs, its summary (summary.csv, summary.md, plots/) is rewritten after trials end, at most this
# often: a long sweep shows its finished trials without waiting for the last one, and a sweep of many short
# trials does not spend its driver's time on plots
SUMMARY_REFRESH_S = 30.0


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
    os.environ.setdefault("TUNE_PRINT_ALL_TRIAL_ERRORS", "0")  # a lost trial gets one line (_Lines), not a traceback
    # Ray's workers SIGKILL their child processes when they exit, which cut a stopped trial's checkpoint short
    # (measured: a peer trial killed while writing it, its last 8k steps lost). Without that, a trial whose worker
    # ends gets SIGTERM (trial.py's PR_SET_PDEATHSIG), checkpoints and exits, and the driver waits for it
    # (_wait_for_trials). The workers of a local Ray inherit this; a cluster's take it from where `ray start` ran.
    # (Ray's kill of a worker's process group does not reach the trial: trial.py starts it in its own session.)
    os.environ.setdefault("RAY_kill_child_processes_on_worker_exit", "false")
    kwargs: dict[str, Any] = {"include_dashboard": False, "logging_level": logging.ERROR, "log_to_driver": False}
    try:
        if address:
            ray.init(address=address, **kwargs)
        else:
            # "local": a Ray of its own even where `ray start` runs on this machine (ray.init() would join that one)
            ray.init(address="local", num_cpus=local_cpus(), **kwargs)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        where = f"the Ray cluster at {address}" if address else "a local Ray"
        raise SoftacError(f"cannot start {where}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}"
                          ) from None
    _shorten_ray_error_messages()
    return ray


def local_cpus() -> int:
    """The CPUs a local Ray offers trials: those this process may run on, so a sweep started under `taskset -c 0`
    runs one 1-CPU trial at a time on that CPU instead of several side by side on it (the machine's count where
    the OS has no affinity API)."""
    from softac.base.cpus import usable_cpus

    return len(usable_cpus()) or os.cpu_count() or 1


def _shorten_ray_error_messages() -> None:
    """Ray's driver prints each error the cluster publishes (a lost raylet: its last 20 log lines) to stdout;
    the sweep keeps the first line, on stderr, and says what it does about it in its own lines."""
    from ray._private import worker

    original = getattr(worker, "print_to_stdstream", None)
    if original is None or getattr(original, "softac", False):
        return

    def first_line(data: dict, ignore_prefix: bool) -> None:
        if data.get("pid") != "raylet":
            return original(data, ignore_prefix)
        for message in data.get("lines", []):
            print(f"softac: Ray: {str(message).strip().splitlines()[0] if str(message).strip() else ''}",
                  file=sys.stderr, flush=True)

    first_line.softac = True
    worker.print_to_stdstream = first_line


def _read_bytes(path: str) -> bytes | None:
    try:
        return Path(path).read_bytes()
    except OSError:
        return None


def _check_nodes_see(out: Path, timeout_s: float = 60.0, log=lambda *a: None) -> None:
    """Every live node must see the sweep directory, and the same one (a node's own local copy at that path would
    scatter the runs): a task pinned to each node reads DIR/sweep.json and compares it with the driver's. A node
    that does not fails the sweep here, in one line, before any trial starts; one that does not answer within
    `timeout_s` is named in a warning (its trials would still fail in seconds: trial.run_trial checks too)."""
    import ray
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    expected = (out / SPEC_FILE).read_bytes()
    nodes = {n["NodeID"]: n.get("NodeManagerHostname", "?") for n in ray.nodes() if n.get("Alive")}
    read = ray.remote(num_cpus=0)(_read_bytes)
    refs = {read.options(scheduling_strategy=NodeAffinitySchedulingStrategy(node, soft=False)).remote(
        str(out / SPEC_FILE)): node for node in nodes}
    ready, late = ray.wait(list(refs), num_returns=len(refs), timeout=timeout_s)
    blind = []
    for ref in ready:
        try:
            if ray.get(ref) != expected:
                blind.append(refs[ref])
        except ray.exceptions.RayError:  # the node went away meanwhile: as one that did not answer
            late.append(ref)
    if blind:
        which = ", ".join(f"node {node[:12]} on {nodes[node]}" for node in blind)
        raise SoftacError(f"{which} {'does' if len(blind) == 1 else 'do'} not see the sweep directory {out} "
                          f"({len(nodes) - len(blind)} of {len(nodes)} nodes do); {SHARED_DIR_HINT}")
    for ref in late:
        log(f"softac: node {refs[ref][:12]} on {nodes[refs[ref]]} did not answer within {timeout_s:.0f} s; "
            f"its trials check {out} themselves")


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
    """Plain progress lines from Tune's callback hooks (Ray's own tables are switched off), and the summary
    so far after trials end."""

    def __init__(self, spec: SweepSpec, total: int, ended: set[str], max_retries: int, refresh):
        # `ended`: the run names of the trials that ended before this driver started (a resumed sweep), so that
        # "[k/N]" counts the sweep's trials, and a trial Tune runs again after it finished counts once
        self.spec, self.total, self.ended, self.max_retries = spec, total, set(ended), max_retries
        self.refresh = refresh  # writes the summary so far (returns the paths written)
        self.pending, self.refreshed_at = False, None

    @property
    def done(self) -> int:
        return len(self.ended)

    def trial_ended(self, trial: Any) -> None:
        config = trial.config or {}
        name = config["trial"]["name"] if "trial" in config else search_trial_name(trial.trial_id, self.spec.seeds[0])
        if name not in self.ended:
            self.ended.add(name)
            self.pending = self.done < self.total  # (the last one is summarised when the sweep ends)

    def refresh_if_due(self) -> None:
        """The summary so far, once a trial has ended since the last one and SUMMARY_REFRESH_S has passed;
        a summary that cannot be written now is said in a line and left to the end of the sweep."""
        now = time.monotonic()
        if not self.pending or (self.refreshed_at is not None and now - self.refreshed_at < SUMMARY_REFRESH_S):
            return
        self.pending, self.refreshed_at = False, now
        try:
            paths = self.refresh()
        except Exception as error:  # noqa: BLE001 (the trials go on; the final summary says what is wrong)
            print(f"softac: could not write the summary so far: {type(error).__name__}: {error}", file=sys.stderr,
                  flush=True)
            return
        if paths:
            print(f"  summary so far ({self.done} of {self.total} trials ended): {paths[0].parent}/summary.md",
                  file=sys.stderr, flush=True)

    def make(self):
        from ray.tune import Callback

        lines = self

        class Printer(Callback):
            def on_step_end(self, iteration, trials, **info):
                lines.refresh_if_due()

            def on_trial_result(self, iteration, trials, trial, result, **info):
                if "trial_error" not in result:
                    print(f"  {_trial_label(trial)}: step {result.get('step')}, "
                          f"eval {result.get(METRIC, float('nan')):.1f}", file=sys.stderr, flush=True)

            def on_trial_complete(self, iteration, trials, trial, **info):
                lines.trial_ended(trial)
                error = (trial.last_result or {}).get("trial_error")
                what = f"FAILED {error}" if error else f"finished {_trial_label(trial)}"
                print(f"[{lines.done}/{lines.total}] {what}", file=sys.stderr, flush=True)

            def on_trial_recover(self, iteration, trials, trial, **info):  # lost; Tune starts it again
                print(f"  {_trial_label(trial)}: lost ({_last_error(trial)}); retry "
                      f"{trial.num_failures} of {lines.max_retries}, from its last checkpoint", file=sys.stderr,
                      flush=True)

            def on_trial_error(self, iteration, trials, trial, **info):  # lost once more than retried
                lines.trial_ended(trial)
                print(f"[{lines.done}/{lines.total}] FAILED {_trial_label(trial)} after {lines.max_retries} "
                      f"retries: {_last_error(trial)}", file=sys.stderr, flush=True)

        return Printer()


def _last_error(trial: Any) -> str:
    """The latest failure of a trial, from the error file Tune appends each one to ("Failure # N ...")."""
    try:
        text = Path(trial.error_file).read_text()
    except (OSError, TypeError):
        return "no error recorded"
    return _error_line(text.rsplit("Failure # ", 1)[-1].split("\n", 1)[-1])


def _error_line(error: BaseException | str | None) -> str:
    """One line for what ended a trial's attempt: ours (TrialLost) names the trial's process and log; Ray's
    (a lost node or worker) gets the line that says what happened, without Ray's traceback."""
    if error is None:
        return "no error recorded"
    text = error if isinstance(error, str) else str(getattr(error, "cause", None) or error)
    lines = [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.startswith((" ", "Traceback"))]
    for line in lines:
        if "TrialLost:" in line:
            return line.split("TrialLost:", 1)[1].strip()
    named = [ln for ln in lines if "died" in ln.lower() or "node" in ln.lower() or "Error" in ln]
    return (named or lines or [type(error).__name__])[-1][:300]


def _trial_label(trial: Any) -> str:
    config = trial.config or {}
    return config["trial"]["name"] if "trial" in config else f"trial={trial.trial_id}"


def run_sweep(spec: SweepSpec, out: Path, address: str | None = None, cpus_per_trial: float = 1.0,
              max_concurrent: int | None = None, threshold: float | None = None, gpus_per_trial: float = 0.0,
              success_threshold: float = SUCCESS_THRESHOLD, max_retries: int = MAX_RETRIES,
              log=lambda *a: print(*a, file=sys.stderr, flush=True)) -> dict[str, Any]:
    """Run (or continue) a sweep; returns {'trials', 'unfinished', 'failed', 'files'}. A trial whose process is
    lost (its node died, a signal killed it) is retried up to `max_retries` times from its last checkpoint."""
    validate(spec)
    if cpus_per_trial <= 0:
        raise SoftacError("--cpus-per-trial must be > 0")
    if max_retries < 0:
        raise SoftacError("--max-retries must be >= 0")
    if gpus_per_trial < 0:
        raise SoftacError("--gpus-per-trial must be >= 0")
    resources = {"cpu": cpus_per_trial, **({"gpu": gpus_per_trial} if gpus_per_trial else {})}
    _require_ray()
    if not address and os.environ.get("RAY_ADDRESS"):  # as `ray job submit` sets it for the driver
        address = os.environ["RAY_ADDRESS"]
        log(f"softac: joining the Ray cluster at {address} (from RAY_ADDRESS; unset it for a local Ray)")
    if address:
        _check_reachable(address)
    with run_lock(out, "sweep"):  # one driver per sweep directory; each trial's run has its own lock
        prepare_out_dir(out, spec)
        out = out.resolve()
        failed: list[str] = []

        def summarise() -> list[Path]:
            return write_summaries(out, spec, threshold, success_threshold)

        if spec.search:
            if unfinished_trials(out, spec):
                failed = _run_search(spec, out, address, resources, max_concurrent, max_retries, log, summarise)
            else:
                log(f"sweep {out}: all {spec.samples} sampled trials are finished")
        else:
            trials = grid_trials(spec)
            todo = [t for t in trials if trial_state(out / t["name"], spec.steps) != "done"]
            log(f"sweep {out}: {len(trials)} trial{'s' * (len(trials) != 1)} ({len(trials) - len(todo)} already "
                f"finished), {spec.framework} on {spec.env_id}, {spec.steps} steps each")
            if todo:
                failed = _run_grid(spec, todo, len(trials), out, address, resources, max_concurrent, max_retries,
                                   log, summarise)
        files = summarise()
    for path in files:
        log(f"wrote {path}")
    unfinished = unfinished_trials(out, spec)
    return {"trials": planned_trials(spec), "unfinished": unfinished, "failed": failed, "files": files}


def _run_config(out: Path, name: str, callbacks: list, max_retries: int) -> Any:
    from ray import tune

    return tune.RunConfig(name=name, storage_path=str(out / RAY_DIR), verbose=0, callbacks=callbacks,
                          failure_config=tune.FailureConfig(max_failures=max_retries))


def _connect(address: str | None, out: Path, log) -> None:
    _start_ray(address)
    if address:  # the driver may run elsewhere than the trials: every node must see DIR
        _check_nodes_see(out, log=log)


def _trainable(spec: SweepSpec, out: Path, resources: dict[str, float]):
    """Ray reserves `resources` per trial; with a GPU, Ray sets CUDA_VISIBLE_DEVICES, which the trial inherits."""
    from ray import tune

    return tune.with_resources(tune.with_parameters(run_trial, spec=spec.to_dict(), out=str(out),
                                                    cpus=resources["cpu"]), resources)


def _failures(results: Any) -> list[str]:
    failed = []
    for result in results:
        if result.error is not None:  # lost more often than retried (trial.TrialLost), or Ray's own error
            line = _error_line(result.error)
            name = ((result.config or {}).get("trial") or {}).get("name")
            failed.append(line if not name or line.startswith(name) else f"{name}: {line}")
        elif (result.metrics or {}).get("trial_error"):
            failed.append(result.metrics["trial_error"])
    return failed


def _run_grid(spec: SweepSpec, todo: list[dict[str, Any]], total: int, out: Path, address: str | None,
              resources: dict[str, float], max_concurrent: int | None, max_retries: int, log,
              summarise) -> list[str]:
    import ray
    from ray import tune

    printer = _Lines(spec, total, ended_trials(out, spec), max_retries, summarise).make()
    try:
        _connect(address, out, log)
        tuner = tune.Tuner(
            _trainable(spec, out, resources),
            param_space={"trial": tune.grid_search(todo)},
            tune_config=tune.TuneConfig(max_concurrent_trials=max_concurrent, reuse_actors=False),
            run_config=_run_config(out, f"grid-{time.strftime('%Y%m%d-%H%M%S')}", [printer], max_retries))
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
                max_concurrent: int | None, max_retries: int, log, summarise) -> list[str]:
    import ray
    from ray import tune

    path = out / RAY_DIR / "search"
    printer = _Lines(spec, spec.samples, ended_trials(out, spec), max_retries, summarise).make()
    try:
        _connect(address, out, log)
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
                run_config=_run_config(out, "search", [printer], max_retries))
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
