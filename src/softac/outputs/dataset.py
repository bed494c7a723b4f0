"""`softac dataset`: a Minari dataset from a run (issue 68): its replay buffer as episodes, or fresh episodes of its
policy (the deterministic action, with Gaussian noise of a given std in [-1, 1] units where asked), written with
Minari's metadata (the env's spec where Gymnasium registers it, the algorithm, softac as author) so that
`minari.load_dataset`, softac's `--offline-data` and other libraries read it."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from softac.replay.offline import OfflineDataError, write_minari
from softac.run.offline_sources import buffer_episodes, replay_rows
from softac.version import __version__


@dataclass
class WrittenDataset:
    path: Path
    episodes: int
    transitions: int
    mean_return: float | None  # the fresh episodes' (None for a replay buffer)


def write_agent_dataset(agent: Any, what: str, out: str | Path, dataset_id: str | None = None,
                        episodes: int | None = None, policy: str = "deployed", noise: float = 0.0, seed: int = 0,
                        steps: int | None = None) -> WrittenDataset:
    """A Minari dataset at `out` from an agent (`what`: whose, for the description): its replay buffer as each env's
    episodes, or, with `episodes` or `steps`, fresh episodes of its policy (policy_episodes). `out` is checked
    before any episode is run."""
    out = Path(out)
    if out.exists():
        raise OfflineDataError(f"{out} exists; pick a new --out")
    if noise < 0:
        raise OfflineDataError(f"noise must be >= 0, got {noise:g}")
    if episodes is not None or steps is not None:
        return policy_dataset(agent, what, episodes, policy, noise, seed, out, dataset_id, steps)
    state = agent.collector.replay_state()  # the host's buffer, or a device run's replay (issue 67)
    if state is None:
        raise OfflineDataError(f"{what} holds no replay buffer (a run's checkpoints/last has one, as agent.save(path, "
                               "include_buffer=True) has): train it, or write fresh episodes (--episodes N)")
    return buffer_dataset(agent, state, what, out, dataset_id)


def default_dataset_id(out: Path, env_id: str, mode: str) -> str:
    """`namespace/name-vN` from `out` when its last two parts read so (a Minari datasets tree), else softac/ENV-MODE-v0."""
    if re.fullmatch(r"[\w.-]+-v\d+", out.name) and out.parent.name:
        return f"{out.parent.name}/{out.name}"
    slug = re.sub(r"[^\w.-]+", "-", env_id.lower()).strip("-")
    return f"softac/{slug}-{mode}-v0"


def observation_format(env: Any, what: str) -> tuple[Any, Callable[[np.ndarray], Any]]:
    """The observation space a dataset of `env` records, and the conversion of the flat observations softac holds
    to it: the env's own Dict of Boxes for a dict-observing env (a goal env's), which softac flattens, so that the
    dataset is in the env's terms (Minari's recover_environment, other libraries); a vector env's Box as it is."""
    import gymnasium as gym

    from softac.envs.goals import dict_layout, dict_observation_space

    from softac.envs.pixels import ImageWithState, is_frame_stack_space, wrapper_of

    space = env.observation_space
    if wrapper_of(env, ImageWithState) is not None:
        raise OfflineDataError(f"{what}: an image with state values (packed into softac's frames) is not written as "
                               "a dataset; softac writes vectors, dicts of them and frame stacks")
    if is_frame_stack_space(space):  # the env's frame stacks [k, h, w, c] as they are
        return space, lambda stacks: stacks
    if not isinstance(space, gym.spaces.Box) or len(space.shape) != 1:
        raise OfflineDataError(f"{what}: {type(space).__name__} observations of shape {space.shape} are not written "
                               "as datasets; softac writes vectors, dicts of them and frame stacks")
    original = dict_observation_space(env)
    if original is None:
        return space, lambda flat: flat
    kinds = sorted({type(sub).__name__ for sub in original.spaces.values()})
    if kinds != ["Box"]:
        raise OfflineDataError(f"{what}: its dict observation holds {', '.join(kinds)} entries; softac writes dicts "
                               "of Box entries")
    layout = dict_layout(original)

    def to_dict(flat: np.ndarray) -> dict[str, np.ndarray]:
        return {k: flat[:, layout.slices[k]].reshape(len(flat), *sub.shape).astype(sub.dtype)
                for k, sub in original.spaces.items()}

    return original, to_dict


