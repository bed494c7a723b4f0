"""Environments: make them from an id or an instance, check their spaces, step several together.

`EnvPool` is softac's own vector env. It steps its envs one after the other
(as Gymnasium's SyncVectorEnv does) but resets a finished env itself, so the
true final observation is always at hand for the replay buffer, whatever
Gymnasium 1.x's vector autoreset mode would have done. It can also save and
restore its envs' exact state (MuJoCo integration state, RNGs, time-limit
counters), which exact resume needs: MuJoCo envs, envs with a NumPy `state`
attribute (classic control), and any env whose unwrapped class has
`save_state() -> np.ndarray` and `load_state(array)`.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import io
import contextlib
from dataclasses import dataclass
from typing import Any, Callable, NamedTuple

import gymnasium as gym
import numpy as np
from gymnasium.envs.registration import EnvSpec

from softac.envs.families import family_of, family_of_entry_point
from softac.errors import EnvError, EnvFailed, SoftacError
from softac.envs.goals import DictLayout, dict_layout, dict_observation_space, is_goal_env
from softac.envs.pixels import (ImageStateLayout, ImageWithState, frame_stack_of, image_key_of, is_frame_stack_space,
                           is_image_space, with_image_wrappers, wrapper_of)

EnvSource = Any  # a Gymnasium id string or a gym.Env instance


def env_name(source: EnvSource | EnvSpec) -> str:
    if isinstance(source, str):
        return source
    if isinstance(source, EnvSpec):
        return source.id
    spec = getattr(source, "spec", None)
    return spec.id if spec is not None else type(getattr(source, "unwrapped", source)).__name__


def resolve_env_id(env_id: str) -> str:
    """Check that `env_id` is registered, importing `module` first for `module:EnvId`, and its family's package
    for a family's id (envs.families: `dmc:DOMAIN-TASK` is `dm_control/DOMAIN-TASK-v0`; Gymnasium-Robotics')."""
    env_id = env_id.strip()
    env_id = family_of(env_id).resolve(env_id)
    if env_id not in gym.registry:
        close = difflib.get_close_matches(env_id, list(gym.registry.keys()), n=3, cutoff=0.6)
        hint = f"; did you mean {', '.join(close)}?" if close else ""
        raise EnvError(f"unknown environment id '{env_id}'{hint}")
    return env_id


def make_env(source: EnvSource | EnvSpec, render_mode: str | None = None, **kwargs: Any) -> gym.Env:
    """A fresh env from an id or a spec, or the given instance itself. kwargs go to gym.make (e.g. width)."""
    if isinstance(source, gym.Env):
        return _flatten_obs_if_needed(source)
    if not isinstance(source, (str, EnvSpec)):
        raise EnvError(f"expected a Gymnasium env id or gym.Env instance, got {type(source).__name__}")
    env_id = resolve_env_id(source) if isinstance(source, str) else source
    if render_mode:
        kwargs["render_mode"] = render_mode
    try:
        with contextlib.redirect_stderr(io.StringIO()):
            env = gym.make(env_id, **kwargs)
    except EnvError:  # a family's own one line (envs.playground's missing robot models)
        raise
    except Exception as exc:
        entry = str(getattr(gym.spec(env_id) if isinstance(env_id, str) else env_id, "entry_point", ""))
        family = family_of_entry_point(entry)
        problem = family.problem() if family is not None else None
        if problem:
            raise EnvError(f"cannot make env '{env_name(env_id)}': {problem}") from None
        raise EnvError(f"cannot make env '{env_name(env_id)}': {type(exc).__name__}: {exc}".splitlines()[0]) from None
    return _flatten_obs_if_needed(env)


def copy_env(source: EnvSource, render_mode: str | None = None, **kwargs: Any) -> gym.Env:
    """Another env like `source`: made again from its id or spec, else a deep copy."""
    if isinstance(source, (str, EnvSpec)):
        return make_env(source, render_mode, **kwargs)
    spec = getattr(source, "spec", None)
    if spec is not None:
        if render_mode:
            kwargs["render_mode"] = render_mode
        try:
            return _flatten_obs_if_needed(gym.make(spec, **kwargs))
        except Exception:
            pass
    try:
        return _flatten_obs_if_needed(copy.deepcopy(source))
    except Exception as exc:
        raise EnvError(f"cannot make a second copy of env {env_name(source)} ({exc}); register it with "
                       "gymnasium.register and pass its id instead") from None


def _flatten_obs_if_needed(env: gym.Env) -> gym.Env:
    space = env.observation_space
    if isinstance(space, gym.spaces.Box) and len(space.shape) == 1 or is_image_space(space) \
            or is_frame_stack_space(space) or image_key_of(space) is not None:  # an image dict: ImageWithState
        return env
    try:
        gym.spaces.flatdim(space)
    except Exception:
        raise EnvError(f"env {env_name(env)}: observation space {space} cannot be flattened to a vector") from None
    return gym.wrappers.FlattenObservation(env)


class ActionRepeat(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Each action applied `repeat` times, the rewards summed; an episode that ends inside the repeat ends the
    step (the DMC papers' action repeat: 2 in SAC's, SimBa's and TD-MPC2's state runs, 8 in DrQ's cartpole)."""

    def __init__(self, env: gym.Env, repeat: int):
        gym.utils.RecordConstructorArgs.__init__(self, repeat=repeat)
        gym.Wrapper.__init__(self, env)
        self.repeat = int(repeat)

    def step(self, action):
        total = 0.0
        for _ in range(self.repeat):
            obs, reward, terminated, truncated, info = self.env.step(action)
            total += float(reward)
            if terminated or truncated:
                break
        return obs, total, terminated, truncated, info


