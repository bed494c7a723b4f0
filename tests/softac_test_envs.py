"""Small envs for tests, registered on import (use them as `softac_test_envs:ID`)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np


class DriftEnv(gym.Env):
    """1-D position pushed by the action; terminates when |x| > 0.3, truncated by a time limit.

    The action space is asymmetric, [-1, 3], and the reward is best at action 1.
    The observation carries the step count, so a final observation always
    differs from the observation after reset.
    """

    metadata = {"render_modes": []}

    def __init__(self, low: float = -1.0, high: float = 3.0):
        self.action_space = gym.spaces.Box(np.float32(low), np.float32(high), (1,), np.float32)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (2,), np.float32)
        self.x = 0.0
        self.t = 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x = float(self.np_random.uniform(-0.1, 0.1))
        self.t = 0
        return self._obs(), {}

    def save_state(self):  # softac's protocol for exact resume of a custom env
        return np.array([self.x, self.t], np.float64)

    def load_state(self, state):
        self.x, self.t = float(state[0]), int(state[1])

    def _obs(self):
        return np.array([self.x, self.t], np.float32)

    def step(self, action):
        a = float(np.asarray(action).reshape(-1)[0])
        self.x += 0.05 * (a - 1.0) + float(self.np_random.normal(0, 0.01))
        self.t += 1
        reward = 1.0 - (a - 1.0) ** 2
        terminated = abs(self.x) > 0.3
        return self._obs(), reward, terminated, False, {}


class UnboundedEnv(DriftEnv):
    def __init__(self):
        super().__init__()
        self.action_space = gym.spaces.Box(-np.inf, np.inf, (1,), np.float32)


class BrokenStepEnv(DriftEnv):
    def step(self, action):
        if self.t >= 30:
            raise RuntimeError("simulator exploded")
        return super().step(action)


class NanObsEnv(DriftEnv):
    def step(self, action):
        obs, r, term, trunc, info = super().step(action)
        if self.t >= 30:
            obs = obs * np.nan
        return obs, r, term, trunc, info


class NanRewardEnv(DriftEnv):
    def step(self, action):
        obs, r, term, trunc, info = super().step(action)
        return obs, (float("nan") if self.t >= 30 else r), term, trunc, info


class BrokenResetEnv(DriftEnv):
    resets = 0

    def reset(self, *, seed=None, options=None):
        BrokenResetEnv.resets += 1
        if BrokenResetEnv.resets > 3:
            raise OSError("simulator license expired")
        return super().reset(seed=seed, options=options)


class HugeRewardEnv(DriftEnv):
    """Finite but absurd rewards: the critic's loss overflows to inf."""

    def step(self, action):
        obs, r, term, trunc, info = super().step(action)
        return obs, 3e38, term, trunc, info


class SlowEnv(DriftEnv):
    """Drift taking 2 ms a step. It can tell a test how far a process got, from the process itself:

    SOFTAC_TEST_ENV_LOG=FILE: each reset and step appends a line to FILE, "reset SEED" or "step SEED", SEED
    being the seed the episode started from (-1 without one). In a run with seed 0, evaluation episodes
    start from seeds >= softac.run.evaluation.EVAL_SEED_OFFSET and training episodes below it (env i, reset k
    from i * 7919 + k, for a few envs); with another seed the training reset seeds reach that range too.
    SOFTAC_TEST_STOP_IN_EVAL=1: the first step of an episode seeded >= EVAL_SEED_OFFSET (in a seed-0 run,
    the first evaluation step), once logged, stops the process (SIGSTOP), so a test can act on it at that
    exact point and then let it go on (SIGCONT).
    SOFTAC_TEST_SLOW_CLOSE_S=S: the first close() in a process of an env that has stepped takes S seconds, as a
    simulator's teardown can: a stopped process then winds down for that long after its checkpoint, before it
    says where it stopped (an env made only to read its spaces closes at once; so do the others, or a peer's ten
    evaluation envs would take 10 S).
    """

    stopped_in_eval = False  # once per process
    slow_closed = False  # once per process

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.episode_seed = -1
        self.stepped = False

    def _log(self, event: str) -> None:
        import os

        path = os.environ.get("SOFTAC_TEST_ENV_LOG")
        if path:
            with open(path, "a") as f:  # one small append per line: whole lines, whichever process writes
                f.write(f"{event} {self.episode_seed}\n")

    def reset(self, *, seed=None, options=None):
        self.episode_seed = -1 if seed is None else int(seed)
        self._log("reset")
        return super().reset(seed=seed, options=options)

    def step(self, action):
        import os
        import time

        from softac.run.evaluation import EVAL_SEED_OFFSET

        time.sleep(0.002)
        self.stepped = True
        result = super().step(action)
        self._log("step")
        if (self.episode_seed >= EVAL_SEED_OFFSET and os.environ.get("SOFTAC_TEST_STOP_IN_EVAL")
                and not SlowEnv.stopped_in_eval):
            import signal

            SlowEnv.stopped_in_eval = True
            os.kill(os.getpid(), signal.SIGSTOP)
        return result

    def close(self):
        import os
        import time

        if self.stepped and not SlowEnv.slow_closed:
            SlowEnv.slow_closed = True
            time.sleep(float(os.environ.get("SOFTAC_TEST_SLOW_CLOSE_S", "0")))
        super().close()