def _in_format(episodes: list[dict[str, np.ndarray]], convert: Callable[[np.ndarray], Any]) -> list[dict[str, Any]]:
    return [{**ep, "observations": convert(ep["observations"])} for ep in episodes]


def buffer_dataset(agent: Any, state: dict[str, np.ndarray], what: str, out: Path,
                   dataset_id: str | None) -> WrittenDataset:
    """An agent's replay buffer (its state_dict), as each env's episodes, as a Minari dataset."""
    env = agent.make_env()
    try:
        space, convert = observation_format(env, f"a dataset of {what}")
        rows = replay_rows(state, agent.config, {"num_steps": agent.num_steps}, what, agent.spaces.layout)
        episodes = buffer_episodes(rows, agent.learner.scaler.to_env)
        env_id = agent.config.env_id
        written = write_minari(out, dataset_id or default_dataset_id(out, env_id, "replay"),
                               _in_format(episodes, convert), env_id, space, env.action_space,
                               f"softac {__version__} SAC (replay buffer)",
                               f"The replay buffer of {what} at step {agent.num_steps}: "
                               f"{len(rows.rewards):,} transitions of {env_id}.")
    finally:
        env.close()
    return WrittenDataset(written, len(episodes), int(len(rows.rewards)), None)


def policy_episodes(act: Callable[[np.ndarray], np.ndarray], scaler: Any, env: Any, episodes: int | None,
                    noise: float, seed: int, steps: int | None = None) -> list[dict[str, np.ndarray]]:
    """`episodes` episodes of the deterministic policy `act` (obs -> env action), or episodes until `steps`
    transitions (the last one cut there, truncated), its actions moved by Gaussian noise of std `noise` in [-1, 1]
    units and clipped to the bounds; episode i starts from reset(seed=seed + i)."""
    rng = np.random.default_rng([seed, 0xDA7A])
    out: list[dict[str, np.ndarray]] = []
    total, i = 0, 0
    while (episodes is None or i < episodes) and (steps is None or total < steps):
        obs, _ = env.reset(seed=seed + i)
        i += 1
        observations, actions, rewards, terminations, truncations = [obs], [], [], [], []
        while True:
            action = np.asarray(act(obs), np.float32)
            if noise > 0:
                moved = scaler.to_normalised(action) + noise * rng.standard_normal(action.shape)
                action = np.asarray(scaler.to_env(np.clip(moved, -1.0, 1.0)), np.float32)
            obs, reward, terminated, truncated, _ = env.step(action)
            observations.append(obs)
            actions.append(action)
            rewards.append(float(reward))
            total += 1
            terminations.append(bool(terminated))
            truncations.append(bool(truncated) or (steps is not None and total >= steps and not terminated))
            if terminations[-1] or truncations[-1]:
                break
        stacked = np.asarray(observations)  # frame stacks stay uint8, vectors become float32
        out.append({"observations": stacked if stacked.dtype == np.uint8 else stacked.astype(np.float32),
                    "actions": np.asarray(actions, np.float32),
                    "rewards": np.asarray(rewards, np.float32), "terminations": np.asarray(terminations),
                    "truncations": np.asarray(truncations)})
    return out


def policy_dataset(agent: Any, what: str, episodes: int | None, policy: str, noise: float, seed: int, out: Path,
                   dataset_id: str | None, steps: int | None = None) -> WrittenDataset:
    """Fresh episodes of an agent's policy as a Minari dataset."""
    env = agent.make_env()
    try:
        space, convert = observation_format(env, f"a dataset of {what}")
        data = policy_episodes(lambda obs: agent.predict(obs, deterministic=True, policy=policy), agent.learner.scaler,
                               env, episodes, noise, seed, steps)
        env_id = agent.config.env_id
        mean_return = float(np.mean([ep["rewards"].sum() for ep in data]))
        how = f"its {policy} policy's deterministic actions" + (f" with Gaussian noise of std {noise:g}" if noise else "")
        written = write_minari(out, dataset_id or default_dataset_id(out, env_id, "policy"), _in_format(data, convert),
                               env_id, space, env.action_space, f"softac {__version__} SAC ({policy} policy)",
                               f"{len(data)} episodes of {what} at step {agent.num_steps}: {how}; mean "
                               f"return {mean_return:.1f}.")
    finally:
        env.close()
    return WrittenDataset(written, len(data), int(sum(len(ep["rewards"]) for ep in data)), mean_return)
