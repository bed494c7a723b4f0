"""MuJoCo Playground (the `playground` extra: its envs, pure JAX on MJX) as Gymnasium envs softac can train.

Ids: `playground:NAME` (any env Playground registers: its DeepMind Control Suite ports such as CheetahRun,
WalkerWalk or HumanoidWalk, its locomotion and manipulation tasks), or the registered `playground/NAME`.
softac registers them with its own entry point (`make_playground_env`, importable, so env workers can make
them), which gives each one env on the host, its `reset` and `step` jitted once per process and env:

- MJX's JAX implementation (`impl=jax`), which runs on every CPU and GPU: Playground's default, `warp`, needs
  the NVIDIA Warp release its MJX was built with (mujoco-mjx 3.11 pins warp-lang 1.14; Playground pulls later);
- the observation as a float32 vector: a dict observation's `state` entry (what Playground's own trainers give
  the policy; `privileged_state` is the critic's in their asymmetric recipes, which softac does not run);
- actions in [-1, 1] (Playground's envs scale them to their actuators);
- Playground's `done` (a fallen robot, a NaN state) as a termination, and its `episode_length` (1000 for the
  suite's ports) as a truncation, never a termination; its `action_repeat` applied here, the rewards summed;
- the exact state for resume (`save_state`/`load_state`, envs.get_env_state's protocol): every leaf of the
  env's state pytree (MJX data, observation, info with its key) and the key the next reset draws from;
- rendering through MuJoCo on the host (camera 0 where the model has one, as the suite films them).

The device source that steps thousands of these inside the update's jit is issue 67's next part; this family
is what it evaluates, films and resumes with.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import warnings
from typing import Any, NamedTuple

import numpy as np

from softac.config.names import PLAYGROUND_PREFIXES, is_playground_id
from softac.errors import EnvError

PREFIX, SHORT_PREFIX = PLAYGROUND_PREFIXES
INSTALL_HINT = "pip install 'softac[playground]'"
IMPL = "jax"  # MJX's JAX implementation (see the module's docstring)


def env_name_of(env_id: str) -> str:
    """`playground:CheetahRun` or `playground/CheetahRun` -> `CheetahRun`."""
    for prefix in (SHORT_PREFIX, PREFIX):
        if env_id.startswith(prefix):
            return env_id[len(prefix):]
    return env_id


def problem() -> str | None:
    """Why the installed packages cannot make Playground's envs, or None."""
    missing = [m for m in ("mujoco_playground", "mujoco.mjx") if not _module_exists(m)]
    if missing:
        return f"MuJoCo Playground's envs need {' and '.join(missing)}, which is not installed: {INSTALL_HINT}"
    return None


