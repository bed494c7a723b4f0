"""The DeepMind Control Suite (the `dmc` extra: dm_control and Shimmy) as Gymnasium envs softac can train.

Ids: Shimmy's `dm_control/DOMAIN-TASK-v0`, or the short `dmc:DOMAIN-TASK`. softac registers them with its
own entry point (`make_suite_env`, importable, so env workers can make them), which gives

- a flat observation: the task's observation arrays concatenated in the task's own order (dm_control's
  observation spec, what its `flatten_observation` and the DrQ and TD-MPC2 code give), each row-major;
  the env's `observation_keys` lists (key, size) in that order;
- dm_control's time limit (1000 steps in the suite) as a truncation, never a termination (Shimmy's rule:
  a last step with discount > 0 is truncated);
- the exact state for resume (`save_state`/`load_state`, envs.get_env_state's protocol): the physics with
  MuJoCo's integration signature, the model fields the suite's tasks set when an episode starts (targets'
  positions and sizes, colours, damping, terrain), the task's RandomState, the step counter and reset flag;
- rendering for `softac video` and the report: camera 0, 2 for quadruped (as DrQ and TD-MPC2 film them).
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import os
import sys
import warnings
from typing import Any

import numpy as np

from softac.config.names import DMC_PREFIX, long_id

INSTALL_HINT = "pip install 'softac[dmc]'"
CAMERAS = {"quadruped": 2}  # the domain's camera in videos (else 0), as DrQ and TD-MPC2 use
# model fields the suite's tasks write in initialize_episode (reacher's and finger's targets, finger's
# damping and colours, quadruped-escape's terrain, ...): saved with the physics, so a resumed episode is the
# episode it was
MODEL_FIELDS = ("geom_pos", "geom_quat", "geom_size", "geom_rgba", "site_pos", "site_quat", "site_size",
                "site_rgba", "body_pos", "body_quat", "body_mass", "dof_damping", "mat_rgba", "hfield_data")
RNG_SIZE = 624 + 3  # a RandomState's MT19937 key, its position, has_gauss and cached_gaussian


def _import_quietly(module: str):
    """dm_control fixes its OpenGL backend when first imported (MUJOCO_GL, else GLFW, which needs a display,
    and warns without one): on a headless machine softac first picks the backend that works here (EGL, else
    OSMesa; none: rendering off, training unaffected), as `softac video` does for Gymnasium's envs."""
    if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY") and "dm_control" not in sys.modules:
        from softac.base.opengl import working_gl_backend

        if working_gl_backend() is None:
            os.environ["MUJOCO_GL"] = "disable"  # rendering then fails with gl.NO_GL_MESSAGE
    with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        warnings.simplefilter("ignore")
        return importlib.import_module(module)


def suite():
    """dm_control.suite, imported as softac imports it (the OpenGL backend chosen first)."""
    from softac.errors import EnvError

    if importlib.util.find_spec("dm_control") is None or importlib.util.find_spec("shimmy") is None:
        raise EnvError(f"the DeepMind Control Suite needs dm_control and Shimmy, which are not installed: {INSTALL_HINT}")
    return _import_quietly("dm_control.suite")


def suite_tasks() -> list[tuple[str, str]]:
    return list(suite().ALL_TASKS)


def resolve(env_id: str) -> str:
    """`dmc:DOMAIN-TASK` or `dm_control/DOMAIN-TASK-v0` -> the latter, the suite's tasks registered."""
    env_id = long_id(env_id)
    register(env_id)
    return env_id


def register(env_id: str) -> None:
    """Register the suite's tasks under Shimmy's ids with softac's entry point (replacing Shimmy's own
    registration, whose entry point cannot be pickled for env workers)."""
    import gymnasium as gym
    from gymnasium.envs.registration import EnvSpec

    if env_id in gym.registry and gym.registry[env_id].entry_point == f"{__name__}:make_suite_env":
        return
    for domain, task in suite_tasks():
        gym.registry[f"{DMC_PREFIX}{domain}-{task}-v0"] = EnvSpec(
            id=f"{DMC_PREFIX}{domain}-{task}-v0", entry_point=f"{__name__}:make_suite_env",
            kwargs={"domain": domain, "task": task}, max_episode_steps=None)


