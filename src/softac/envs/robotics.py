"""Gymnasium-Robotics (the `robotics` extra): its goal envs (Fetch, the mazes, the Shadow hand, Adroit,
Franka kitchen) register when the package is imported, which softac does for their ids."""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import io

from softac.errors import EnvError

INSTALL_HINT = "pip install 'softac[robotics]'"
# ids Gymnasium-Robotics registers when imported; softac imports it for them
ROBOTICS_PREFIXES = ("Fetch", "PointMaze", "AntMaze", "HandReach", "HandManipulate", "AdroitHand", "FrankaKitchen")
# its Fetch envs fail to construct with later MuJoCo releases (AssertionError in mujoco_utils.set_joint_qpos)
ROBOTICS_MUJOCO = ((3, 8, 1), (3, 12, 0))


def is_robotics_id(env_id: str) -> bool:
    """One of the ids Gymnasium-Robotics registers (`module:EnvId` is the module's, whatever EnvId)."""
    return ":" not in env_id and env_id.startswith(ROBOTICS_PREFIXES)


def resolve(env_id: str) -> str:
    """Import Gymnasium-Robotics, which registers its envs, when `env_id` is one of them and not registered."""
    import gymnasium as gym

    if env_id in gym.registry or not is_robotics_id(env_id):
        return env_id
    if importlib.util.find_spec("gymnasium_robotics") is None:
        raise EnvError(f"env '{env_id}' comes from Gymnasium-Robotics, which is not installed: {INSTALL_HINT}")
    import warnings

    with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        warnings.simplefilter("ignore")
        importlib.import_module("gymnasium_robotics")
    return env_id


def mujoco_problem() -> str | None:
    """Why the installed MuJoCo cannot run Gymnasium-Robotics' envs, or None."""
    try:
        import mujoco
    except ImportError:
        return None
    have = tuple(int(p) for p in mujoco.__version__.split(".")[:3] if p.isdigit())
    low, high = ROBOTICS_MUJOCO
    if low <= have < high:
        return None
    return (f"Gymnasium-Robotics' envs need MuJoCo {'.'.join(map(str, low))} up to (not including) "
            f"{'.'.join(map(str, high))}, and MuJoCo {mujoco.__version__} is installed: {INSTALL_HINT}")