def with_action_repeat(source: EnvSource, repeat: int) -> EnvSource:
    """`source` with each action repeated `repeat` times: an id becomes its Gymnasium spec with ActionRepeat
    among its wrappers (so copies and env workers make it the same way), an instance is wrapped."""
    if repeat == 1:
        return source
    if isinstance(source, gym.Env):
        return ActionRepeat(source, repeat)
    spec = gym.spec(resolve_env_id(source)) if isinstance(source, str) else source
    wrapper = gym.envs.registration.WrapperSpec("ActionRepeat", f"{__name__}:ActionRepeat", {"repeat": repeat})
    return dataclasses.replace(spec, additional_wrappers=(*spec.additional_wrappers, wrapper))


def training_env_source(env: EnvSource, config: Any) -> tuple[EnvSource, gym.Env]:
    """What a run makes its envs from, and a probe env made from it: `env` with config's action repeat and,
    where observations are images (config.pixels, or the env's own), the image wrappers after it (a repeated
    action yields one frame; softac.envs.pixels). For an instance, the probe is the (wrapped) instance itself, which
    is then the source too; for an id the caller closes the probe."""
    if config.pixels:  # MuJoCo's headless GL backend is chosen once per process, before it is imported
        from softac.base.opengl import choose_gl_backend

        choose_gl_backend()
    probe = make_env(env)
    if not (config.pixels or is_image_space(probe.observation_space) or image_key_of(probe.observation_space)):
        return with_action_repeat(env if isinstance(env, (str, EnvSpec)) else probe, config.action_repeat), probe
    raw_space = probe.observation_space
    if isinstance(env, (str, EnvSpec)):
        probe.close()
        base: EnvSource = gym.spec(resolve_env_id(env)) if isinstance(env, str) else env
    else:
        base = probe
    source = with_image_wrappers(with_action_repeat(base, config.action_repeat), raw_space, config.pixels,
                                 config.pixel_size, config.frame_stack)
    return source, make_env(source)


