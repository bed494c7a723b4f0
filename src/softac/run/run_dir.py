"""The run directory: its layout, atomic writes, the config and summary files, the checks before writing,
and where a checkpoint sits in a run. (What one training call writes is the loop's `RunWriter`.)

    RUN/config.yaml         the resolved config, library versions, machine facts
    RUN/progress.csv        a row every log_interval steps (losses, alpha, fps, recent return)
    RUN/episodes.csv        a row per finished training episode
    RUN/eval.csv            a row per deterministic evaluation
    RUN/tb/                 TensorBoard events of the same scalars
    RUN/checkpoints/last    the latest state (with the replay buffer and the envs), to resume from
    RUN/checkpoints/best    the best evaluation's networks, for predict/eval/video
    RUN/summary.json        written when a training call ends normally
    RUN/.lock               held (an OS lock) by the one process that writes the run (`run_lock`)

A crash at any moment leaves each file either whole and old or whole and new (`write_atomic`), a new
run never writes over another run's checkpoints (`RunState.check_may_write`), and two processes never write one
run (or one sweep directory) at the same time (`run_lock`).
"""

from __future__ import annotations

import contextlib
import copy
import json
import os
import secrets
import socket
import sys
import time
from pathlib import Path
from typing import Any, Iterator

import yaml

from softac.errors import SoftacError

CHECKPOINTS = "checkpoints"
LOCK = ".lock"


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


# what a segment records; a change of any starts a new segment (cpus_shared is the segment's own, never top-level)
SEGMENT_FACTS = ("host", "pid", "machine", "cpus", "cpus_shared", "versions", "resolved_matmul_dtype")


def write_config(run_dir: Path, config: dict[str, Any], extra: dict[str, Any], start_step: int = 0,
                 continuing: bool = False) -> None:
    """RUN/config.yaml: the config, then `extra` (versions, resolved values) and the machine it ran on, and
    `segments`: one entry for each stretch of training (its first step, when, where, on what: a resumed run
    may go on under other versions, on another machine or CPU count; `cpus_shared: true` where it was pinned to
    CPUs another pinned softac process held, softac.base.cpus.cpus_shared). When `continuing` a run, the config
    keys are updated, the top-level record (versions, cpus, machine) stays the run's first, and a segment is
    added unless the same process goes on training on the same machine."""
    from softac.base.cpus import cpus_shared, machine_description

    data = dict(config)
    data.update(extra)
    data["machine"] = machine_description()
    segment = {"start_step": start_step, "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
               "host": socket.gethostname(), "pid": os.getpid(),
               **copy.deepcopy({key: data[key] for key in SEGMENT_FACTS if key in data})}  # no YAML aliases
    if cpus_shared():  # pinned beside another pinned softac process: its wall time is not an undisturbed one's
        segment["cpus_shared"] = True
    previous = _read_yaml(run_dir / "config.yaml") if continuing else {}
    segments = list(previous.get("segments") or [])
    if previous and not segments:  # a run from before segments were kept: its record is the first one
        segments = [{"start_step": 0, **{key: previous[key] for key in SEGMENT_FACTS if key in previous}}]
    for key in ("versions", "cpus", "machine", "resolved_matmul_dtype"):
        if key in previous:
            data[key] = previous[key]
    if not segments or any(segments[-1].get(key) != segment.get(key) for key in SEGMENT_FACTS):
        segments.append(segment)
    data["segments"] = segments
    write_atomic(run_dir / "config.yaml", yaml.safe_dump(data, sort_keys=False).encode())


def _read_yaml(path: Path) -> dict[str, Any]:
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError):
        return {}
    return data if isinstance(data, dict) else {}


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


# ---- one writer at a time -------------------------------------------------------------------

class RunLocked(SoftacError):
    """The run (or sweep) directory is being written by another process."""


HOLDER_WAIT_POLLS = 200  # x 10 ms: how long a refused process waits for a fresh holder to write its pid
_held: dict[str, list] = {}  # this process's run locks: resolved directory -> [fd, depth]


def _holder(fd: int) -> str:
    """Who holds the lock, from what the holder wrote into the lock file."""
    try:
        info = json.loads(os.pread(fd, 4096, 0) or b"{}")
    except (OSError, ValueError):
        info = {}
    if not isinstance(info, dict) or "pid" not in info:
        return "another process"
    where = f" on {info['host']}" if info.get("host") and info["host"] != socket.gethostname() else ""
    since = f", since {info['since']}" if info.get("since") else ""
    return f"pid {info['pid']}{where}{since}"


