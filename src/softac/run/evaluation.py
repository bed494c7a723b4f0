"""Evaluate a policy: mean and std of the return over N episodes (and the success rate, for envs that report
success in info["is_success"], as goal envs do).

Episodes run side by side on up to `MAX_PARALLEL` envs with one batched
policy call per step, which makes long evaluations several times faster than
one episode after another. Episode i always starts from seed `seed + i`, so an
evaluation is a deterministic function of the policy (and, when stochastic, of
the key).
"""

from __future__ import annotations

from typing import Any, Callable, Protocol

import gymnasium as gym
import numpy as np

from softac.envs.make import EnvError, EnvFailed, EnvSource, copy_env, env_name, observation_array, success_of


class Evaluable(Protocol):
    """What `evaluate` needs of an agent (softac.SAC is one): its config (for the eval seed), its env, and
    predict(). Typed by shape, so this module never imports the agent."""
    config: Any
    env_source: EnvSource

    def predict(self, obs: Any, deterministic: bool = True) -> np.ndarray: ...  # and policy=, when evaluate gets one

MAX_PARALLEL = 32
EVAL_SEED_OFFSET = 1_000_000


def run_episodes(policy: Callable[[np.ndarray], np.ndarray], make_env: Callable[[], gym.Env], episodes: int,
                 seed: int, envs: list[gym.Env] | None = None,
                 should_stop: Callable[[], bool] | None = None) -> dict[str, Any]:
    """Run `episodes` episodes; `policy` maps a batch of observations to env actions."""
    envs = envs if envs is not None else [make_env() for _ in range(min(episodes, MAX_PARALLEL))]
    returns = np.zeros(episodes)
    lengths = np.zeros(episodes, np.int64)
    successes = np.full(episodes, np.nan)  # at each episode's last step; nan where the env reports none
    terms: dict[str, np.ndarray] = {}  # per-episode sums of the env's reward terms (info["reward_*"])
    next_episode = 0
    active: dict[int, int] = {}  # env slot -> episode index
    obs = [None] * len(envs)

    def start(slot: int) -> None:
        nonlocal next_episode
        ep = next_episode
        next_episode += 1
        try:
            o, _ = envs[slot].reset(seed=seed + ep)
        except Exception as exc:
            raise EnvFailed(f"env {env_name(envs[slot])} raised in reset during evaluation: "
                           f"{type(exc).__name__}: {exc}".splitlines()[0]) from None
        obs[slot] = observation_array(o)
        active[slot] = ep

    for slot in range(min(len(envs), episodes)):
        start(slot)
    while active:
        if should_stop is not None and should_stop():
            break
        slots = sorted(active)
        actions = policy(np.stack([obs[s] for s in slots]))
        for slot, action in zip(slots, actions):
            ep = active[slot]
            try:
                o, r, terminated, truncated, info = envs[slot].step(action)
            except Exception as exc:
                raise EnvFailed(f"env {env_name(envs[slot])} raised in step during evaluation: "
                               f"{type(exc).__name__}: {exc}".splitlines()[0]) from None
            returns[ep] += float(r)
            lengths[ep] += 1
            add_reward_terms(terms, info, ep, episodes)
            obs[slot] = observation_array(o)
            if terminated or truncated:
                success = success_of(info)
                if success is not None:
                    successes[ep] = success
                del active[slot]
                if next_episode < episodes:
                    start(slot)
    return summarize(returns, lengths, terms, successes)


def add_reward_terms(terms: dict[str, np.ndarray], info: Any, episode: int, episodes: int) -> None:
    """Add the scalar `reward_*` entries of a step's info (MuJoCo envs report their reward's parts there:
    Pusher's reward_near, reward_dist, reward_ctrl) to the episode's sums."""
    if not isinstance(info, dict):
        return
    for key, value in info.items():
        if key.startswith("reward_") and isinstance(value, (int, float, np.number)) and not isinstance(value, bool):
            if key not in terms:
                terms[key] = np.zeros(episodes)
            terms[key][episode] += float(value)


def run_on_copies(policy: Callable[[np.ndarray], np.ndarray], source: EnvSource, episodes: int,
                  seed: int) -> dict[str, Any]:
    """`run_episodes` on fresh copies of `source` (an id or an instance), closed afterwards."""
    envs = [copy_env(source) for _ in range(min(episodes, MAX_PARALLEL))]
    try:
        return run_episodes(policy, lambda: copy_env(source), episodes, seed, envs=envs)
    finally:
        for env in envs:
            if env is not source:
                env.close()


def summarize(returns: np.ndarray, lengths: np.ndarray, terms: dict[str, np.ndarray] | None = None,
              successes: np.ndarray | None = None) -> dict[str, Any]:
    """`reward_terms`: the mean per-episode sum of each reward term the env reports in `info`;
    `success_rate`: the share of episodes that ended in success, None when the env reports no success."""
    reported = successes[np.isfinite(successes)] if successes is not None else np.zeros(0)
    return {
        "mean_return": float(np.mean(returns)),
        "std_return": float(np.std(returns)),
        "min_return": float(np.min(returns)),
        "max_return": float(np.max(returns)),
        "mean_length": float(np.mean(lengths)),
        "episodes": int(len(returns)),
        "returns": [float(r) for r in returns],
        "lengths": [int(n) for n in lengths],
        "reward_terms": {k: float(np.mean(v)) for k, v in sorted((terms or {}).items())},
        "success_rate": float(np.mean(reported)) if reported.size else None,
        "successes": [None if not np.isfinite(s) else bool(s) for s in successes] if reported.size else None,
    }


def acting(agent: Evaluable, deterministic: bool = True,
           policy: str = "deployed") -> Callable[[np.ndarray], np.ndarray]:
    """obs -> action with `agent.predict` and one of its policies ("deployed", "actor", "average")."""
    if policy == "deployed":  # `policy` only when asked for: a wrapped predict(obs, deterministic) keeps working
        return lambda obs: agent.predict(obs, deterministic=deterministic)
    return lambda obs: agent.predict(obs, deterministic=deterministic, policy=policy)


def evaluate(agent: Evaluable, episodes: int = 10, deterministic: bool = True, seed: int | None = None,
             env: Any = None, policy: str = "deployed") -> dict[str, Any]:
    """Mean/std return of `agent` over `episodes` episodes on fresh copies of its env (deterministic ones of an
    agent that collects on the device: on device envs, at once). The default seed is the one training's
    evaluations use, so the `last` checkpoint of a finished run gives its final evaluation again.
    `policy`: "deployed", "actor" or "average" (SAC.predict)."""
    if episodes < 1:
        raise EnvError("episodes must be >= 1")
    seed = agent.config.seed + EVAL_SEED_OFFSET if seed is None else seed
    source = env if env is not None else agent.env_source
    from softac.replay.device_collector import DeviceCollector

    if deterministic and env is None and isinstance(getattr(agent, "collector", None), DeviceCollector):
        # a run collected on the device evaluates there, all episodes at once, as its training's evaluations did
        from softac.run.device_transitions import device_episodes

        stats = summarize(*device_episodes(agent.learner, agent.collector, episodes, seed, policy))
    else:
        stats = run_on_copies(acting(agent, deterministic, policy), source, episodes, seed)
    stats["deterministic"] = deterministic
    stats["policy"] = policy
    stats["env_id"] = env_name(source)
    return stats