@dataclass(frozen=True)
class SpaceInfo:
    obs_dim: int
    act_dim: int
    low: np.ndarray
    high: np.ndarray
    layout: DictLayout | None = None  # a dict observation's keys in the flat vector (their space's order)
    goal_env: bool = False  # observation, achieved_goal, desired_goal and compute_reward: HER can train it
    image_shape: tuple[int, int, int, int] | None = None  # stacked image observations, uint8 [k, h, w, c]
    image_state: ImageStateLayout | None = None  # a dict of an image and state values, packed (ImageWithState)

    @property
    def image_state_dim(self) -> int:
        """The state values beside an image (0 for images alone)."""
        return 0 if self.image_state is None else self.image_state.state_dim


def check_spaces(env: gym.Env) -> SpaceInfo:
    """SAC needs a bounded 1-D Box action space; say clearly when it is not one."""
    name = env_name(env)
    space = env.action_space
    if not isinstance(space, gym.spaces.Box):
        raise EnvError(f"env {name} has a {type(space).__name__} action space; SAC needs a continuous Box space")
    if len(space.shape) != 1:
        raise EnvError(f"env {name} has a {len(space.shape)}-D action Box {space.shape}; SAC here needs a 1-D Box")
    low, high = np.asarray(space.low, np.float64), np.asarray(space.high, np.float64)
    if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high))):
        raise EnvError(f"env {name} has an unbounded action space; SAC needs finite low/high bounds "
                       "(wrap it with gymnasium.wrappers.ClipAction or RescaleAction)")
    if np.any(high <= low):
        raise EnvError(f"env {name} has action bounds with high <= low")
    obs_space = env.observation_space
    obs_dim = int(np.prod(obs_space.shape))
    image = tuple(int(n) for n in obs_space.shape) if is_frame_stack_space(obs_space) else None
    packed = wrapper_of(env, ImageWithState)
    dict_space = dict_observation_space(env) if packed is None else None
    layout = dict_layout(dict_space) if dict_space is not None else None
    return SpaceInfo(obs_dim, int(space.shape[0]), low.astype(np.float32), high.astype(np.float32), layout,
                     packed is None and is_goal_env(env), image, packed.layout if packed else None)


# ---- exact env state, for resume -----------------------------------------------

def _time_limit(env: gym.Env) -> gym.wrappers.TimeLimit | None:
    while isinstance(env, gym.Wrapper):
        if isinstance(env, gym.wrappers.TimeLimit):
            return env
        env = env.env
    return None


def _mujoco_parts(env: gym.Env):
    raw = env.unwrapped
    if hasattr(raw, "model") and hasattr(raw, "data"):
        try:
            import mujoco
        except ImportError:
            return None
        if isinstance(raw.model, mujoco.MjModel):
            return mujoco, raw.model, raw.data
    return None


def get_env_state(env: gym.Env) -> tuple[dict, np.ndarray | None]:
    """(JSON-able metadata, physics state array or None) that restore this env exactly."""
    raw = env.unwrapped
    meta: dict[str, Any] = {"kind": "none"}
    physics = None
    parts = _mujoco_parts(env)
    if callable(getattr(raw, "save_state", None)) and callable(getattr(raw, "load_state", None)):
        physics = np.asarray(raw.save_state(), np.float64)
        meta["kind"] = "protocol"
    elif parts is not None:
        mujoco, model, data = parts
        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        physics = np.empty(mujoco.mj_stateSize(model, spec), np.float64)
        mujoco.mj_getState(model, data, physics, spec)
        meta["kind"] = "mujoco"
    elif isinstance(getattr(raw, "state", None), np.ndarray):
        physics = np.array(raw.state)
        meta["kind"] = "state_attr"
    goal = getattr(raw, "goal", None)
    if isinstance(goal, np.ndarray):  # a goal env's goal lives beside the physics (Gymnasium-Robotics' envs)
        meta["goal"] = {"values": goal.tolist(), "dtype": str(goal.dtype)}
    rng = getattr(raw, "_np_random", None)
    meta["np_random"] = rng.bit_generator.state if rng is not None else None
    limit = _time_limit(env)
    meta["elapsed_steps"] = getattr(limit, "_elapsed_steps", None) if limit else None
    return meta, physics


