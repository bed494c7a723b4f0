"""The run directory: its layout, atomic writes, the config and summary files, the checks before writing,
and where a checkpoint sits in a run. (What one training call writes is the trainer's `RunWriter`.)

    RUN/config.yaml         the resolved config, library versions, machine facts
    RUN/progress.csv        a row every log_interval steps (losses, alpha, fps, recent return)
    RUN/episodes.csv        a row per finished training episode
    RUN/eval.csv            a row per deterministic evaluation
    RUN/tb/                 TensorBoard events of the same scalars
    RUN/checkpoints/last    the latest state (with the replay buffer and the envs), to resume from
    RUN/checkpoints/best    the best evaluation's networks, for predict/eval/video
    RUN/summary.json        written when a training call ends normally

A crash at any moment leaves each file either whole and old or whole and new (`write_atomic`), and a new
run never writes over another run's checkpoints (`check_run_dir_for`).
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from softac.errors import SoftacError

if TYPE_CHECKING:
    from softac.runstate import RunState

CHECKPOINTS = "checkpoints"


def fsync_dir(path: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def write_atomic(path: Path, data: bytes) -> None:
    """Write under a temporary name, fsync, rename over `path`: readers see the old file or the new one."""
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def versions() -> dict[str, str]:
    """Versions of the packages a run's numbers depend on (recorded in config.yaml and checkpoints)."""
    from importlib import metadata

    out = {}
    for pkg in ("softac", "jax", "jaxlib", "optax", "numpy", "gymnasium", "mujoco"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            pass
    return out


def write_config(run_dir: Path, config: dict[str, Any], extra: dict[str, Any]) -> None:
    """RUN/config.yaml: the config, then `extra` (versions, resolved values) and the machine it ran on."""
    from softac.cpus import machine_description

    data = dict(config)
    data.update(extra)
    data["machine"] = machine_description()
    write_atomic(run_dir / "config.yaml", yaml.safe_dump(data, sort_keys=False).encode())


def write_summary(run_dir: Path, summary: dict[str, Any]) -> None:
    """RUN/summary.json: written when a training call ends normally (not when killed or interrupted)."""
    write_atomic(run_dir / "summary.json", (json.dumps(summary, indent=1) + "\n").encode())


# ---- the layout and the checks before writing ---------------------------------------------

def checkpoint_path(run: Path, name: str) -> Path:
    """RUN/checkpoints/NAME (`last` or `best`)."""
    return run / CHECKPOINTS / name


def run_of_last_checkpoint(directory: Path) -> Path | None:
    """The run whose checkpoints/last `directory` is, or None for any other checkpoint directory."""
    if directory.name == "last" and directory.parent.name == CHECKPOINTS:
        return directory.parent.parent
    return None


def holds_run(run: Path) -> bool:
    return (run / CHECKPOINTS).is_dir() and any((run / CHECKPOINTS).iterdir())


def check_new_run_dir(run: Path) -> None:
    """A new run never writes over another run's checkpoints."""
    if run.exists() and not run.is_dir():
        raise SoftacError(f"run directory {run} exists and is not a directory")
    if holds_run(run):
        raise SoftacError(f"{run} already holds a run; continue it with --resume {run} or pick another --out")


def check_run_dir_for(state: RunState, run: Path) -> None:
    """An agent writes only into a new directory or the run its state is the latest of: a loaded agent never
    writes over another run, nor rewinds its own from an older (best) checkpoint. Its own run includes one
    killed (kill -9, power loss) before its first periodic checkpoint, continued from the step-0 checkpoint."""
    if state.run_dir == run.resolve():
        return
    if state.num_steps > 0 and holds_run(run):
        raise SoftacError(f"{run} already holds a run that this agent is not the latest state of (it was loaded "
                          f"from {state.restored_from or 'elsewhere'}); train into a new directory, or load "
                          f"{checkpoint_path(run, 'last')} to continue that run")
    check_new_run_dir(run)
