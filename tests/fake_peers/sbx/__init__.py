"""A stand-in for sbx.SAC (see tests/fake_peers/README.md): random actions, SB3's callback protocol."""

import time

import numpy as np

STEP_S = 0.001  # each env step, and predict() for each observation, take at least this long: progress rows'
                # intervals are long enough for their rounded time_s to pin down fps, and those with an
                # evaluation are markedly slower (tests/test_peer_runs.py)


class SAC:
    def __init__(self, policy, env, seed=None, verbose=0, **kwargs):
        self.env, self.seed = env, seed
        self.learning_rate, self.batch_size, self.gamma = 3e-4, 256, 0.99
        self.policy_kwargs = {}
        self.num_timesteps = 0
        self.rng = np.random.default_rng(seed)

    def predict(self, obs, deterministic=True):
        obs = np.asarray(obs)
        time.sleep(STEP_S * (obs.shape[0] if obs.ndim > 1 else 1))
        shape = (obs.shape[0], *self.env.action_space.shape) if obs.ndim > 1 else self.env.action_space.shape
        return np.zeros(shape, np.float32), None

    def learn(self, total_timesteps, callback):
        callback.model = self
        space = self.env.action_space
        self.env.reset(seed=self.seed)
        episode_return, length = 0.0, 0
        for _ in range(total_timesteps):
            time.sleep(STEP_S)
            action = self.rng.uniform(space.low, space.high).astype(np.float32)
            _, reward, terminated, truncated, info = self.env.step(action)
            episode_return, length = episode_return + float(reward), length + 1
            self.num_timesteps += 1
            if terminated or truncated:  # SB3's Monitor wrapper puts the finished episode in info
                info = {**info, "episode": {"r": episode_return, "l": length}}
                episode_return, length = 0.0, 0
                self.env.reset()
            callback.locals = {"infos": [info]}
            if callback._on_step() is False:
                break
        return self


class CrossQ(SAC):
    """A stand-in for sbx.CrossQ: SBX's defaults, replaced by the keywords it is given (kept to be read back)."""

    def __init__(self, policy, env, seed=None, verbose=0, **kwargs):
        super().__init__(policy, env, seed, verbose)
        self.learning_rate, self.qf_learning_rate, self.batch_size, self.learning_starts = 1e-3, None, 256, 100
        self.policy_delay, self.buffer_size = 3, 1_000_000
        for key, value in kwargs.items():
            setattr(self, key, value)