def set_env_state(env: gym.Env, meta: dict, physics: np.ndarray | None) -> bool:
    """Restore what `get_env_state` captured; False when this env cannot be restored exactly."""
    raw = env.unwrapped
    if meta["kind"] == "protocol" and physics is not None and callable(getattr(raw, "load_state", None)):
        raw.load_state(np.array(physics))
    elif meta["kind"] == "mujoco" and physics is not None and _mujoco_parts(env) is not None:
        mujoco, model, data = _mujoco_parts(env)
        mujoco.mj_setState(model, data, np.asarray(physics, np.float64), mujoco.mjtState.mjSTATE_INTEGRATION)
        mujoco.mj_forward(model, data)
    elif meta["kind"] == "state_attr" and physics is not None:
        raw.state = np.array(physics)
    else:
        return False
    if meta.get("goal") is not None:
        raw.goal = np.array(meta["goal"]["values"], dtype=meta["goal"]["dtype"])
    if meta.get("np_random") is not None and getattr(raw, "_np_random", None) is not None:
        raw._np_random.bit_generator.state = meta["np_random"]
    limit = _time_limit(env)
    if limit is not None and meta.get("elapsed_steps") is not None:
        limit._elapsed_steps = meta["elapsed_steps"]
    return True


# ---- several envs stepped together ---------------------------------------------

class Episode(NamedTuple):
    """A finished training episode: its env's index, return, length, and success (the env's
    info["is_success"], or info["success"] as Gymnasium-Robotics' mazes say, at its last step; None when
    the env reports neither)."""
    env: int
    ret: float
    length: int
    success: float | None = None
    step: int | None = None  # the run's env steps when it ended, where a chunk of many steps knows (else its end)


def observation_array(obs: Any) -> np.ndarray:
    """An env's observation as the policy takes it: images (uint8 [k, h, w, c] or [h, w, c]) as they are, else a
    float32 vector."""
    obs = np.asarray(obs)
    return obs if obs.dtype == np.uint8 and obs.ndim in (3, 4) else obs.astype(np.float32).reshape(-1)


def success_of(info: Any) -> float | None:
    """1.0 or 0.0 from a step's info["is_success"] (or "success"), None when the env reports neither."""
    if not isinstance(info, dict):
        return None
    value = info.get("is_success", info.get("success"))
    if value is None:
        return None
    try:
        return float(bool(np.asarray(value).reshape(-1)[0]))
    except (TypeError, ValueError, IndexError):
        return None


@dataclass
class StepResult:
    next_obs: np.ndarray  # the true next observation (the final one where an episode ended)
    rewards: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    finished: list[Episode]


