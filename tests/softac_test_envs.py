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
    start from seeds >= softac.evaluation.EVAL_SEED_OFFSET and training episodes below it (env i, reset k
    from i * 7919 + k, for a few envs); with another seed the training reset seeds reach that range too.
    SOFTAC_TEST_STOP_IN_EVAL=1: the first step of an episode seeded >= EVAL_SEED_OFFSET (in a seed-0 run,
    the first evaluation step), once logged, stops the process (SIGSTOP), so a test can act on it at that
    exact point and then let it go on (SIGCONT).
    """

    stopped_in_eval = False  # once per process

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.episode_seed = -1

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

        from softac.evaluation import EVAL_SEED_OFFSET

        time.sleep(0.002)
        result = super().step(action)
        self._log("step")
        if (self.episode_seed >= EVAL_SEED_OFFSET and os.environ.get("SOFTAC_TEST_STOP_IN_EVAL")
                and not SlowEnv.stopped_in_eval):
            import signal

            SlowEnv.stopped_in_eval = True
            os.kill(os.getpid(), signal.SIGSTOP)
        return result


class CrashingEnv(DriftEnv):
    """A simulator that takes its process down (as a segfault would): only ever run it in an env worker."""

    def step(self, action):
        if self.t >= 30:
            import os
            import signal

            os.kill(os.getpid(), signal.SIGKILL)
        return super().step(action)


gym.register("Drift-v0", entry_point=DriftEnv, max_episode_steps=25)
gym.register("Unbounded-v0", entry_point=UnboundedEnv, max_episode_steps=25)
gym.register("BrokenStep-v0", entry_point=BrokenStepEnv, max_episode_steps=100)
gym.register("NanObs-v0", entry_point=NanObsEnv, max_episode_steps=100)
gym.register("NanReward-v0", entry_point=NanRewardEnv, max_episode_steps=100)
gym.register("BrokenReset-v0", entry_point=BrokenResetEnv, max_episode_steps=10)
gym.register("HugeReward-v0", entry_point=HugeRewardEnv, max_episode_steps=25)
gym.register("Slow-v0", entry_point=SlowEnv, max_episode_steps=25)
gym.register("Crashing-v0", entry_point=CrashingEnv, max_episode_steps=100)
