"""A peer's checkpoint in softac's format (its model and replay buffer), so that its runs resume exactly."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from softac.peers.models import _peer_algorithm, normalized_env, peer_env, sweep_config, without_log_dir


BUFFER_FIELDS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")
HER_BUFFER_FIELDS = ("ep_start", "ep_length")


def _buffer_arrays(buffer: Any, filled: int) -> dict[str, Any]:
    """The filled rows of an SB3 replay buffer's arrays, a dict buffer's per key, HER's episode arrays too."""
    arrays = {}
    for name in BUFFER_FIELDS + (HER_BUFFER_FIELDS if hasattr(buffer, "ep_start") else ()):
        value = getattr(buffer, name)
        if isinstance(value, dict):
            arrays.update({f"buffer_{name}.{key}": part[:filled] for key, part in value.items()})
        else:
            arrays[f"buffer_{name}"] = value[:filled]
    if hasattr(buffer, "_current_ep_start"):
        arrays["buffer__current_ep_start"] = buffer._current_ep_start
    return arrays


def _refill_buffer(buffer: Any, arrays: dict[str, Any]) -> None:
    for name, rows in arrays.items():
        if not name.startswith("buffer_"):
            continue
        field, _, key = name[len("buffer_"):].partition(".")
        target = getattr(buffer, field)
        if field == "_current_ep_start":
            target[:] = rows
        elif key:
            target[key][:len(rows)] = rows
        else:
            target[:len(rows)] = rows


def save_peer_checkpoint(model: Any, directory: Path, meta: dict[str, Any]) -> None:
    """The peer's model in its own library's format (its `save()` zip, kept as bytes), the filled rows of its
    replay buffer, and the run's bookkeeping (`meta`), written as softac writes its checkpoints: atomically,
    checksummed, no pickle of ours (SB3's zip holds its own pickled settings, read only by SB3 on resume)."""
    import io

    import numpy as np

    from softac.run import checkpoint as ckpt

    zipped = io.BytesIO()
    model.save(zipped)
    buffer = model.replay_buffer
    filled = buffer.buffer_size if buffer.full else buffer.pos
    arrays = {"model_zip": np.frombuffer(zipped.getvalue(), np.uint8)}
    normalizer = model.get_vec_normalize_env()
    if normalizer is not None:  # VecNormalize's statistics: the model's zip leaves them out
        stats = normalizer.obs_rms
        arrays.update(obs_rms_mean=np.asarray(stats.mean), obs_rms_var=np.asarray(stats.var),
                      obs_rms_count=np.asarray(stats.count, np.float64))
    arrays.update(_buffer_arrays(buffer, filled))
    ckpt.save(directory, {**meta, "buffer_pos": int(buffer.pos), "buffer_full": bool(buffer.full)}, arrays)


def load_peer_checkpoint(framework: str, env_id: str, directory: Path,
                         identity: dict[str, Any]) -> tuple[Any, dict[str, Any]]:
    """The model and the bookkeeping `save_peer_checkpoint` wrote, the replay buffer refilled (SB3's `load()`
    alone leaves it empty, and SBX's CrossQ then learns from one row and diverges to NaN). A checkpoint of
    another run (`identity`: framework, env, seed, steps) is refused."""
    import io

    from softac.run import checkpoint as ckpt
    from softac.errors import SoftacError

    meta, arrays = ckpt.load(directory)
    if meta.get("peer") != identity:
        raise SoftacError(f"{directory} holds the checkpoint of another run ({meta.get('peer') or 'softac'}), not "
                          f"of {identity}; pick another --out")
    algorithm, kwargs = _peer_algorithm(framework)
    env = peer_env(framework, env_id, int(identity.get("action_repeat", 1)))
    if "obs_rms_mean" in arrays:
        env = normalized_env(env, sweep_config(env_id, **meta["sweep"]))
        env.obs_rms.mean, env.obs_rms.var = arrays["obs_rms_mean"].copy(), arrays["obs_rms_var"].copy()
        env.obs_rms.count = float(arrays["obs_rms_count"])
    model = without_log_dir(algorithm.load(io.BytesIO(arrays["model_zip"].tobytes()), env=env, **kwargs))
    buffer = model.replay_buffer
    _refill_buffer(buffer, arrays)
    buffer.pos, buffer.full = int(meta["buffer_pos"]), bool(meta["buffer_full"])
    return model, meta