class EnvPool:
    """`n` envs stepped one after the other. `first_index` is the index of its first env among all the run's
    envs (an env worker's pool holds a slice of them), so each env's reset seeds are the same wherever it runs."""

    def __init__(self, make: Callable[[int], gym.Env], n: int, seed: int, name: str, first_index: int = 0):
        self.name = name
        self.envs = [make(i) for i in range(n)]
        self.seed = seed
        self.n = n
        self.first_index = first_index
        space = self.envs[0].observation_space
        # images stay uint8 (they are stored and sent as they are); every other observation a float32 vector
        images = is_image_space(space) or is_frame_stack_space(space)
        self.obs_shape = tuple(space.shape) if images else (int(np.prod(space.shape)),)
        self.obs_dtype = np.uint8 if images else np.float32
        self.obs = np.zeros((n, *self.obs_shape), self.obs_dtype)
        self.episode_return = np.zeros(n, np.float64)
        self.episode_length = np.zeros(n, np.int64)
        self.resets = np.zeros(n, np.int64)  # resets so far per env: each reset gets its own seed

    def _reset_one(self, i: int, step: int) -> None:
        # a distinct seed per (env, reset), so an episode's start does not depend on the others
        seed = (self.seed * 1_000_003 + (self.first_index + i) * 7919 + int(self.resets[i])) % (2**31)
        try:
            obs, _ = self.envs[i].reset(seed=seed)
        except Exception as exc:
            raise EnvFailed(f"env {self.name} raised in reset at step {step}: {type(exc).__name__}: {exc}") from None
        self.obs[i] = np.asarray(obs, self.obs_dtype).reshape(self.obs_shape)
        self.resets[i] += 1
        self.episode_return[i] = 0.0
        self.episode_length[i] = 0

    def reset(self, step: int = 0) -> np.ndarray:
        for i in range(self.n):
            self._reset_one(i, step)
        return self.obs

    def step(self, actions: np.ndarray, step: int) -> StepResult:
        n = self.n
        next_obs = np.empty_like(self.obs)
        rewards = np.empty(n, np.float32)
        terminated = np.empty(n, bool)
        truncated = np.empty(n, bool)
        finished, infos = [], [None] * n
        for i, env in enumerate(self.envs):
            try:
                obs, reward, term, trunc, infos[i] = env.step(actions[i])
            except Exception as exc:
                raise EnvFailed(f"env {self.name} raised in step at step {step}: "
                               f"{type(exc).__name__}: {exc}".splitlines()[0]) from None
            next_obs[i] = np.asarray(obs, self.obs_dtype).reshape(self.obs_shape)
            rewards[i], terminated[i], truncated[i] = reward, term, trunc
            self.episode_return[i] += float(reward)
            self.episode_length[i] += 1
        if not (np.all(np.isfinite(next_obs)) and np.all(np.isfinite(rewards))):
            what = "observation" if not np.all(np.isfinite(next_obs)) else "reward"
            raise EnvFailed(f"env {self.name} returned a non-finite {what} at step {step}")
        self.obs = next_obs.copy()
        for i in np.flatnonzero(terminated | truncated):
            finished.append(Episode(int(i), float(self.episode_return[i]), int(self.episode_length[i]),
                                    success_of(infos[i])))
            self._reset_one(int(i), step)
        return StepResult(next_obs, rewards, terminated, truncated, finished)

    def get_state(self) -> tuple[dict, dict[str, np.ndarray]]:
        metas, arrays = [], {"obs": self.obs.copy()}
        for i, env in enumerate(self.envs):
            meta, physics = get_env_state(env)
            metas.append(meta)
            if physics is not None:
                arrays[f"physics_{i}"] = physics
        meta = {"envs": metas, "resets": self.resets.tolist(),
                "episode_return": self.episode_return.tolist(), "episode_length": self.episode_length.tolist()}
        return meta, arrays

    def set_state(self, meta: dict, arrays: dict[str, np.ndarray], step: int) -> bool:
        """Restore every env; returns False (and starts fresh episodes) where that is impossible."""
        if len(meta["envs"]) != self.n:
            raise SoftacError(f"checkpoint has {len(meta['envs'])} envs but n_envs={self.n}")
        self.resets = np.asarray(meta["resets"], np.int64)
        exact = True
        for i, env in enumerate(self.envs):
            env.reset(seed=0)  # Gymnasium requires a reset before step; the state is overwritten next
            if not set_env_state(env, meta["envs"][i], arrays.get(f"physics_{i}")):
                exact = False
        if exact:
            self.obs = np.asarray(arrays["obs"], self.obs_dtype).copy()
            for env, obs in zip(self.envs, self.obs):
                if (stack := frame_stack_of(env)) is not None:  # the frames an image observation stacks live there
                    stack.load_frames(obs)
            self.episode_return = np.asarray(meta["episode_return"], np.float64)
            self.episode_length = np.asarray(meta["episode_length"], np.int64)
        else:
            self.reset(step)
        return exact

    def apply(self, fn: Callable[[gym.Env], Any]) -> list[Any]:
        """`fn(env)` for each env, in order (a callback's curriculum changes a physics parameter this way)."""
        return [fn(env) for env in self.envs]

    def close(self) -> None:
        for env in self.envs:
            with contextlib.suppress(Exception):
                env.close()
