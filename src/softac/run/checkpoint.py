"""Checkpoints: a directory with one .npz of arrays and a meta.json, never pickle.

Writing is atomic in effect: the arrays go to a new, uniquely named file
(written under a temporary name, fsynced, renamed), then meta.json, which
names that file and its SHA-256, replaces the old meta.json in one rename.
Only then is the previous arrays file removed. A crash at any moment leaves
either the old checkpoint or the new one, whole.

Two processes saving into one directory (two `agent.save(path)` at once) take
turns on the directory's lock, so neither removes the other's arrays, and
the last to finish wins whole; a reader that meets a save replacing the files
under it reads again (`load`).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import secrets
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from softac.errors import CheckpointError  # noqa: F401  (raised here; softac.run.checkpoint.CheckpointError, its old home)
from softac.run.run_dir import checkpoint_path, fsync_dir, write_atomic

FORMAT = "softac-checkpoint"
FORMAT_VERSION = 1
META = "meta.json"


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _write_npz(f: Any, arrays: dict[str, np.ndarray]) -> None:
    """What np.savez writes (an uncompressed zip of .npy members, read back by np.load), with the zip closed
    on every path: NumPy 1.x's savez leaves it open when a write fails (a full disk), and its finaliser
    then prints a traceback at exit."""
    zf = zipfile.ZipFile(f, "w", zipfile.ZIP_STORED, allowZip64=True)
    try:
        for key, value in arrays.items():
            with zf.open(f"{key}.npy", "w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.asarray(value), allow_pickle=False)
    finally:
        with contextlib.suppress(Exception):  # the error that matters is the one raised above
            zf.close()
        zf.fp = None  # never closed again by the finaliser


@contextlib.contextmanager
def _writing(directory: Path):
    """The checkpoint directory's own lock (flock on the directory, so a checkpoint holds no extra file),
    waited for: one save at a time, so that a save may remove every arrays file its meta.json does not name
    (those of a save killed midway) without touching another's. Where the filesystem cannot lock a directory
    (NFS), saves go on unserialised, as before."""
    import fcntl

    fd = os.open(directory, os.O_RDONLY)
    try:
        with contextlib.suppress(OSError):
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


def save(directory: str | Path, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> Path:
    """Write a checkpoint into `directory` (created if needed) atomically."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    with _writing(directory):
        return _save(directory, meta, arrays)


def _save(directory: Path, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> Path:
    name = f"arrays-{secrets.token_hex(6)}.npz"
    final = directory / name
    tmp = directory / f".{name}.tmp"
    try:
        with open(tmp, "wb") as f:
            _write_npz(f, arrays)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, final)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise
    meta = dict(meta, format=FORMAT, format_version=FORMAT_VERSION, arrays_file=name, sha256=_sha256(final))
    try:
        write_atomic(directory / META, json.dumps(meta, indent=1).encode())
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            final.unlink()
        raise
    fsync_dir(directory)
    for old in directory.glob("arrays-*.npz"):
        if old.name != name:
            with contextlib.suppress(OSError):
                old.unlink()
    for stale in [*directory.glob(".arrays-*.tmp"), *directory.glob(f".{META}.*.tmp")]:
        with contextlib.suppress(OSError):
            stale.unlink()
    return directory


def is_checkpoint(path: Path) -> bool:
    return (path / META).is_file()


def resolve(path: str | Path, which: str | None = None) -> Path:
    """A checkpoint directory from a checkpoint or a run directory.

    For a run, `which` picks checkpoints/best or checkpoints/last; by default
    best when it exists, else last.
    """
    path = Path(path)
    if not path.exists():
        raise CheckpointError(f"no such run or checkpoint: {path}")
    if which is None and is_checkpoint(path):
        return path
    order = [which] if which else ["best", "last"]
    for name in order:
        candidate = checkpoint_path(path, name)
        if is_checkpoint(candidate):
            return candidate
    if which:
        raise CheckpointError(f"{path} has no {which} checkpoint (looked for {checkpoint_path(path, which)})")
    raise CheckpointError(f"{path} holds no checkpoint (neither {META} nor checkpoints/best|last)")


def load(directory: str | Path, attempts: int = 5) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Read and verify a checkpoint; any problem is a one-line CheckpointError. A checkpoint replaced while
    it is read (`softac eval RUN` while the run saves its best) is read again."""
    directory = Path(directory)
    meta = _read_meta(directory)
    for _ in range(attempts - 1):
        try:
            return meta, _read_arrays(directory, meta)
        except CheckpointError:
            # a save that replaced the checkpoint meanwhile left a meta.json naming another arrays file
            now = _read_meta(directory)
            if now["arrays_file"] == meta["arrays_file"]:
                raise
            meta = now
    return meta, _read_arrays(directory, meta)


def arrays_bytes(directory: str | Path) -> int:
    """The size of a checkpoint's arrays file: what loading it takes in memory (an uncompressed .npz), known
    before it is read."""
    directory = Path(directory)
    try:
        return (directory / _read_meta(directory)["arrays_file"]).stat().st_size
    except OSError:
        raise CheckpointError(f"corrupt checkpoint {directory}: its arrays file is missing") from None


def _read_meta(directory: Path) -> dict[str, Any]:
    try:
        meta = json.loads((directory / META).read_text())
    except FileNotFoundError:
        raise CheckpointError(f"no checkpoint at {directory} (missing {META})") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CheckpointError(f"corrupt checkpoint {directory}: {META} is unreadable ({exc})".splitlines()[0]) from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise CheckpointError(f"{directory} is not a softac checkpoint")
    version = meta.get("format_version")
    if not isinstance(version, int) or version > FORMAT_VERSION:
        raise CheckpointError(f"checkpoint {directory} has format version {version}, newer than this softac "
                              f"reads ({FORMAT_VERSION}); upgrade softac")
    name = meta.get("arrays_file")
    if not isinstance(name, str) or "/" in name or not name.endswith(".npz"):
        raise CheckpointError(f"corrupt checkpoint {directory}: bad arrays_file in {META}")
    return meta


def _read_arrays(directory: Path, meta: dict[str, Any]) -> dict[str, np.ndarray]:
    name = meta["arrays_file"]
    arrays_path = directory / name
    if not arrays_path.is_file():
        raise CheckpointError(f"corrupt checkpoint {directory}: {name} is missing")
    if _sha256(arrays_path) != meta.get("sha256"):
        raise CheckpointError(f"corrupt checkpoint {directory}: {name} does not match its checksum")
    try:
        with np.load(arrays_path, allow_pickle=False) as npz:
            return {k: npz[k] for k in npz.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise CheckpointError(f"corrupt checkpoint {directory}: cannot read {name} ({exc})".splitlines()[0]) from None
