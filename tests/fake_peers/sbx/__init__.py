"""A stand-in for sbx.SAC (see tests/fake_peers/README.md): random actions, SB3's callback protocol, SB3's
save/load and replay buffer layout (so that a peer's checkpoint and resume are tested)."""

import datetime
import json
import os
import tempfile
import time

import numpy as np

STEP_S = 0.001  # each env step, and predict() for each observation, take at least this long: progress rows'
                # intervals are long enough for their rounded time_s to pin down fps, and those with an
                # evaluation are markedly slower (tests/test_peer_runs.py)


class ReplayBuffer:
    """SB3's ReplayBuffer layout: preallocated [size, n_envs, ...] arrays, a write position, a full flag."""

    def __init__(self, size, env):
        self.buffer_size, self.pos, self.full = size, 0, False
        obs, act = env.observation_space.shape, env.action_space.shape
        self.observations = np.zeros((size, 1, *obs))
        self.next_observations = np.zeros((size, 1, *obs))
        self.actions = np.zeros((size, 1, *act), np.float32)
        self.rewards, self.dones, self.timeouts = (np.zeros((size, 1), np.float32) for _ in range(3))

    def add(self, obs, next_obs, action, reward, done, episode_end=False):
        self.observations[self.pos, 0], self.next_observations[self.pos, 0] = obs, next_obs
        self.actions[self.pos, 0], self.rewards[self.pos, 0], self.dones[self.pos, 0] = action, reward, done
        self.pos = (self.pos + 1) % self.buffer_size
        self.full = self.full or self.pos == 0


class _NoCallback:
    def _on_step(self):
        return True


