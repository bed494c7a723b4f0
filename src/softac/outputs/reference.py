"""Baselines to beat: random actions, the zero action, and hand-written controllers.

The heuristic controllers read only the observation (as an agent does):
- InvertedPendulum: linear feedback on pole angle, pole angular velocity, cart position and velocity.
- Pusher: Jacobian-transpose control of the fingertip, first to a point behind the object (on
  the far side from the goal), then through the object toward the goal. The arm's Jacobian comes
  from the env's own MuJoCo model, evaluated at the joint angles in the observation.
"""

from __future__ import annotations

from typing import Any, Callable

import gymnasium as gym
import numpy as np

from softac.envs.make import SpaceInfo, check_spaces, copy_env, env_name
from softac.run.evaluation import EVAL_SEED_OFFSET, run_on_copies

Policy = Callable[[np.ndarray], np.ndarray]


def random_policy(spaces: SpaceInfo, seed: int) -> Policy:
    rng = np.random.default_rng(seed)
    return lambda obs: rng.uniform(spaces.low, spaces.high, (len(obs), spaces.act_dim)).astype(np.float32)


def zero_policy(spaces: SpaceInfo) -> Policy:
    # zero where the bounds allow it, else the point of the box nearest to zero
    action = np.clip(np.zeros(spaces.act_dim, np.float32), spaces.low, spaces.high)
    return lambda obs: np.tile(action, (len(obs), 1))


def pendulum_policy(spaces: SpaceInfo) -> Policy:
    # obs = [cart position, pole angle, cart velocity, pole angular velocity]; gains found by a small grid search
    gains = np.array([1.0, 20.0, 1.0, 2.0], np.float32)
    return lambda obs: np.clip((obs[:, :4] @ gains)[:, None], spaces.low, spaces.high)


class PusherController:
    """Fingertip to behind the object, then push it to the goal (Jacobian-transpose PD control)."""

    KP, KD, BEHIND, REACHED = 8.0, 0.6, 0.10, 0.04

    def __init__(self, env: gym.Env, spaces: SpaceInfo):
        import mujoco

        raw = env.unwrapped
        self.mujoco = mujoco
        self.model = raw.model
        self.data = mujoco.MjData(raw.model)
        self.tip = mujoco.mj_name2id(raw.model, mujoco.mjtObj.mjOBJ_BODY, "tips_arm")
        self.spaces = spaces

    def action(self, o: np.ndarray) -> np.ndarray:
        mj = self.mujoco
        qpos, qvel, tip, obj, goal = o[:7], o[7:14], o[14:17], o[17:20], o[20:23]
        push_dir = goal[:2] - obj[:2]
        push_dir /= np.linalg.norm(push_dir) + 1e-8
        rel = tip[:2] - obj[:2]
        along = float(rel @ push_dir)  # < 0: the fingertip is on the far side of the object from the goal
        lateral = float(np.linalg.norm(rel - along * push_dir))
        target = obj.copy()
        if along < -0.03 and lateral < self.REACHED:
            target[:2] += 0.05 * push_dir  # lined up behind the object: push through it toward the goal
        else:
            target[:2] -= self.BEHIND * push_dir  # first get behind it
        target[2] = -0.275  # the table's height for the fingertip
        self.data.qpos[:7] = qpos
        mj.mj_fwdPosition(self.model, self.data)  # kinematics and the com-based quantities mj_jacBody needs
        jac = np.zeros((3, self.model.nv))
        mj.mj_jacBody(self.model, self.data, jac, None, self.tip)
        torque = jac[:, :7].T @ (self.KP * (target - tip)) - self.KD * qvel
        return np.clip(torque, self.spaces.low, self.spaces.high).astype(np.float32)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return np.stack([self.action(o) for o in obs])


def heuristic_policy(env: gym.Env, spaces: SpaceInfo) -> Policy | None:
    name = env_name(env)
    if name.startswith("InvertedPendulum") and spaces.obs_dim == 4 and spaces.act_dim == 1:
        return pendulum_policy(spaces)
    if name.startswith("Pusher") and spaces.obs_dim == 23 and spaces.act_dim == 7:
        return PusherController(env, spaces)
    return None


def run_baselines(source: Any, episodes: int = 10, seed: int = 0) -> dict[str, Any]:
    """{name: stats} for random, zero and (where one exists) heuristic; same episode seeds as evaluation."""
    probe = copy_env(source)
    spaces = check_spaces(probe)
    policies: dict[str, Policy] = {"random": random_policy(spaces, seed), "zero": zero_policy(spaces)}
    heuristic = heuristic_policy(probe, spaces)
    if heuristic is not None:
        policies["heuristic"] = heuristic
    results = {}
    try:
        for name, policy in policies.items():
            stats = run_on_copies(policy, source, episodes, seed + EVAL_SEED_OFFSET)
            results[name] = {k: stats[k] for k in ("mean_return", "std_return", "episodes", "returns", "lengths")}
    finally:
        probe.close()
    return {"env_id": env_name(probe), "episodes": episodes, "baselines": results}
