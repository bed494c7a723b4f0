"""The env families softac knows by their ids, one row each: which ids are the family's, how an id becomes a
registered Gymnasium id (importing or registering the family's package, or a one-line error naming what to
install: each family module's INSTALL_HINT), why the installed packages cannot make its envs, and which of
its envs render at a given size.
Any other Gymnasium id, or `module:EnvId`, is the `gymnasium` family's. A family's default preset is the
config's knowledge (softac.config.names: the id forms that choose presets), since the config imports no env.

Adding a family: its module here in envs/ (a resolver; the exact env state where Gymnasium's is not enough)
and a row in FAMILIES, before gymnasium's (which takes every id); an id form in config/names.py and a preset
file only if it has a default preset.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Callable

from softac.config.names import is_dmc_id
from softac.envs import dmc, playground, robotics
from softac.errors import EnvError


@dataclass(frozen=True)
class EnvFamily:
    name: str
    owns: Callable[[str], bool]  # whether an id, as the user wrote it, is the family's
    resolve: Callable[[str], str]  # the id -> a registered Gymnasium id (EnvError when it cannot be)
    problem: Callable[[], str | None] = lambda: None  # why the installed packages cannot make its envs, or None
    entry_points: tuple[str, ...] = ()  # its envs' entry points (a made env is the family's by them)
    sized_rendering: tuple[str, ...] = ()  # the entry points whose envs render at a given width and height


def resolve_gymnasium(env_id: str) -> str:
    """`module:EnvId` imports `module` (which registers EnvId) first; any other id is Gymnasium's as it is."""
    if ":" not in env_id:
        return env_id
    module, _, name = env_id.partition(":")
    try:
        importlib.import_module(module)
    except Exception as exc:  # any import failure is the user's module, not ours
        raise EnvError(f"cannot import module '{module}' for env '{env_id}': {exc}") from None
    return robotics.resolve(name)  # `module:FetchReach-v4`: Gymnasium-Robotics' id, where module did not register it


FAMILIES = (
    EnvFamily("dmc", owns=is_dmc_id, resolve=dmc.resolve,
              entry_points=("softac.envs.dmc",), sized_rendering=("softac.envs.dmc",)),
    EnvFamily("playground", owns=playground.is_playground_id, resolve=playground.resolve,
              problem=playground.problem, entry_points=("softac.envs.playground",),
              sized_rendering=("softac.envs.playground",)),
    EnvFamily("robotics", owns=robotics.is_robotics_id, resolve=robotics.resolve,
              problem=robotics.mujoco_problem,
              entry_points=("gymnasium_robotics",)),
    EnvFamily("gymnasium", owns=lambda env_id: True, resolve=resolve_gymnasium,
              sized_rendering=("gymnasium.envs.mujoco",)),
)


def family_of(env_id: str) -> EnvFamily:
    """The first family whose ids include `env_id` (gymnasium's, the last row, include every id: a new family's
    row goes before it)."""
    return next(family for family in FAMILIES if family.owns(env_id))


def family_of_entry_point(entry_point: str) -> EnvFamily | None:
    return next((f for f in FAMILIES if f.entry_points and entry_point.startswith(f.entry_points)), None)


def renders_at_size(entry_point: str) -> bool:
    """Whether envs of this entry point take a render width and height (MuJoCo's and the suite's)."""
    return any(entry_point.startswith(f.sized_rendering) for f in FAMILIES if f.sized_rendering)
