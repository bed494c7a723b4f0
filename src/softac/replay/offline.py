"""Transitions from before the run (issue 68): a dataset loaded once, held beside the env's replay buffer and sampled
into each batch (RLPD's symmetric sampling, Ball et al. 2023: half of every batch offline), or copied into the
replay before the first step (`offline_mode: prefill`).

A dataset is Minari's format (Farama's, for Gymnasium: episodes of observations [T+1], actions, rewards,
terminations and truncations [T]) or a softac run's replay buffer (softac.run.offline_sources reads those). Inside
softac its actions are in [-1, 1] as the replay's are; Minari's files hold them in the env's units. Terminations and
truncations stay apart: only a termination stops the bootstrap. Observations are stored raw and normalised when
drawn, with the statistics of that moment, as the replay's are (obs_norm). A dict observation (a goal env's, Minari's
Dict space) is flattened as the env's is (its DictLayout); a goal env's dataset keeps its episodes whole, so that
HER relabels its rows in each batch as it relabels the replay's (Andrychowicz et al. 2017, on demonstrations as
Nair et al. 2018).
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from softac.base.memory import human_bytes, memory_shortfall, transition_bytes
from softac.envs.goals import DictLayout
from softac.envs.make import SpaceInfo
from softac.errors import SoftacError
from softac.replay.her_buffer import HerSetup, goal_steps, relabel_goals


class OfflineDataError(SoftacError):
    """A dataset that cannot be used: missing, unreadable, of other spaces, or too large (one line, exit 2)."""


@dataclass
class OfflineData:
    """Transitions as arrays, one row each: observations raw, actions in [-1, 1]. Image observations (frame stacks,
    uint8) are held once an episode: `obs` is each episode's [T+1] observations in turn, row r's observation is
    obs[obs_row[r]] and its next one the one after, and `next_obs` is None."""
    obs: np.ndarray  # [n, obs_dim] float32 (images: [n + episodes, k, h, w, c] uint8)
    actions: np.ndarray  # [n, act_dim] float32, in [-1, 1]
    rewards: np.ndarray  # [n] float32
    next_obs: np.ndarray | None  # [n, obs_dim] float32: the true next observation (at a truncation, the final one)
    terminated: np.ndarray  # [n] float32: 1 where the episode terminated (no bootstrap)
    truncated: np.ndarray  # [n] bool: the episode was cut there (a time limit, or the data's end)
    source: str  # what it was loaded from, as the user named it
    checksum: str  # sha256 of the files it was read from: a resumed run checks it
    episodes: int
    # a goal env's data, its episodes whole and in order: each row's step in its episode, and the episode's length
    # (HER's relabelling); None where rows are not laid out by episode
    t: np.ndarray | None = None
    length: np.ndarray | None = None
    obs_row: np.ndarray | None = None  # images: each row's observation in `obs`

    def __len__(self) -> int:
        return len(self.rewards)

    @property
    def nbytes(self) -> int:
        arrays = (self.obs, self.actions, self.rewards, self.next_obs, self.terminated, self.truncated, self.t,
                  self.length, self.obs_row)
        return sum(a.nbytes for a in arrays if a is not None)

    def observations(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The observations and next observations of rows `idx` (any shape)."""
        if self.obs_row is None:
            return self.obs[idx], self.next_obs[idx]
        rows = self.obs_row[idx]
        return self.obs[rows], self.obs[rows + 1]

    def sample(self, rng: np.random.Generator, batch_size: int, n_batches: int = 1,
               her: HerSetup | None = None) -> dict[str, np.ndarray]:
        """`n_batches` batches of `batch_size` rows drawn uniformly, as the replay's sample lays them out; with
        `her` (a goal env), a share her_k / (her_k + 1) of them given a goal their episode achieved, as the HER
        buffer's rows are."""
        idx = rng.integers(0, len(self), size=(n_batches, batch_size))
        obs, next_obs = self.observations(idx)
        out = {"obs": obs, "actions": self.actions[idx], "rewards": self.rewards[idx], "next_obs": next_obs,
               "terminated": self.terminated[idx], "steps": np.ones(idx.shape, np.float32)}
        if her is not None and self.t is not None:
            self._relabel(rng, idx.reshape(-1), out, her)
        return out

    def _relabel(self, rng: np.random.Generator, idx: np.ndarray, batch: dict[str, np.ndarray], her: HerSetup) -> None:
        which = np.flatnonzero(rng.random(idx.shape) < her.k / (her.k + 1.0))
        if not which.size:
            return
        rows, t = idx[which], self.t[idx[which]]
        goals = self.next_obs[rows + goal_steps(rng, t, self.length[rows], her.strategy) - t,
                              her.layout.slices["achieved_goal"]]
        obs, next_obs = (batch[k].reshape(len(idx), -1) for k in ("obs", "next_obs"))
        rewards = batch["rewards"].reshape(-1)
        relabel_goals(obs, next_obs, rewards, which, goals, her.layout, her.reward_fn)

    def check_prefill_fits(self, capacity: int) -> None:
        """offline_mode prefill copies every transition into the replay (the host's or the device's): refused in one
        line when they are more than it holds."""
        if len(self) > capacity:
            raise OfflineDataError(f"offline_mode prefill: {self.source} holds {len(self):,} transitions, more than "
                                   f"the replay's {capacity:,} (buffer_size)")

    def describe(self) -> str:
        return (f"offline data {self.source}: {len(self):,} transitions in {self.episodes:,} episodes, "
                f"{human_bytes(self.nbytes)}")


