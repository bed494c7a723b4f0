"""One trial: the `softac train` (or peer) process that a Ray trial starts, pins to its CPUs and watches,
reporting each new evaluation to Tune."""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

from softac.config.sac_config import SACConfig
from softac.base.cpus import claim_cpus, trial_settings_env
from softac.peers import PEERS
from softac.run.run_dir import holder, wait_released
from softac.sweep.spec import (LOG_DIR, METRIC, SHARED_DIR_HINT, SPEC_FILE, SweepSpec, search_trial_name,
                               value_text)

# how long a trial waits for the lock of its run directory, held by an earlier attempt's process that is still
# writing its checkpoint (a stopped driver's trial), or by one on a lost node until the filesystem frees its lock
# (NFSv4: when the node's lease expires, 90 s by default)
LOCK_WAIT_S = 300.0


class TrialLost(RuntimeError):
    """The trial's process ended without finishing and without an error of its own: killed by a signal (a lost
    node, the OOM killer, `kill -9`) or stopped by someone other than the sweep. Raised, so that Tune retries the
    trial (FailureConfig.max_failures), which continues from the run's last checkpoint. A run's own error (exit 2
    or 3: bad settings, a diverging run) is reported instead and not retried: it would fail again."""


def trial_state(run: Path, steps: int | None = None) -> str:
    """'done', 'partial' (a checkpoint to continue from) or 'new', from the run directory alone; `steps`: the
    sweep's budget, where it was raised past the run's own (a run finished at its old budget is then partial)."""
    try:
        summary = json.loads((run / "summary.json").read_text())
        if summary.get("stopped_early") or summary["steps"] >= max(summary["total_steps"], steps or 0):
            return "done"
    except (OSError, ValueError, KeyError, TypeError):
        pass
    return "partial" if (run / "checkpoints" / "last").exists() else "new"


def sweep_settings(spec: SweepSpec) -> list[str]:
    """A peer that runs at the sweep's settings gets its --preset and --set (softac.peers)."""
    if PEERS[spec.framework].settings != "sweep":
        return []
    return [*(["--preset", spec.preset] if spec.preset else []), *(["--set", *spec.overrides] if spec.overrides else [])]


def trial_command(spec: SweepSpec, base: SACConfig, trial: dict[str, Any], run: Path) -> list[str]:
    # one token: a negative target (Pendulum's -200) must not read as an option
    target = [] if spec.target_return is None else [f"--target-return={float(spec.target_return)!r}"]
    if spec.target_success is not None:
        target.append(f"--target-success={float(spec.target_success)!r}")
    if spec.framework != "softac":
        # the same command continues a peer's run from its last checkpoint
        return [sys.executable, "-m", "softac.peers", "run", spec.framework, "--env", spec.env_id,
                "--seed", str(trial["seed"]), "--steps", str(spec.steps), "--out", str(run),
                "--eval-interval", str(base.eval_interval), "--eval-episodes", str(base.eval_episodes),
                "--log-interval", str(base.log_interval), "--checkpoint-interval", str(base.checkpoint_interval),
                *(["--action-repeat", str(base.action_repeat)] if base.action_repeat != 1 else []),
                *sweep_settings(spec), *target]
    if trial_state(run, spec.steps) == "partial":  # also a run finished before the sweep's budget was raised
        return [sys.executable, "-m", "softac", "train", "--resume", str(run), "--total-steps", str(spec.steps),
                "--no-progress", *target]
    pairs = list(spec.overrides) + [f"{k}={value_text(v)}" for k, v in trial["values"].items()]
    cmd = [sys.executable, "-m", "softac", "train", "--env", spec.env_id, "--seed", str(trial["seed"]),
           "--steps", str(spec.steps), "--out", str(run), "--no-progress", *target]
    if spec.preset:
        cmd += ["--preset", spec.preset]
    if pairs:
        cmd += ["--set", *pairs]
    return cmd


def trial_process_env(threads: int, cpus: list[int], shared: bool = False) -> dict[str, str]:
    """The environment of a trial's process: thread counts for the libraries that read them (PyTorch for the
    peers, OpenMP, MKL; XLA takes its own from the CPU affinity), and its CPUs and parent, which the process
    applies itself when it starts (softac.base.cpus.adopt_trial_settings)."""
    env = dict(os.environ)
    env["SOFTAC_THREADS"] = env["OMP_NUM_THREADS"] = env["MKL_NUM_THREADS"] = str(threads)
    env.update(trial_settings_env(cpus, os.getpid(), shared))
    return env


def read_evals(run: Path, column: str = "mean_return") -> list[tuple[int, float]]:
    """(step, value) of each evaluation in eval.csv that has `column` (mean_return, or success_rate)."""
    from softac.run.csv_logs import read_csv

    out = []
    for row in read_csv(run / "eval.csv"):
        with contextlib.suppress(ValueError, TypeError, KeyError):  # (a run written before the column: none)
            out.append((int(float(row["step"])), float(row[column])))
    return out


