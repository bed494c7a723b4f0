"""Transitions from before the run (issue 68): a dataset loaded once, held beside the env's replay buffer and sampled
into each batch (RLPD's symmetric sampling, Ball et al. 2023: half of every batch offline), or copied into the
replay before the first step (`offline_mode: prefill`).

A dataset is Minari's format (Farama's, for Gymnasium: episodes of observations [T+1], actions, rewards,
terminations and truncations [T]) or a softac run's replay buffer (softac.run.offline_sources reads those). Inside
softac its actions are in [-1, 1] as the replay's are; Minari's files hold them in the env's units. Terminations and
truncations stay apart: only a termination stops the bootstrap. Observations are stored raw and normalised when
drawn, with the statistics of that moment, as the replay's are (obs_norm).
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from softac.base.memory import available_memory_bytes, human_bytes, transition_bytes
from softac.errors import SoftacError


class OfflineDataError(SoftacError):
    """A dataset that cannot be used: missing, unreadable, of other spaces, or too large (one line, exit 2)."""


@dataclass
class OfflineData:
    """Transitions as arrays, one row each: observations raw, actions in [-1, 1]."""
    obs: np.ndarray  # [n, obs_dim] float32
    actions: np.ndarray  # [n, act_dim] float32, in [-1, 1]
    rewards: np.ndarray  # [n] float32
    next_obs: np.ndarray  # [n, obs_dim] float32: the true next observation (at a truncation, the final one)
    terminated: np.ndarray  # [n] float32: 1 where the episode terminated (no bootstrap)
    truncated: np.ndarray  # [n] bool: the episode was cut there (a time limit, or the data's end)
    source: str  # what it was loaded from, as the user named it
    checksum: str  # sha256 of the files it was read from: a resumed run checks it
    episodes: int

    def __len__(self) -> int:
        return len(self.rewards)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.obs, self.actions, self.rewards, self.next_obs, self.terminated,
                                      self.truncated))

    def sample(self, rng: np.random.Generator, batch_size: int, n_batches: int = 1) -> dict[str, np.ndarray]:
        """`n_batches` batches of `batch_size` rows drawn uniformly, as the replay's sample lays them out."""
        idx = rng.integers(0, len(self), size=(n_batches, batch_size))
        return {"obs": self.obs[idx], "actions": self.actions[idx], "rewards": self.rewards[idx],
                "next_obs": self.next_obs[idx], "terminated": self.terminated[idx],
                "steps": np.ones(idx.shape, np.float32)}

    def describe(self) -> str:
        return (f"offline data {self.source}: {len(self):,} transitions in {self.episodes:,} episodes, "
                f"{human_bytes(self.nbytes)}")