def _module_exists(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except ModuleNotFoundError:
        return False


def registry():
    """mujoco_playground.registry, imported quietly (it logs and warns about its optional GPU backends)."""
    trouble = problem()
    if trouble:
        raise EnvError(trouble)
    with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        warnings.simplefilter("ignore")
        from mujoco_playground import registry as reg
    return reg


def env_names() -> list[str]:
    return list(registry().ALL_ENVS)


def resolve(env_id: str) -> str:
    """`playground:NAME` or `playground/NAME` -> the latter, registered; an unknown NAME is one line naming the
    closest of Playground's envs."""
    import difflib

    import gymnasium as gym
    from gymnasium.envs.registration import EnvSpec

    name = env_name_of(env_id.strip())
    long = f"{PREFIX}{name}"
    if long in gym.registry and gym.registry[long].entry_point == f"{__name__}:make_playground_env":
        return long
    names = env_names()
    if name not in names:
        close = difflib.get_close_matches(name, names, n=3, cutoff=0.6)
        hint = f"; did you mean {', '.join(SHORT_PREFIX + c for c in close)}?" if close else ""
        raise EnvError(f"unknown MuJoCo Playground env '{name}'{hint} ({len(names)} envs: "
                       f"python -c 'from mujoco_playground import registry; print(registry.ALL_ENVS)')")
    config = registry().get_default_config(name)
    steps = int(config.episode_length) // max(1, int(getattr(config, "action_repeat", 1)))
    gym.registry[long] = EnvSpec(id=long, entry_point=f"{__name__}:make_playground_env", kwargs={"name": name},
                                 max_episode_steps=steps)
    return long


_LOADED: dict[str, Any] = {}  # name -> (env, jitted reset, jitted step): compiled once per process


def load(name: str):
    """Playground's env NAME with MJX's JAX implementation, and its jitted reset and step (shared by every
    env of that name in the process: one compile each)."""
    if name in _LOADED:
        return _LOADED[name]
    reg = registry()
    config = reg.get_default_config(name)
    overrides = {"impl": IMPL} if "impl" in config else None
    if getattr(config, "vision", False):
        overrides = {**(overrides or {}), "vision": False}
    try:
        with contextlib.redirect_stdout(io.StringIO()) as out, contextlib.redirect_stderr(io.StringIO()) as err:
            env = reg.load(name, config_overrides=overrides)
    except Exception as exc:
        raise EnvError(_load_failure(name, exc, out.getvalue() + err.getvalue())) from None
    import jax

    _LOADED[name] = (env, config, jax.jit(env.reset), jax.jit(env.step))
    return _LOADED[name]


def _load_failure(name: str, exc: Exception, output: str) -> str:
    """One line for a Playground env that would not load: the robot models it fetches at first use (MuJoCo
    Menagerie, a git clone from GitHub) named with where they go, else the error's first line."""
    try:
        from mujoco_playground._src import mjx_env
        menagerie, sha = mjx_env.MENAGERIE_PATH, mjx_env.MENAGERIE_COMMIT_SHA
    except Exception:  # a Playground without these names: say what failed
        menagerie = None
    if menagerie is not None and ("menagerie" in output.lower() or "git" in f"{exc}".lower()) \
            and not menagerie.exists():
        return (f"MuJoCo Playground env '{name}' needs the robot models of MuJoCo Menagerie, which Playground clones "
                f"from GitHub at first use and could not: git clone https://github.com/google-deepmind/mujoco_menagerie "
                f"{menagerie} && git -C {menagerie} checkout {sha}")
    first = (f"{type(exc).__name__}: {exc}".strip().splitlines() or [type(exc).__name__])[0]
    return f"cannot load MuJoCo Playground env '{name}': {first}"


class DeviceEnv(NamedTuple):
    """What device collection steps (softac.envs.device_envs): Playground's env itself, its episode length in its
    own steps and its action repeat."""
    env: Any
    episode_length: int
    action_repeat: int


def device_env(env_id: str) -> DeviceEnv:
    name = env_name_of(resolve(env_id))
    env, config, _, _ = load(name)
    repeat = max(1, int(getattr(config, "action_repeat", 1)))
    return DeviceEnv(env, int(config.episode_length) // repeat, repeat)


def make_playground_env(name: str, render_mode: str | None = None, width: int = 320, height: int = 240,
                        camera_id: int | None = None) -> Any:
    return playground_env_class()(name, render_mode, width, height, camera_id)


_ENV_CLASS = None


def playground_env_class() -> type:
    """PlaygroundEnv, defined on first use (softac imports without the extra, and without JAX until needed)."""
    global _ENV_CLASS
    if _ENV_CLASS is None:
        _ENV_CLASS = _define_env_class()
    return _ENV_CLASS


def state_observation(obs: Any) -> Any:
    """The policy's observation: a dict observation's `state` entry, else the observation itself."""
    return obs["state"] if isinstance(obs, dict) or hasattr(obs, "keys") else obs


def _define_env_class() -> type:
    import gymnasium as gym
    import jax
    import jax.numpy as jnp

    class PlaygroundEnv(gym.Env):
        """One MuJoCo Playground env on the host, as a Gymnasium env."""

        metadata = {"render_modes": ["rgb_array"]}

        def __init__(self, name: str, render_mode: str | None = None, width: int = 320, height: int = 240,
                     camera_id: int | None = None):
            self.name = name
            self._env, config, self._reset, self._step = load(name)
            self.action_repeat = max(1, int(getattr(config, "action_repeat", 1)))
            self.metadata = {**self.metadata, "render_fps": int(round(1.0 / (self._env.dt * self.action_repeat)))}
            size = self._env.observation_size
            if isinstance(size, dict) or hasattr(size, "keys"):
                if "state" not in size:
                    raise EnvError(f"MuJoCo Playground env '{name}' has dict observations without a 'state' entry "
                                   f"({', '.join(size)}): softac trains on a vector observation")
                size = size["state"]
            dim = int(np.prod(size)) if isinstance(size, tuple) else int(size)
            self.observation_space = gym.spaces.Box(-np.inf, np.inf, (dim,), np.float32)
            self.action_space = gym.spaces.Box(-1.0, 1.0, (int(self._env.action_size),), np.float32)
            self.render_mode, self.width, self.height = render_mode, int(width), int(height)
            self.camera_id = (0 if self._env.mj_model.ncam > 0 else -1) if camera_id is None else int(camera_id)
            self._key = jax.random.PRNGKey(0)
            self._state = None
            self._renderer = None

        def _obs(self) -> np.ndarray:
            return np.asarray(state_observation(self._state.obs), np.float32).reshape(-1)

        def reset(self, *, seed: int | None = None, options: dict | None = None):
            super().reset(seed=seed)
            if seed is not None:
                self._key = jax.random.PRNGKey(int(seed) % 2**32)
            self._key, key = jax.random.split(self._key)
            self._state = self._reset(key)
            return self._obs(), {}

        def step(self, action):
            if self._state is None:
                raise gym.error.ResetNeeded("call reset() before step()")
            action = jnp.asarray(np.clip(np.asarray(action, np.float32), -1.0, 1.0))
            reward, done = 0.0, False
            for _ in range(self.action_repeat):
                self._state = self._step(self._state, action)
                reward += float(self._state.reward)
                done = bool(self._state.done)
                if done:
                    break
            return self._obs(), reward, done, False, {}

        # ---- exact state (envs.get_env_state's save_state/load_state protocol) ----

        def _template(self):
            return jax.eval_shape(self._reset, self._key)

        def save_state(self) -> np.ndarray:
            if self._state is None:
                self.reset()
            leaves = jax.tree_util.tree_leaves((self._state, self._key))
            return np.concatenate([np.asarray(leaf).astype(np.float64).reshape(-1) for leaf in leaves])

        def load_state(self, state: np.ndarray) -> None:
            state = np.asarray(state, np.float64)
            template = (self._template(), jax.ShapeDtypeStruct(self._key.shape, self._key.dtype))
            leaves, tree = jax.tree_util.tree_flatten(template)
            expected = sum(int(np.prod(leaf.shape)) for leaf in leaves)
            if state.shape != (expected,):
                raise ValueError(f"a saved playground/{self.name} state has {state.size} values where this env "
                                 f"has {expected}")
            values, at = [], 0
            for leaf in leaves:
                n = int(np.prod(leaf.shape))
                values.append(jnp.asarray(state[at:at + n].reshape(leaf.shape).astype(leaf.dtype)))
                at += n
            self._state, self._key = jax.tree_util.tree_unflatten(tree, values)

        # ---- rendering through MuJoCo on the host ----

        def render(self):
            if self.render_mode != "rgb_array":
                return None
            import mujoco

            model = self._env.mj_model
            if self._renderer is None:
                self._renderer = mujoco.Renderer(model, height=self.height, width=self.width)
                self._data = mujoco.MjData(model)
            if self._state is None:
                self.reset()
            data, mjx_data = self._data, self._state.data
            data.qpos[:], data.qvel[:] = np.asarray(mjx_data.qpos), np.asarray(mjx_data.qvel)
            if model.nmocap:
                data.mocap_pos[:], data.mocap_quat[:] = np.asarray(mjx_data.mocap_pos), np.asarray(mjx_data.mocap_quat)
            mujoco.mj_forward(model, data)
            self._renderer.update_scene(data, camera=self.camera_id)
            return self._renderer.render()

        def close(self):
            if self._renderer is not None:
                self._renderer.close()
                self._renderer = None

    return PlaygroundEnv