def node_label() -> str:
    """This process's Ray node (its id's first 12 characters, as `ray status` and the dashboard show them) and
    host, for the trial's log: which node ran which attempt."""
    import ray

    return f"node {ray.get_runtime_context().get_node_id()[:12]} on {socket.gethostname()}"


def run_trial(params: dict[str, Any], spec: dict[str, Any], out: str, cpus: float) -> None:
    """A Ray Tune function trainable: one trial = one `softac train` process, its evals reported to Tune."""
    from ray import tune

    sweep = SweepSpec.from_dict(spec)
    base = sweep.base_config()
    if sweep.search:
        trial = {"name": search_trial_name(tune.get_context().get_trial_id(), sweep.seeds[0]), "seed": sweep.seeds[0],
                 "values": {k: params[k] for k in sweep.space or {}}}
    else:
        trial = params["trial"]
    root = Path(out)
    run = root / trial["name"]
    if not (root / SPEC_FILE).exists():  # checked before anything is written there: nothing lands on a local disk
        tune.report({METRIC: -math.inf, "step": 0, "trial_error": (
            f"{trial['name']}: {node_label()} does not see the sweep directory {root} (no {SPEC_FILE} there); "
            f"{SHARED_DIR_HINT}")})
        return
    if trial_state(run, sweep.steps) == "done":
        return
    if not wait_released(run, LOCK_WAIT_S):
        raise TrialLost(f"{trial['name']}: its run directory is still locked by {holder(run)} after "
                        f"{LOCK_WAIT_S:.0f} s")
    if sweep.framework != "softac" and run.exists() and trial_state(run) == "new":
        # a peer's run stopped before its first checkpoint cannot continue: keep it aside, start again
        n = 1
        while run.with_name(f"{run.name}.incomplete-{n}").exists():
            n += 1
        os.replace(run, run.with_name(f"{run.name}.incomplete-{n}"))
    (root / LOG_DIR).mkdir(parents=True, exist_ok=True)
    log_path = root / LOG_DIR / f"{trial['name']}.log"
    previous = read_evals(run)  # a resumed trial has reported these already
    reported = {step for step, _ in previous}
    best = max((v for _, v in previous), default=-math.inf)
    cmd = trial_command(sweep, base, trial, run)
    threads = max(1, int(cpus))
    where = node_label()
    pinned, locks, shared = claim_cpus(threads)
    with open(log_path, "a") as log, contextlib.ExitStack() as held:
        for lock in locks:
            held.callback(lock.close)
        shown = f"CPUs {pinned}{' shared: none free' if shared else ''}, " if pinned else ""
        log.write(f"$ {' '.join(cmd)}  ({shown}{where})\n")
        log.flush()
        # a session of its own: Ray starts each worker in its own process group and SIGKILLs the group when
        # Tune force-stops the trial (5 s after asking it to stop), which killed a trial still writing its
        # checkpoint or winding down; outside that group it ends through its own SIGTERM path (PDEATHSIG)
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=trial_process_env(threads, pinned, shared),
                                start_new_session=True)
        code = None
        try:
            while True:
                code = proc.poll()
                for step, value in read_evals(run):
                    if step not in reported:
                        reported.add(step)
                        best = max(best, value)
                        tune.report({METRIC: value, "best_eval_mean_return": best, "step": step})
                if code is not None:
                    break
                with contextlib.suppress(subprocess.TimeoutExpired):
                    proc.wait(1.0)  # back at once when the trial ends (its slot frees), else once a second
        finally:
            if proc.poll() is None:  # the trial was stopped (ASHA, Ctrl-C): the run checkpoints and exits 130
                proc.terminate()
                try:
                    proc.wait(60)
                except subprocess.TimeoutExpired:
                    proc.kill()
    if code is not None and (code < 0 or (code == 130 and trial_state(run, sweep.steps) != "done")):
        # ended by a signal the sweep did not send (it stops a trial in the `finally` above, where code stays None)
        how = f"killed by {signal.Signals(-code).name}" if code < 0 else "stopped (SIGTERM or SIGINT)"
        raise TrialLost(f"{trial['name']}: its process was {how} (log: {log_path})")
    if code not in (0, 130, None):
        # reported, not raised: a raised error makes Tune print a traceback; this way the user gets one line
        lines = [ln for ln in log_path.read_text().splitlines() if ln.strip()]
        tune.report({METRIC: best, "step": max(reported, default=0),
                     "trial_error": f"{trial['name']} exited {code}: {lines[-1] if lines else ''} (log: {log_path})"})