def mixed_batches(online: dict[str, np.ndarray], offline: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Each batch's offline rows after its online ones ([n_batches, rows, ...] each): the losses average over
    rows, so their order is immaterial, and batch statistics (CrossQ) see both sources as RLPD's joint batch."""
    return {k: np.concatenate([online[k], offline[k]], axis=1) for k in online}


def offline_rows(batch_size: int, fraction: float) -> int:
    """How many of a batch's rows the dataset gives: at least one, and one at least left to the env's replay."""
    return min(max(1, int(round(batch_size * fraction))), batch_size - 1)


def check_offline_memory(rows: int, obs_dim: int, act_dim: int, source: str, memory_fraction: float = 0.8) -> None:
    """Refuse, before reading it, a dataset the machine cannot hold beside what is running."""
    need, have = rows * transition_bytes(obs_dim, act_dim), available_memory_bytes()
    if need > memory_fraction * have:
        raise OfflineDataError(f"offline data {source}: its {rows:,} transitions need {human_bytes(need)} but only "
                               f"{human_bytes(have)} is available")


def check_dataset_spaces(source: str, obs_shape: tuple, act_low: np.ndarray, act_high: np.ndarray,
                         env_name: str, obs_dim: int, low: np.ndarray, high: np.ndarray) -> None:
    """The dataset's observations and actions must be the env's: one line naming both where they are not."""
    if tuple(obs_shape) != (obs_dim,):
        raise OfflineDataError(f"offline data {source} observes shape {tuple(obs_shape)} but {env_name} observes "
                               f"({obs_dim},)")
    act_low, act_high = np.asarray(act_low, np.float64).ravel(), np.asarray(act_high, np.float64).ravel()
    if act_low.shape != low.shape or not (np.allclose(act_low, low) and np.allclose(act_high, high)):
        raise OfflineDataError(f"offline data {source} acts in [{_bounds(act_low)}, {_bounds(act_high)}] but "
                               f"{env_name} in [{_bounds(low)}, {_bounds(high)}]")


def _bounds(a: np.ndarray) -> str:
    return np.array2string(np.asarray(a, np.float64), precision=3, separator=", ", threshold=8)


def from_episodes(episodes: Iterable[Any], to_normalised: Any, source: str, checksum: str) -> OfflineData:
    """Transitions from Minari-style episodes (observations [T+1], actions [T] in env units, rewards, terminations,
    truncations): row t is (o_t, a_t, r_t, o_t+1). An episode whose last step neither terminated nor truncated
    (the data ends inside it) is marked truncated there: its last transition still bootstraps."""
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("obs", "actions", "rewards", "next_obs", "terminated",
                                                          "truncated")}
    count = 0
    for ep in episodes:
        observations = np.asarray(ep.observations, np.float32)
        if observations.ndim != 2:
            raise OfflineDataError(f"offline data {source}: episode {count} has observations of shape "
                                   f"{observations.shape}; softac reads flat vector observations")
        t = len(ep.rewards)
        if t == 0:
            continue
        truncated = np.asarray(ep.truncations, bool).copy()
        terminated = np.asarray(ep.terminations, bool)
        truncated[-1] |= not terminated[-1]
        parts["obs"].append(observations[:t])
        parts["next_obs"].append(observations[1:t + 1])
        parts["actions"].append(np.asarray(to_normalised(np.asarray(ep.actions, np.float32)), np.float32))
        parts["rewards"].append(np.asarray(ep.rewards, np.float32))
        parts["terminated"].append(terminated.astype(np.float32))
        parts["truncated"].append(truncated)
        count += 1
    if count == 0:
        raise OfflineDataError(f"offline data {source} holds no transitions")
    arrays = {k: np.concatenate(v) for k, v in parts.items()}
    return OfflineData(**arrays, source=source, checksum=checksum, episodes=count)


# ---- Minari's datasets -------------------------------------------------------------------------------------

MINARI_ID = re.compile(r"^([\w.-]+/)*[\w.-]+-v\d+$")


def files_checksum(directory: Path) -> str:
    """sha256 over a directory's files (their relative names and bytes, in name order)."""
    digest = hashlib.sha256()
    for path in sorted(p for p in directory.rglob("*") if p.is_file()):
        digest.update(str(path.relative_to(directory)).encode() + b"\0")
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def minari_data_dir(path: Path) -> Path | None:
    """A Minari dataset's data directory (metadata.json and the episodes' file) at `path` or `path/data`."""
    for candidate in (path / "data", path):
        if (candidate / "metadata.json").is_file():
            return candidate
    return None


def _import_minari() -> Any:
    try:
        import minari
    except ImportError:
        raise OfflineDataError("offline data from Minari needs minari: pip install 'softac[offline]'") from None
    return minari


