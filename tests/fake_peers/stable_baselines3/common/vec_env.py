"""Stand-ins for SB3's DummyVecEnv and VecNormalize (see tests/fake_peers/README.md): the VecEnv protocol (batched
reset and step, autoreset) and VecNormalize's running observation statistics (obs_rms: mean, var, count),
normalize_obs and training flag, as softac's peer adapter uses them."""

import numpy as np


class RunningMeanStd:
    def __init__(self, shape):
        self.mean, self.var, self.count = np.zeros(shape), np.ones(shape), 1e-4

    def update(self, batch):
        mean, var, n = batch.mean(0), batch.var(0), batch.shape[0]
        delta, total = mean - self.mean, self.count + n
        self.mean = self.mean + delta * n / total
        self.var = (self.var * self.count + var * n + delta**2 * self.count * n / total) / total
        self.count = total


class DummyVecEnv:
    def __init__(self, env_fns):
        self.envs = [fn() for fn in env_fns]
        self.num_envs = len(self.envs)
        self.observation_space, self.action_space = self.envs[0].observation_space, self.envs[0].action_space

    def reset(self, seed=None):
        return np.stack([env.reset(seed=seed)[0] for env in self.envs])

    def step(self, actions):
        obs, reward, terminated, truncated, info = self.envs[0].step(actions[0])
        if terminated or truncated:
            info = {**info, "terminal_observation": obs}
            obs = self.envs[0].reset()[0]
        return obs[None], np.asarray([reward]), np.asarray([terminated or truncated]), [info]


class VecNormalize:
    def __init__(self, venv, norm_obs=True, norm_reward=True, clip_obs=10.0, gamma=0.99, epsilon=1e-8):
        self.venv, self.clip_obs, self.epsilon, self.training = venv, clip_obs, epsilon, True
        self.num_envs, self.observation_space, self.action_space = venv.num_envs, venv.observation_space, venv.action_space
        self.obs_rms = RunningMeanStd(venv.observation_space.shape)

    def normalize_obs(self, obs):
        return np.clip((obs - self.obs_rms.mean) / np.sqrt(self.obs_rms.var + self.epsilon), -self.clip_obs,
                       self.clip_obs).astype(np.float32)

    def reset(self, seed=None):
        obs = self.venv.reset(seed=seed)
        if self.training:
            self.obs_rms.update(obs)
        return self.normalize_obs(obs)

    def step(self, actions):
        obs, rewards, dones, infos = self.venv.step(actions)
        if self.training:
            self.obs_rms.update(obs)
        return self.normalize_obs(obs), rewards, dones, infos
