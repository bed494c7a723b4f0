"""The peers: which library and class each is, at which settings, and how to make its model and env."""

from __future__ import annotations

import importlib.util
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from softac.peers.settings import SWEEP_TRANSLATORS, crossq_settings, rl_zoo_sac_settings

if TYPE_CHECKING:
    from softac.config.sac_config import SACConfig


@dataclass(frozen=True)
class Peer:
    package: str  # the module to import (the [bench] extra installs it)
    distribution: str  # its name on PyPI, for the version in config.yaml
    algorithm: str  # the class trained: SAC or CrossQ
    settings: str  # "defaults" (the peer's own), "sweep" (the sweep's --preset/--set), "zoo" (RL Zoo's for the
    # env), or the softac preset it runs at
    about: str
    label: str  # the configuration's name in tables and legends
    her: bool = False  # with SB3's HerReplayBuffer: for goal envs only
    policy: str = "MlpPolicy"  # the policy class's name in the library (MultiInputPolicy for dict observations)
    extra: str = "bench"  # softac's extra that installs it


PEERS = {
    "sb3": Peer("stable_baselines3", "stable-baselines3", "SAC", "defaults", "Stable-Baselines3's SAC at its defaults",
                "SB3 SAC, its defaults"),
    "sbx": Peer("sbx", "sbx-rl", "SAC", "defaults", "SBX's SAC at its defaults", "SBX SAC, its defaults"),
    "sbx-crossq": Peer("sbx", "sbx-rl", "CrossQ", "defaults",
                       "SBX's CrossQ at its defaults (256x256 actor, 1024x1024 critics, batch 256)",
                       "SBX CrossQ, its defaults"),
    "sbx-crossq-softac": Peer("sbx", "sbx-rl", "CrossQ", "crossq",
                              "SBX's CrossQ at softac's crossq preset settings (256x256, batch 128, learning_starts "
                              "5000, lr 1e-3, Adam b1 0.5, policy delay 3)",
                              "SBX CrossQ, crossq preset's settings"),
    "sbx-tqc": Peer("sbx", "sbx-rl", "TQC", "defaults",
                    "SBX's TQC at its defaults (2 critics of 25 quantiles, 2 dropped per critic, 256x256, batch 256)",
                    "SBX TQC, its defaults"),
    "sbx-tqc-softac": Peer("sbx", "sbx-rl", "TQC", "sweep",
                           "SBX's TQC at the sweep's own settings (its --preset and --set, e.g. --preset tqc; what "
                           "SBX cannot take is refused)", "SBX TQC, same settings"),
    "sbx-simba-softac": Peer("sbx", "sbx-rl", "SAC", "sweep",
                             "SBX's SAC with its SimbaPolicy at the sweep's own settings (its --preset and --set, e.g. "
                             "--preset simba; obs_norm through SB3's VecNormalize; what SBX cannot take is refused)",
                             "SBX SAC + SimBa, same settings", policy="SimbaPolicy"),
    "sb3-zoo": Peer("stable_baselines3", "stable-baselines3", "SAC", "zoo",
                    "Stable-Baselines3's SAC at RL Zoo's tuned settings for the env (Pendulum-v1, "
                    "MountainCarContinuous-v0, LunarLanderContinuous-v3, BipedalWalker-v3; softac.peers.settings)",
                    "SB3 SAC, RL Zoo's tuned settings"),
    "sb3-her": Peer("stable_baselines3", "stable-baselines3", "SAC", "defaults",
                    "Stable-Baselines3's SAC at its defaults with its HerReplayBuffer (future, 4 goals) and "
                    "learning_starts 1000, for goal envs", "SB3 SAC + HER, its defaults", her=True),
    "brax-sac": Peer("brax", "brax", "SAC", "sweep",
                     "Brax's SAC trainer (brax.training.agents.sac) at the sweep's own settings (its --preset and "
                     "--set, e.g. --preset brax-sac) on a MuJoCo Playground env, its whole loop on the device; what "
                     "Brax cannot take is refused (softac.peers.brax_sac)", "Brax SAC, same settings",
                     extra="playground"),
    "sbx-her": Peer("sbx", "sbx-rl", "SAC", "defaults",
                    "SBX's SAC at its defaults with SB3's HerReplayBuffer (future, 4 goals) and learning_starts "
                    "1000, for goal envs", "SBX SAC + HER, its defaults", her=True),
}
# SB3's HER examples' settings; its buffer cannot sample before an episode has ended
HER_SETTINGS = {"n_sampled_goal": 4, "goal_selection_strategy": "future"}
HER_LEARNING_STARTS = 1000
THROUGHPUT_LEARNING_STARTS = 100


def missing_peers(names: list[str]) -> list[str]:
    """The peers among `names` whose package is not installed (the [bench] extra)."""
    return [name for name in names if name in PEERS and importlib.util.find_spec(PEERS[name].package) is None]


def _peer_algorithm(framework: str) -> tuple[Any, dict[str, Any]]:
    """The peer's algorithm class, and the keywords both making and loading it take."""
    peer = PEERS[framework]
    if peer.package == "stable_baselines3":
        import torch
        from stable_baselines3 import SAC

        torch.set_num_threads(int(os.environ.get("SOFTAC_THREADS", 0)) or os.cpu_count() or 1)
        return SAC, {"device": "cpu"}
    import sbx

    return getattr(sbx, peer.algorithm), {}