class SAC:
    BUFFER = 500  # rows: small, so that the tests' runs fill it and wrap around

    def __init__(self, policy, env, seed=None, verbose=0, **kwargs):
        # a VecNormalize (its stand-in) in front of the env: SB3 keeps it as _vec_normalize_env
        self.vec_normalize = env if hasattr(env, "obs_rms") else None
        self.env = env.venv.envs[0] if self.vec_normalize is not None else env
        self.seed, self.policy = seed, policy
        self.learning_rate, self.batch_size, self.gamma = 3e-4, 256, 0.99
        self.policy_kwargs = kwargs.get("policy_kwargs", {})
        self.num_timesteps = 0
        self.rng = np.random.default_rng(seed)
        self.her = kwargs.get("replay_buffer_class") is not None  # SB3's HerReplayBuffer (its stand-in)
        if self.her:
            from stable_baselines3 import HerReplayBuffer

            self.replay_buffer = HerReplayBuffer(self.BUFFER, env, **kwargs.get("replay_buffer_kwargs", {}))
            self.learning_starts = kwargs.get("learning_starts", 100)
        else:
            self.replay_buffer = ReplayBuffer(self.BUFFER, env)
        self._custom_logger = False

    def get_vec_normalize_env(self):
        return self.vec_normalize

    def set_logger(self, logger):
        self._logger, self._custom_logger = logger, True

    def save(self, file):
        # as SB3's zip: the settings (policy_kwargs as its text: it may hold functions)
        file.write(json.dumps({"num_timesteps": self.num_timesteps, "seed": self.seed, "her": self.her,
                               "settings": {**{k: v for k, v in vars(self).items() if isinstance(v, (int, float))},
                                            "policy_kwargs": str(self.policy_kwargs)}}).encode())

    @classmethod
    def load(cls, file, env, **kwargs):
        data = json.loads(file.read())
        if data["her"]:  # as SB3: the replay buffer class is part of what save() kept
            from stable_baselines3 import HerReplayBuffer

            model = cls("MultiInputPolicy", env, seed=data["seed"], replay_buffer_class=HerReplayBuffer)
        else:
            model = cls("MlpPolicy", env, seed=data["seed"])
        for key, value in data["settings"].items():
            setattr(model, key, value)
        return model  # like SB3's load(): the replay buffer comes back empty

    def train(self, gradient_steps, batch_size):
        """SB3's off-policy train(): here it only checks that the buffer can give a batch."""
        filled = self.BUFFER if self.replay_buffer.full else self.replay_buffer.pos
        if filled < batch_size or gradient_steps < 1:
            raise RuntimeError(f"train() with {filled} rows, batch {batch_size}, {gradient_steps} steps")
        self.gradient_steps_taken = getattr(self, "gradient_steps_taken", 0) + gradient_steps

    def predict(self, obs, deterministic=True):
        if isinstance(obs, dict):  # MultiInputPolicy: a dict of arrays, batched or not
            obs = obs["observation"]
        obs = np.asarray(obs)
        time.sleep(STEP_S * (obs.shape[0] if obs.ndim > 1 else 1))
        shape = (obs.shape[0], *self.env.action_space.shape) if obs.ndim > 1 else self.env.action_space.shape
        return np.zeros(shape, np.float32), None

    def learn(self, total_timesteps, callback=None, reset_num_timesteps=True):
        callback = callback if callback is not None else _NoCallback()
        if reset_num_timesteps:
            self.num_timesteps = 0
        if not self._custom_logger:  # as SB3's configure_logger(): a directory per learn(), also at verbose=0
            stamp = datetime.datetime.now().strftime("SB3-%Y-%m-%d-%H-%M-%S-%f")
            os.makedirs(os.path.join(tempfile.gettempdir(), stamp), exist_ok=True)
        # a resumed model must have its replay buffer back: every step so far is in it but the last one, which
        # SB3 stores after the callback that saved the checkpoint
        expected = min(self.num_timesteps, self.BUFFER)
        filled = self.BUFFER if self.replay_buffer.full else self.replay_buffer.pos
        observations = self.replay_buffer.observations
        held = any(a.any() for a in observations.values()) if isinstance(observations, dict) else observations.any()
        if not expected - 1 <= filled <= expected or (self.num_timesteps and not held):
            raise RuntimeError(f"replay buffer holds {filled} rows after {self.num_timesteps} steps")
        callback.model = self
        space = self.env.action_space
        obs, _ = self.env.reset(seed=self.seed)
        episode_return, length = 0.0, 0
        for _ in range(total_timesteps):
            time.sleep(STEP_S)
            action = self.rng.uniform(space.low, space.high).astype(np.float32)
            next_obs, reward, terminated, truncated, info = self.env.step(action)
            if self.vec_normalize is not None:  # as VecNormalize: statistics of every observation while training
                self.vec_normalize.obs_rms.update(np.asarray(next_obs)[None])
            episode_return, length = episode_return + float(reward), length + 1
            self.num_timesteps += 1
            if terminated or truncated:  # SB3's Monitor wrapper puts the finished episode in info
                info = {**info, "episode": {"r": episode_return, "l": length}}
                episode_return, length = 0.0, 0
            callback.locals = {"infos": [info]}
            if callback._on_step() is False:  # as SB3: the callback first, then the transition is stored
                break
            self.replay_buffer.add(obs, next_obs, action, reward, terminated, episode_end=terminated or truncated)
            if self.her and self.num_timesteps >= self.learning_starts:
                self.replay_buffer.sample_check()
            obs = self.env.reset()[0] if terminated or truncated else next_obs
        return self


class CrossQ(SAC):
    """A stand-in for sbx.CrossQ: SBX's defaults, replaced by the keywords it is given (kept to be read back)."""

    def __init__(self, policy, env, seed=None, verbose=0, **kwargs):
        super().__init__(policy, env, seed, verbose)
        self.learning_rate, self.qf_learning_rate, self.batch_size, self.learning_starts = 1e-3, None, 256, 100
        self.policy_delay, self.buffer_size = 3, 1_000_000
        for key, value in kwargs.items():
            setattr(self, key, value)


class TQC(SAC):
    """A stand-in for sbx.TQC: SBX's defaults, replaced by the keywords it is given (kept to be read back)."""

    def __init__(self, policy, env, seed=None, verbose=0, **kwargs):
        super().__init__(policy, env, seed, verbose)
        self.learning_rate, self.qf_learning_rate, self.batch_size, self.learning_starts = 3e-4, None, 256, 100
        self.policy_delay, self.buffer_size, self.top_quantiles_to_drop_per_net = 1, 1_000_000, 2
        for key, value in kwargs.items():
            setattr(self, key, value)