def holder(directory: Path) -> str:
    """Who holds DIRECTORY's lock (or held it last), as the lock file names them: "pid N on HOST, since T"."""
    try:
        fd = os.open(directory / LOCK, os.O_RDONLY)
    except OSError:
        return "another process"
    try:
        return _holder(fd)
    finally:
        os.close(fd)


def _lock_file(directory: Path, what: str) -> int:
    """An open descriptor of DIRECTORY/.lock holding its exclusive lock (fcntl.flock: the kernel drops it
    when the holder exits, however it exits, so a process killed with -9 never blocks the next one)."""
    import fcntl

    path = directory / LOCK
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            # the holder writes its pid just after it locks: refused in between, give it a moment to name itself
            for _ in range(HOLDER_WAIT_POLLS):
                if holder != "another process":
                    break
                time.sleep(0.01)
                holder = _holder(fd)
            os.close(fd)
            raise RunLocked(f"{directory} is being written by {holder} (another softac {what}); wait for it "
                            f"to end, or pick another directory") from None
        except OSError as exc:  # a filesystem without locks: say so rather than write unguarded
            os.close(fd)
            raise SoftacError(f"cannot lock {path}: {exc.strerror or exc} (softac needs file locks to keep one "
                              "writer per run)") from None
        try:  # the file we locked must still be the one at the path (a holder may have removed it meanwhile)
            if os.stat(path).st_ino == os.fstat(fd).st_ino:
                return fd
        except FileNotFoundError:
            directory.mkdir(parents=True, exist_ok=True)
        os.close(fd)


@contextlib.contextmanager
def run_lock(directory: str | Path, what: str = "run") -> Iterator[Path]:
    """Hold DIRECTORY's lock while writing it: a second process that tries gets a one-line RunLocked (exit 2)
    naming the holder's pid. Re-entrant within a process (the CLI takes it, then learn() again). The directory
    is made if missing, and removed again on the way out if nothing but the lock was written into it (a run
    refused before it started leaves nothing behind: a lock file it made, and the directory if it made that).
    A lock file next to other files stays, emptied (it names its holder only while held). Works across nodes
    where the shared filesystem supports locks (NFSv4, Lustre, GPFS, CephFS)."""
    directory = Path(directory)
    key = str(directory.resolve())
    if key in _held:
        _held[key][1] += 1
        try:
            yield directory
        finally:
            _held[key][1] -= 1
        return
    if directory.exists() and not directory.is_dir():
        raise SoftacError(f"{directory} exists and is not a directory")
    created = not directory.exists()
    lock_was_there = (directory / LOCK).exists()
    try:
        directory.mkdir(parents=True, exist_ok=True)
        fd = _lock_file(directory, what)
    except OSError as exc:
        raise SoftacError(f"cannot create {what} directory {directory}: {exc.strerror or exc}") from None
    info = {"pid": os.getpid(), "host": socket.gethostname(), "since": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "argv": sys.argv}
    with contextlib.suppress(OSError):
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(info).encode(), 0)
    _held[key] = [fd, 1]
    try:
        yield directory
    finally:
        del _held[key]
        try:  # nothing written: leave the directory as it was (still locked: nobody else can have written)
            if not lock_was_there and [p.name for p in directory.iterdir()] == [LOCK]:
                (directory / LOCK).unlink()
                if created:
                    directory.rmdir()
            else:  # the file names its holder only while held
                os.ftruncate(fd, 0)
        except OSError:
            pass
        finally:
            os.close(fd)  # releases the lock


def wait_released(directory: Path, timeout_s: float) -> bool:
    """Wait until no process holds DIRECTORY's lock (True), or `timeout_s` passed (False). A directory without
    a lock file was never locked."""
    import fcntl

    deadline = time.monotonic() + timeout_s
    while True:
        try:
            fd = os.open(directory / LOCK, os.O_RDWR)
        except OSError:
            return True
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            fcntl.flock(fd, fcntl.LOCK_UN)
            return True
        except BlockingIOError:
            if time.monotonic() >= deadline:
                return False
        except OSError:  # a filesystem without locks: nothing to wait for
            return True
        finally:
            os.close(fd)
        time.sleep(0.2)


def holds_lock(directory: Path) -> bool:
    """Whether this process holds DIRECTORY's lock."""
    return str(Path(directory).resolve()) in _held