def check_her_env(framework: str, env: Any, env_id: str, named: str | None = None) -> None:
    """A HER peer on an env that is no goal env is refused in one line (naming the peer as `named`, e.g. the
    command-line option that chose it)."""
    from softac.errors import SoftacError
    from softac.envs.goals import is_goal_env

    if PEERS[framework].her and not is_goal_env(env):
        raise SoftacError(f"{named or framework} needs a goal env (a dict observation with observation, achieved_goal, "
                          f"desired_goal and compute_reward); {env_id} is not one")


def peer_env(framework: str, env_id: str, action_repeat: int = 1):
    """The peer's training env as Gymnasium makes it (a goal env's dict observation kept: SB3's
    MultiInputPolicy takes it; each action repeated `action_repeat` times by softac's ActionRepeat), checked
    by check_her_env."""
    import gymnasium as gym

    from softac.envs.make import resolve_env_id, with_action_repeat

    # resolve_env_id imports Gymnasium-Robotics for its ids (and registers the DeepMind Control Suite's)
    env = gym.make(with_action_repeat(resolve_env_id(env_id), action_repeat))
    check_her_env(framework, env, env_id)
    return env


def sweep_config(env_id: str, preset: str | None, overrides: list[str] | None) -> SACConfig:
    """The softac config a sweep's --preset and --set make (default: the env's own preset): what a peer whose
    settings are "sweep" runs at."""
    from softac.config.sac_config import SACConfig, parse_overrides

    changes = parse_overrides(list(overrides or []))
    return SACConfig.preset(preset, env_id=env_id, overrides=changes) if preset else SACConfig.for_env(env_id, changes)


def peer_settings(framework: str, config: SACConfig | None, act_dim: int, env_id: str = "") -> dict[str, Any]:
    """The keywords a peer is made with besides its library's defaults (ValueError for settings it cannot take;
    a "zoo" peer's are RL Zoo's for `env_id`)."""
    from softac.config.sac_config import SACConfig

    peer = PEERS[framework]
    if peer.settings == "defaults":
        return {}
    if peer.settings == "zoo":
        return rl_zoo_sac_settings(env_id)
    if peer.settings == "sweep":
        if config is None:
            raise ValueError(f"{framework} runs at a sweep's settings: give its config")
        return SWEEP_TRANSLATORS[framework](config, act_dim)
    return crossq_settings(SACConfig.preset(peer.settings))


def peer_model(framework: str, env_id: str, seed: int, config: SACConfig | None = None, action_repeat: int = 1,
               **overrides: Any):
    """The peer's model on a fresh env, at its settings (a "sweep" peer's from `config`; `overrides`, e.g.
    learning_starts for a throughput probe, replace them), each action repeated `action_repeat` times."""
    import gymnasium as gym
    import numpy as np

    from softac.errors import SoftacError

    algorithm, kwargs = _peer_algorithm(framework)
    peer = PEERS[framework]
    env = peer_env(framework, env_id, action_repeat)
    try:
        kwargs.update(peer_settings(framework, config, int(np.prod(env.action_space.shape)), env_id))
    except ValueError as exc:
        raise SoftacError(f"{framework}: {exc}") from None
    if peer.her:
        from stable_baselines3 import HerReplayBuffer

        kwargs.update(replay_buffer_class=HerReplayBuffer, replay_buffer_kwargs=dict(HER_SETTINGS),
                      learning_starts=HER_LEARNING_STARTS)
    kwargs.update(overrides)
    policy = "MultiInputPolicy" if isinstance(env.observation_space, gym.spaces.Dict) else peer.policy
    if config is not None and config.obs_norm:
        env = normalized_env(env, config)
    return without_log_dir(algorithm(policy, env, seed=seed, verbose=0, **kwargs))


def normalized_env(env: Any, config: SACConfig) -> Any:
    """The peer's env behind SB3's VecNormalize: observations normalised by their running mean and variance,
    updated on each training step, clipped at obs_norm_clip, epsilon 1e-8, as softac's obs_norm (rewards left
    alone); SB3's Monitor inside, as SB3 adds it to an env it wraps itself, so that episodes are reported."""
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    from softac.learner.normalization import EPSILON

    return VecNormalize(DummyVecEnv([lambda: Monitor(env)]), norm_obs=True, norm_reward=False,
                        clip_obs=config.obs_norm_clip, gamma=config.gamma, epsilon=EPSILON)


def without_log_dir(model):
    """SB3's learn() otherwise configures a logger that makes an empty SB3-<time> directory in the temp dir
    on every call, even at verbose=0; softac writes the run's logs itself."""
    from stable_baselines3.common.logger import Logger

    model.set_logger(Logger(folder=None, output_formats=[]))
    return model


# the replay buffer's arrays (SB3's ReplayBuffer, which SBX uses too; its DictReplayBuffer keeps observations
# as a dict of arrays; its HerReplayBuffer adds where each episode starts and how long it is)

def peer_version(framework: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(PEERS[framework].distribution)
    except PackageNotFoundError:
        return "unknown"