class OfflineSource:
    """A run's offline dataset, read on first use by `loader` (None: the run has none); a resumed run's must still
    have the checksum its checkpoint recorded. Both collectors (the host's and the device's) hold one."""

    def __init__(self, loader: Callable[[], OfflineData] | None):
        self.loader, self.data = loader, None
        self.expected: dict[str, Any] | None = None  # what a checkpoint recorded: source, checksum, transitions

    def load(self) -> OfflineData | None:
        if self.data is None and self.loader is not None:
            data = self.loader()
            if self.expected is not None and self.expected.get("checksum") != data.checksum:
                raise OfflineDataError(f"offline data {data.source} changed since this run started (its checksum "
                                       "differs from the checkpoint's): restore that dataset, or start a new run")
            self.data = data
        return self.data

    def checkpoint_meta(self) -> dict[str, Any]:
        """The checkpoint's record of the dataset ({} without one)."""
        if self.data is None:
            return {} if self.expected is None else {"offline": self.expected}
        return {"offline": {"source": self.data.source, "checksum": self.data.checksum, "transitions": len(self.data)}}

    def restore(self, meta: dict[str, Any]) -> None:
        self.expected = meta.get("offline")


def mixed_batches(online: dict[str, np.ndarray], offline: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Each batch's offline rows after its online ones ([n_batches, rows, ...] each): the losses average over
    rows, so their order is immaterial, and batch statistics (CrossQ) see both sources as RLPD's joint batch."""
    return {k: np.concatenate([online[k], offline[k]], axis=1) for k in online}


def offline_rows(batch_size: int, fraction: float) -> int:
    """How many of a batch's rows the dataset gives: at least one, and one at least left to the env's replay."""
    return min(max(1, int(round(batch_size * fraction))), batch_size - 1)


def offline_bytes(rows: int, episodes: int, spaces: SpaceInfo) -> int:
    """What `rows` transitions in `episodes` episodes take as OfflineData: float32 vector rows, or each episode's
    frame stacks once (uint8) beside the rows' actions, rewards and flags."""
    if spaces.image_shape is None:
        return rows * transition_bytes(spaces.obs_dim, spaces.act_dim)
    return (rows + episodes) * int(np.prod(spaces.image_shape)) + rows * (4 * spaces.act_dim + 4 + 4 + 1 + 8)


def check_offline_memory(rows: int, episodes: int, spaces: SpaceInfo, source: str,
                         memory_fraction: float = 0.8) -> None:
    """Refuse, before reading it, a dataset the machine cannot hold beside what is running."""
    short = memory_shortfall(offline_bytes(rows, episodes, spaces), memory_fraction)
    if short is not None:
        raise OfflineDataError(f"offline data {source}: its {rows:,} transitions need {short}")


def env_obs_shape(spaces: SpaceInfo) -> tuple[int, ...]:
    """The shape of what softac's env observes: a frame stack [k, h, w, c], else a flat vector."""
    return tuple(spaces.image_shape) if spaces.image_shape is not None else (spaces.obs_dim,)


def check_dataset_spaces(source: str, obs_shape: tuple, act_low: np.ndarray, act_high: np.ndarray, env_name: str,
                         spaces: SpaceInfo, layout: DictLayout | None = None) -> None:
    """The dataset's observations and actions must be the env's (`spaces`): one line naming both where they are
    not. `layout`: a dict-observing dataset's (the env's must match it key by key)."""
    ours = spaces.layout
    if layout is not None:
        if ours is None or layout.keys != ours.keys or layout.slices != ours.slices:
            raise OfflineDataError(f"offline data {source} observes {describe_observations(layout)} but {env_name} "
                                   f"observes {describe_observations(ours, env_obs_shape(spaces))}")
    elif tuple(obs_shape) != env_obs_shape(spaces):
        raise OfflineDataError(f"offline data {source} observes shape {tuple(obs_shape)} but {env_name} observes "
                               f"{env_obs_shape(spaces)}")
    act_low, act_high = np.asarray(act_low, np.float64).ravel(), np.asarray(act_high, np.float64).ravel()
    low, high = np.asarray(spaces.low, np.float64), np.asarray(spaces.high, np.float64)
    if act_low.shape != low.shape or not (np.allclose(act_low, low) and np.allclose(act_high, high)):
        raise OfflineDataError(f"offline data {source} acts in [{_bounds(act_low)}, {_bounds(act_high)}] but "
                               f"{env_name} in [{_bounds(low)}, {_bounds(high)}]")


def describe_observations(layout: DictLayout | None, shape: tuple[int, ...] = ()) -> str:
    """`a dict of achieved_goal (2), desired_goal (2), observation (3) values`, or `shape (dim,)`."""
    if layout is None:
        return f"shape {tuple(shape)}"
    return "a dict of " + ", ".join(f"{k} ({layout.slices[k].stop - layout.slices[k].start})" for k in layout.keys) \
        + " values"


def episode_steps(ends: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each row's step in its episode and the episode's length, for rows laid out episode after episode, `ends`
    marking each episode's last row (the last row always ends one)."""
    ends = np.asarray(ends, bool).copy()
    ends[-1] = True
    last = np.flatnonzero(ends)
    lengths = np.diff(np.concatenate([[-1], last]))
    starts = last - lengths + 1
    episode = np.repeat(np.arange(len(last)), lengths)
    return np.arange(len(ends)) - starts[episode], lengths[episode]


def _bounds(a: np.ndarray) -> str:
    return np.array2string(np.asarray(a, np.float64), precision=3, separator=", ", threshold=8)


def from_episodes(episodes: Iterable[Any], to_normalised: Any, source: str, checksum: str,
                  layout: DictLayout | None = None, keep_episodes: bool = False,
                  image_shape: tuple[int, ...] | None = None) -> OfflineData:
    """Transitions from Minari-style episodes (observations [T+1], actions [T] in env units, rewards, terminations,
    truncations): row t is (o_t, a_t, r_t, o_t+1). An episode whose last step neither terminated nor truncated
    (the data ends inside it) is marked truncated there: its last transition still bootstraps. Dict observations
    are flattened by `layout`; `keep_episodes` records each row's step and episode length (HER); frame stacks of
    `image_shape` are kept once an episode (OfflineData.obs_row)."""
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("obs", "actions", "rewards", "next_obs", "terminated",
                                                          "truncated", "obs_row")}
    count, held = 0, 0
    for ep in episodes:
        observations = ep.observations
        if isinstance(observations, dict) and layout is not None:
            observations = layout.flatten(observations)
        observations = np.asarray(observations, np.uint8 if image_shape is not None else np.float32)
        if (observations.shape[1:] != tuple(image_shape)) if image_shape is not None else observations.ndim != 2:
            raise OfflineDataError(f"offline data {source}: episode {count} has observations of shape "
                                   f"{observations.shape[1:]}; softac reads flat vectors, dicts of them, or its "
                                   "env's frame stacks")
        t = len(ep.rewards)
        if t == 0:
            continue
        truncated = np.asarray(ep.truncations, bool).copy()
        terminated = np.asarray(ep.terminations, bool)
        truncated[-1] |= not terminated[-1]
        if image_shape is None:
            parts["obs"].append(observations[:t])
            parts["next_obs"].append(observations[1:t + 1])
        else:  # each frame stack once: row i's next observation is the one after its own
            parts["obs"].append(observations[:t + 1])
            parts["obs_row"].append(held + np.arange(t))
            held += t + 1
        parts["actions"].append(np.asarray(to_normalised(np.asarray(ep.actions, np.float32)), np.float32))
        parts["rewards"].append(np.asarray(ep.rewards, np.float32))
        parts["terminated"].append(terminated.astype(np.float32))
        parts["truncated"].append(truncated)
        count += 1
    if count == 0:
        raise OfflineDataError(f"offline data {source} holds no transitions")
    arrays = {k: np.concatenate(v) if v else None for k, v in parts.items()}
    if keep_episodes:
        arrays["t"], arrays["length"] = episode_steps((arrays["terminated"] > 0) | arrays["truncated"])
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


def minari_transitions(source: str, env_name: str, spaces: SpaceInfo, to_normalised: Any) -> OfflineData:
    """A Minari dataset's transitions for an env of `spaces`, its spaces checked against the env's and its size
    against the memory; a goal env's keep their episodes whole (HER)."""
    import gymnasium as gym

    from softac.envs.goals import dict_layout

    dataset, data_dir = load_minari(source)
    obs_space, act_space = dataset.observation_space, dataset.action_space
    dict_box = isinstance(obs_space, gym.spaces.Dict) and all(isinstance(s, gym.spaces.Box)
                                                               for s in obs_space.spaces.values())
    if not (isinstance(obs_space, gym.spaces.Box) or dict_box) or not isinstance(act_space, gym.spaces.Box):
        raise OfflineDataError(f"offline data {source} observes {type(obs_space).__name__} and acts in "
                               f"{type(act_space).__name__}; softac reads Box observations (or a Dict of Boxes) "
                               "and Box actions")
    check_dataset_spaces(source, getattr(obs_space, "shape", None) or (), act_space.low, act_space.high, env_name,
                         spaces, dict_layout(obs_space) if dict_box else None)
    if spaces.image_shape is not None and obs_space.dtype != np.uint8:
        raise OfflineDataError(f"offline data {source} observes {obs_space.dtype} images but {env_name} uint8 ones")
    check_offline_memory(int(dataset.total_steps), int(dataset.total_episodes), spaces, source)
    return from_episodes(dataset.iterate_episodes(), to_normalised, source, files_checksum(data_dir), spaces.layout,
                         spaces.goal_env, spaces.image_shape)


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