class CrashingEnv(DriftEnv):
    """A simulator that takes its process down (as a segfault would): only ever run it in an env worker."""

    def step(self, action):
        if self.t >= 30:
            import os
            import signal

            os.kill(os.getpid(), signal.SIGKILL)
        return super().step(action)


class PointGoalEnv(gym.Env):
    """A goal env in Gymnasium-Robotics' shape: a point in the plane moved by the action towards a goal drawn
    at reset. Observation dict: observation [x, y, t/20], achieved_goal [x, y], desired_goal [gx, gy]; sparse
    reward -1 until within 0.1 of the goal, 0 there (compute_reward works on batches); info["is_success"].
    Episodes end by the time limit only. save_state/load_state for exact resume."""

    metadata = {"render_modes": []}
    THRESHOLD = 0.1

    def __init__(self):
        box = lambda n: gym.spaces.Box(-2.0, 2.0, (n,), np.float32)  # noqa: E731
        self.observation_space = gym.spaces.Dict(
            {"observation": box(3), "achieved_goal": box(2), "desired_goal": box(2)})
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.pos, self.goal, self.t = np.zeros(2), np.zeros(2), 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.pos = self.np_random.uniform(-0.5, 0.5, 2)
        self.goal = self.np_random.uniform(-0.8, 0.8, 2)
        self.t = 0
        return self._obs(), {}

    def _obs(self):
        return {"observation": np.array([*self.pos, self.t / 20], np.float32),
                "achieved_goal": self.pos.astype(np.float32), "desired_goal": self.goal.astype(np.float32)}

    def compute_reward(self, achieved_goal, desired_goal, info):
        distance = np.linalg.norm(np.asarray(achieved_goal) - np.asarray(desired_goal), axis=-1)
        return -(distance > self.THRESHOLD).astype(np.float32)

    def step(self, action):
        self.pos = np.clip(self.pos + 0.15 * np.clip(np.asarray(action, np.float64), -1, 1), -2.0, 2.0)
        self.t += 1
        obs = self._obs()
        reward = float(self.compute_reward(obs["achieved_goal"], obs["desired_goal"], {}))
        return obs, reward, False, False, {"is_success": np.float32(reward == 0.0)}

    def save_state(self):
        return np.array([*self.pos, *self.goal, self.t], np.float64)

    def load_state(self, state):
        self.pos, self.goal, self.t = np.array(state[:2]), np.array(state[2:4]), int(state[4])


class OneGoalRewardEnv(PointGoalEnv):
    """A goal env whose compute_reward takes one goal at a time (HER cannot use it)."""

    def compute_reward(self, achieved_goal, desired_goal, info):
        return -float(np.linalg.norm(np.asarray(achieved_goal) - np.asarray(desired_goal)) > self.THRESHOLD)


class DictObsEnv(DriftEnv):
    """A dict observation that is not a goal env (no compute_reward): flattened, keys in the space's order."""

    def __init__(self):
        super().__init__()
        self.observation_space = gym.spaces.Dict({"velocity": gym.spaces.Box(-np.inf, np.inf, (1,), np.float32),
                                                  "position": gym.spaces.Box(-np.inf, np.inf, (1,), np.float32)})

    def _obs(self):
        return {"position": np.array([self.x], np.float32), "velocity": np.array([self.t], np.float32)}


