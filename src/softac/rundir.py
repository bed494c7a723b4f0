"""The run directory: its layout, atomic writes, the config and summary files, the checks before writing,
and `RunWriter`, which owns everything one training call writes into it.

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
from typing import Any

import yaml

from softac.errors import RunFailed, SoftacError
from softac.logs import RunLogger

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
    data = dict(config)
    data.update(extra)
    write_atomic(run_dir / "config.yaml", yaml.safe_dump(data, sort_keys=False).encode())


def write_summary(run_dir: Path, summary: dict[str, Any]) -> None:
    """RUN/summary.json: written when a training call ends normally (not when killed or interrupted)."""
    write_atomic(run_dir / "summary.json", (json.dumps(summary, indent=1) + "\n").encode())


# ---- the checks before writing ---------------------------------------------------------

def holds_run(run: Path) -> bool:
    return (run / CHECKPOINTS).is_dir() and any((run / CHECKPOINTS).iterdir())


def check_new_run_dir(run: Path) -> None:
    """A new run never writes over another run's checkpoints."""
    if run.exists() and not run.is_dir():
        raise SoftacError(f"run directory {run} exists and is not a directory")
    if holds_run(run):
        raise SoftacError(f"{run} already holds a run; continue it with --resume {run} or pick another --out")


def check_run_dir_for(num_steps: int, own_run: Path | None, restored_from: Path | None, run: Path) -> None:
    """An agent writes only into a new directory or the run it is the latest state of (`own_run`): a loaded
    agent never writes over another run, nor rewinds its own from an older (best) checkpoint. Its own run
    includes one killed (kill -9, power loss) before its first periodic checkpoint, continued from the
    step-0 checkpoint."""
    if own_run == run.resolve():
        return
    if num_steps > 0 and holds_run(run):
        raise SoftacError(f"{run} already holds a run that this agent is not the latest state of (it was loaded "
                          f"from {restored_from or 'elsewhere'}); train into a new directory, or load "
                          f"{run / CHECKPOINTS / 'last'} to continue that run")
    check_new_run_dir(run)


# ---- what one training call writes ---------------------------------------------------------

class RunWriter:
    """The run directory of one training call: made (after the checks), its config written, its logs
    opened; checkpoints written atomically (a failed write keeps the previous one and fails the run, exit 3);
    the summary written at a normal end."""

    def __init__(self, run: Path, config: dict[str, Any], extra: dict[str, Any], resume_step: int):
        try:
            run.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise SoftacError(f"cannot create run directory {run}: {exc.strerror or exc}") from None
        self.run = run
        write_config(run, config, {"versions": versions(), **extra})
        self.logs = RunLogger(run, resume_step=resume_step)

    def has_checkpoint(self, name: str) -> bool:
        return (self.run / CHECKPOINTS / name).exists()

    def checkpoint_path(self, name: str) -> Path:
        return self.run / CHECKPOINTS / name

    def save_checkpoint(self, name: str, meta: dict[str, Any], arrays: dict[str, Any]) -> str:
        from softac import checkpoint as ckpt

        try:
            return str(ckpt.save(self.checkpoint_path(name), meta, arrays))
        except OSError as exc:
            raise RunFailed(f"could not write checkpoint {self.checkpoint_path(name)}: {exc.strerror or exc}; "
                            "the previous checkpoint is kept") from None

    def write_summary(self, summary: dict[str, Any]) -> None:
        write_summary(self.run, summary)

    def close(self) -> None:
        self.logs.close()
