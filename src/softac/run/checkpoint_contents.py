"""What a checkpoint holds, put together and taken apart: the config, the env's spaces, the learner's
arrays, the run state, and (in a run's `last` checkpoint) the replay buffer and the envs' state.

`checkpoint.py` writes and reads the files; this module says what goes in them. The agent and the
training loop save through `checkpoint_parts`; `load_learner` reads just the policy (export) without
building an agent.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from softac.run import checkpoint as ckpt
from softac.replay.collector import Collector
from softac.config.sac_config import SACConfig
from softac.envs.make import SpaceInfo, check_spaces, training_env_source
from softac.errors import SoftacError
from softac.learner.learner import Learner
from softac.run.run_dir import versions
from softac.run.run_state import RunState


def checkpoint_parts(learner: Learner, run: RunState, collector: Collector | None,
                     include_buffer: bool) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The meta.json entries and the arrays of one checkpoint (format version 1)."""
    spaces = learner.spaces
    run_meta, run_arrays = run.checkpoint_parts()
    meta: dict[str, Any] = {
        "config": learner.config.to_dict(),
        "versions": versions(),
        "saved_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "spaces": {"obs_dim": spaces.obs_dim, "act_dim": spaces.act_dim,
                   "low": spaces.low.tolist(), "high": spaces.high.tolist()},
        **run_meta,
    }
    arrays = {**learner.arrays(), **run_arrays}
    if collector is not None:
        collector_meta, collector_arrays = collector.checkpoint_parts(include_buffer)
        meta.update(collector_meta)
        arrays.update(collector_arrays)
    else:
        meta.update(has_buffer=False, has_envs=False)
    return meta, arrays


def saved_config(meta: dict[str, Any], where: Path | str, **overrides: Any) -> SACConfig:
    """The config a checkpoint was trained with; `overrides` (None values skipped) replace settings that do
    not change what the agent computes (device, env_workers, loggers)."""
    if "peer" in meta:  # softac.peers writes its peers' checkpoints in softac's format, to resume their runs
        raise ckpt.CheckpointError(f"{where} is the checkpoint of a peer's run ({meta['peer'].get('framework')}): "
                                   "it resumes that run, but softac cannot load it as an agent")
    if not isinstance(meta.get("config"), dict):
        raise ckpt.CheckpointError(f"corrupt checkpoint {where}: it names no config")
    saved = dict(meta["config"])
    saved.setdefault("pixel_range", "centered")  # checkpoints from before the key scaled pixels so
    try:
        config = SACConfig().replace(**saved)
    except SoftacError as exc:
        raise ckpt.CheckpointError(f"checkpoint {where} has an invalid config: {exc}") from None
    return config.replace(**{key: value for key, value in overrides.items() if value is not None})


def _bounds_text(low: np.ndarray, high: np.ndarray) -> str:
    def one_line(a: np.ndarray) -> str:
        return np.array2string(np.asarray(a), precision=4, separator=", ", threshold=8, max_line_width=10**9)

    return f"low {one_line(low)}, high {one_line(high)}"


def check_saved_spaces(saved: dict[str, Any], spaces: SpaceInfo, where: Path | str, allow_new_bounds: bool) -> None:
    """The checkpoint's spaces against the env's: sizes must match; bounds too, unless allowed."""
    if saved.get("obs_dim") != spaces.obs_dim or saved.get("act_dim") != spaces.act_dim:
        raise ckpt.CheckpointError(
            f"checkpoint {where} is for observations of {saved.get('obs_dim')} and actions of "
            f"{saved.get('act_dim')} values, but the env has {spaces.obs_dim} and {spaces.act_dim}")
    if allow_new_bounds or "low" not in saved:
        return
    low, high = (np.asarray(saved[k], np.float32) for k in ("low", "high"))
    if not (np.array_equal(low, spaces.low) and np.array_equal(high, spaces.high)):
        raise ckpt.CheckpointError(
            f"checkpoint {where} was trained with action bounds {_bounds_text(low, high)}, but the env has "
            f"{_bounds_text(spaces.low, spaces.high)}; to scale its actions to the new bounds, "
            "pass allow_new_bounds=True (--allow-new-bounds)")


def restore(meta: dict[str, Any], arrays: dict[str, np.ndarray], learner: Learner, run: RunState,
            collector: Collector, where: Path | str = "", allow_new_bounds: bool = False) -> None:
    """Put a checkpoint's contents back into a learner, run state and collector made for its config."""
    check_saved_spaces(meta.get("spaces", {}), learner.spaces, where, allow_new_bounds)
    learner.load_arrays(arrays, where)
    run.restore(meta, arrays, where)
    collector.restore(meta, arrays, run.num_steps)


def load_learner(path: str | Path, which: str | None = None, device: str | None = None,
                 allow_new_bounds: bool = False) -> tuple[Learner, int]:
    """The learner of a run's (best, else last) or a checkpoint directory's checkpoint, and the step it was
    saved at; the env of its config gives the spaces (made once, then closed)."""
    from softac.base.device import select_device

    directory = ckpt.resolve(path, which)
    meta, arrays = ckpt.load(directory)
    config = saved_config(meta, directory, device=device)
    select_device(config.device)
    _, env = training_env_source(config.env_id, config)  # image observations: the wrappers that made them
    try:
        spaces = check_spaces(env)
    finally:
        env.close()
    check_saved_spaces(meta.get("spaces", {}), spaces, directory, allow_new_bounds)
    learner = Learner(config, spaces)
    learner.load_arrays(arrays, directory)
    return learner, int(meta["num_steps"])