class DotImageEnv(gym.Env):
    """Image observations (issue 44): a bright square at a random column of a dark 16x16 image, drawn afresh each
    step. The reward pays the action pointing to the square's side: 1 - (a - side)^2, side -1 left, +1 right, so
    the best action depends on what the image shows. `channels_first` gives [3, 16, 16] (PyTorch's layout); `size`
another side than 16.
    Renders rgb_array (a 30x40 picture of the same) for pixels=true."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(self, channels_first: bool = False, render_mode: str | None = None, size: int = 16):
        self.channels_first = channels_first
        self.render_mode = render_mode
        self.size = size
        shape = (3, size, size) if channels_first else (size, size, 3)
        self.observation_space = gym.spaces.Box(0, 255, shape, np.uint8)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.column = 0
        self.t = 0

    def _draw(self, height: int, width: int) -> np.ndarray:
        image = np.full((height, width, 3), 20, np.uint8)
        left = self.column * width // 16
        image[height // 3:height // 3 + max(3 * height // 16, 1), left:left + max(3 * width // 16, 1)] = (250, 200, 90)
        return image

    def _obs(self) -> np.ndarray:
        image = self._draw(self.size, self.size)
        return np.transpose(image, (2, 0, 1)).copy() if self.channels_first else image

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.column, self.t = int(self.np_random.integers(0, 14)), 0
        return self._obs(), {}

    def step(self, action):
        side = -1.0 if self.column < 7 else 1.0
        reward = 1.0 - (float(np.asarray(action).reshape(-1)[0]) - side) ** 2
        self.column, self.t = int(self.np_random.integers(0, 14)), self.t + 1
        return self._obs(), reward, False, False, {}

    def render(self):
        return self._draw(30, 40)

    def save_state(self):
        return np.array([self.column, self.t], np.float64)

    def load_state(self, state):
        self.column, self.t = int(state[0]), int(state[1])


class DotStateImageEnv(DotImageEnv):
    """A dict observation of an image beside state values (issue 44): DotImage's picture under "camera" (CxHxW
    with `channels_first`), and under "flip" a value of -1 or +1 drawn each step, beside a "clock" of two values.
    The reward pays the action pointing to the square's side times flip: 1 - (a - side * flip)^2, so the best
    action needs the image and the state together."""

    def __init__(self, channels_first: bool = False, render_mode: str | None = None, size: int = 16):
        super().__init__(channels_first, render_mode, size)
        image = self.observation_space
        self.observation_space = gym.spaces.Dict({
            "camera": image, "flip": gym.spaces.Box(-1.0, 1.0, (1,), np.float32),
            "clock": gym.spaces.Box(-np.inf, np.inf, (2,), np.float32)})
        self.flip = 1.0

    def _obs(self):
        return {"camera": super()._obs(), "flip": np.array([self.flip], np.float32),
                "clock": np.array([self.t / 20.0, -self.t / 3.0], np.float32)}

    def reset(self, *, seed=None, options=None):
        obs, info = super().reset(seed=seed, options=options)
        self.flip = float(self.np_random.choice([-1.0, 1.0]))
        return self._obs(), info

    def step(self, action):
        side = (-1.0 if self.column < 7 else 1.0) * self.flip
        reward = 1.0 - (float(np.asarray(action).reshape(-1)[0]) - side) ** 2
        self.column, self.t = int(self.np_random.integers(0, 14)), self.t + 1
        self.flip = float(self.np_random.choice([-1.0, 1.0]))
        return self._obs(), reward, False, False, {}

    def save_state(self):
        return np.array([self.column, self.t, self.flip], np.float64)

    def load_state(self, state):
        self.column, self.t, self.flip = int(state[0]), int(state[1]), float(state[2])


gym.register("Drift-v0", entry_point=DriftEnv, max_episode_steps=25)
gym.register("DotImage-v0", entry_point=DotImageEnv, max_episode_steps=20)
gym.register("DotStateImage-v0", entry_point=DotStateImageEnv, max_episode_steps=20)
gym.register("PointGoal-v0", entry_point=PointGoalEnv, max_episode_steps=20)
gym.register("OneGoalReward-v0", entry_point=OneGoalRewardEnv, max_episode_steps=20)
gym.register("DictObs-v0", entry_point=DictObsEnv, max_episode_steps=25)
gym.register("Unbounded-v0", entry_point=UnboundedEnv, max_episode_steps=25)
gym.register("BrokenStep-v0", entry_point=BrokenStepEnv, max_episode_steps=100)
gym.register("NanObs-v0", entry_point=NanObsEnv, max_episode_steps=100)
gym.register("NanReward-v0", entry_point=NanRewardEnv, max_episode_steps=100)
gym.register("BrokenReset-v0", entry_point=BrokenResetEnv, max_episode_steps=10)
gym.register("HugeReward-v0", entry_point=HugeRewardEnv, max_episode_steps=25)
gym.register("Slow-v0", entry_point=SlowEnv, max_episode_steps=25)
gym.register("Crashing-v0", entry_point=CrashingEnv, max_episode_steps=100)