def load_minari(source: str) -> tuple[Any, Path]:
    """A Minari dataset by directory or id (local, else downloaded by Minari), and its data directory."""
    minari = _import_minari()
    path = Path(source).expanduser()
    data_dir = minari_data_dir(path) if path.is_dir() else None
    if data_dir is None:
        if path.exists() or not MINARI_ID.match(source):
            raise OfflineDataError(f"offline data {source}: not a Minari dataset directory, a softac run, or a Minari "
                                   "dataset id (namespace/name-v0)")
        from minari.storage.datasets_root_dir import get_dataset_path

        local = minari_data_dir(Path(get_dataset_path(source)))
        if local is None:
            try:
                minari.download_dataset(source)
            except Exception as exc:  # Minari's own errors: unreachable host, unknown id
                first = (str(exc).splitlines() or [type(exc).__name__])[0]
                raise OfflineDataError(f"offline data {source}: not found locally and Minari could not download it "
                                       f"({first})") from None
            local = minari_data_dir(Path(get_dataset_path(source)))
        if local is None:
            raise OfflineDataError(f"offline data {source}: Minari's copy has no metadata.json")
        data_dir = local
    from minari.dataset.minari_dataset import MinariDataset

    try:
        return MinariDataset(data_dir), data_dir
    except Exception as exc:
        first = (str(exc).splitlines() or [type(exc).__name__])[0]
        raise OfflineDataError(f"offline data {source}: Minari cannot read it ({first})") from None


def minari_transitions(source: str, env_name: str, obs_dim: int, low: np.ndarray, high: np.ndarray,
                       to_normalised: Any) -> OfflineData:
    """A Minari dataset's transitions, its spaces checked against the env's and its size against the memory."""
    import gymnasium as gym

    dataset, data_dir = load_minari(source)
    obs_space, act_space = dataset.observation_space, dataset.action_space
    if not isinstance(obs_space, gym.spaces.Box) or not isinstance(act_space, gym.spaces.Box):
        raise OfflineDataError(f"offline data {source} observes {type(obs_space).__name__} and acts in "
                               f"{type(act_space).__name__}; softac reads Box observations and actions")
    check_dataset_spaces(source, obs_space.shape, act_space.low, act_space.high, env_name, obs_dim, low, high)
    check_offline_memory(int(dataset.total_steps), obs_dim, len(low), source)
    return from_episodes(dataset.iterate_episodes(), to_normalised, source, files_checksum(data_dir))


def write_minari(out: Path, dataset_id: str, episodes: list[dict[str, np.ndarray]], env_id: str | None,
                 observation_space: Any, action_space: Any, algorithm: str, description: str) -> Path:
    """A Minari dataset at `out` (out/data/metadata.json and the episodes), written through Minari's own
    create_dataset_from_buffers in a staging directory beside `out`, then renamed into place whole. Each episode:
    observations [T+1], actions [T] (env units), rewards, terminations, truncations."""
    minari = _import_minari()
    from minari.data_collector.episode_buffer import EpisodeBuffer

    out = Path(out).absolute()  # Minari joins its datasets root and the id: a relative root would be joined twice
    if out.exists():
        raise OfflineDataError(f"{out} exists; pick a new --out")
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".softac-dataset-", dir=out.parent))
    buffers = [EpisodeBuffer(id=i, observations=ep["observations"], actions=ep["actions"],
                             rewards=list(map(float, ep["rewards"])), terminations=list(map(bool, ep["terminations"])),
                             truncations=list(map(bool, ep["truncations"])))
               for i, ep in enumerate(episodes)]
    previous = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(staging)  # Minari writes under its datasets root, by id
    try:
        spec = _registered_spec(env_id)
        minari.create_dataset_from_buffers(
            dataset_id, buffers, env=spec, eval_env=spec, observation_space=observation_space, action_space=action_space,
            algorithm_name=algorithm, author="softac", author_email="softac@users.noreply.github.com",
            code_permalink="https://github.com/softac/softac", description=description)
        os.replace(staging / dataset_id, out)
    finally:
        if previous is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = previous
        shutil.rmtree(staging, ignore_errors=True)
    return out


def _registered_spec(env_id: str | None) -> Any:
    """Gymnasium's spec of a registered env id (Minari records it, so that recover_environment() works), else None."""
    import gymnasium as gym

    if env_id is None:
        return None
    try:
        return gym.spec(env_id)
    except Exception:  # a softac-only id (dmc:..., playground:...) or an env instance's name
        return None