def make_suite_env(domain: str, task: str, render_mode: str | None = None, width: int = 320, height: int = 240,
                   camera_id: int | None = None, task_kwargs: dict | None = None,
                   environment_kwargs: dict | None = None) -> Any:
    env = suite().load(domain, task, task_kwargs=task_kwargs, environment_kwargs=environment_kwargs)
    camera = CAMERAS.get(domain, 0) if camera_id is None else camera_id
    return suite_env_class()(env, render_mode, {"width": width, "height": height, "camera_id": camera})


_SUITE_CLASS = None


def suite_env_class() -> type:
    """DmcSuiteEnv: Shimmy's wrapper (imported on first use: softac imports without the extra) subclassed."""
    global _SUITE_CLASS
    if _SUITE_CLASS is None:
        _SUITE_CLASS = _define_suite_class(_import_quietly("shimmy.dm_control_compatibility").DmControlCompatibilityV0)
    return _SUITE_CLASS


def _define_suite_class(base: type) -> type:
    import gymnasium as gym
    import mujoco

    integration = mujoco.mjtState.mjSTATE_INTEGRATION

    class DmcSuiteEnv(base):
        """Shimmy's dm_control wrapper with a flat observation in the task's order and an exact state."""

        def __init__(self, env: Any, render_mode: str | None, render_kwargs: dict):
            super().__init__(env, render_mode=render_mode, render_kwargs=render_kwargs)
            spec = env.observation_spec()  # an OrderedDict in the task's order
            self.observation_keys = [(key, int(np.prod(array.shape, dtype=np.int64))) for key, array in spec.items()]
            size = sum(n for _, n in self.observation_keys)
            self.observation_space = gym.spaces.Box(-np.inf, np.inf, (size,), np.float64)

        def _flat(self, obs: dict) -> np.ndarray:
            return np.concatenate([np.asarray(obs[key], np.float64).reshape(-1) for key, _ in self.observation_keys])

        def reset(self, *, seed: int | None = None, options: dict | None = None):
            obs, info = super().reset(seed=seed, options=options)
            return self._flat(obs), info

        def step(self, action: np.ndarray):
            obs, reward, terminated, truncated, info = super().step(action)
            return self._flat(obs), float(reward), terminated, truncated, info

        # ---- exact state (envs.get_env_state's save_state/load_state protocol) ----

        def _parts(self) -> list[np.ndarray]:
            model = self._env.physics.model.ptr
            return [getattr(model, name) for name in MODEL_FIELDS if getattr(model, name).size]

        def save_state(self) -> np.ndarray:
            physics, env = self._env.physics, self._env
            key, words, pos, has_gauss, cached = env.task.random.get_state()
            assert key == "MT19937"
            rng = np.concatenate([np.asarray(words, np.float64), [pos, has_gauss, cached]])
            return np.concatenate([physics.get_state(sig=integration),
                                   *[np.asarray(part, np.float64).reshape(-1) for part in self._parts()],
                                   rng, [env._step_count, float(env._reset_next_step)]])

        def load_state(self, state: np.ndarray) -> None:
            physics, env = self._env.physics, self._env
            state = np.asarray(state, np.float64)
            n = mujoco.mj_stateSize(physics.model.ptr, integration)
            parts = self._parts()
            expected = n + sum(p.size for p in parts) + RNG_SIZE + 2
            if state.shape != (expected,):
                raise ValueError(f"a saved {self.spec.id if self.spec else 'dm_control'} state has {state.size} "
                                 f"values where this env has {expected}")
            physics.set_state(state[:n], sig=integration)
            at = n
            for part in parts:
                part[...] = state[at:at + part.size].reshape(part.shape).astype(part.dtype)
                at += part.size
            words, (pos, has_gauss, cached) = state[at:at + 624], state[at + 624:at + RNG_SIZE]
            env.task.random.set_state(("MT19937", words.astype(np.uint32), int(pos), int(has_gauss), float(cached)))
            at += RNG_SIZE
            env._step_count, env._reset_next_step = int(state[at]), bool(state[at + 1])
            physics.forward()

    return DmcSuiteEnv
