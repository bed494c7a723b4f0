"""Observation normalisation by a running mean and variance (`obs_norm`), as users know it from
Stable-Baselines3's VecNormalize: (obs - mean) / sqrt(var + eps), clipped to [-clip, clip].

The replay buffer keeps raw observations; batches are normalised when sampled, with the statistics of
that moment (as SB3's off-policy algorithms do), so old transitions never carry stale statistics. The
statistics are updated with every observation the policy acts on while training, frozen otherwise
(evaluation, video, `predict`), and saved in every checkpoint so a resumed run continues them exactly.
"""

from __future__ import annotations

import numpy as np

from softac.errors import SoftacError

EPSILON = 1e-8  # added to the variance, as VecNormalize does: a constant feature maps to 0, not to inf


def merged_moments(count, mean, m2, batch):
    """(count, mean, m2) with a batch of rows merged in (Chan, Golub & LeVeque 1979): NumPy's float64 here, and
    JAX's float32 arrays inside device collection's jitted chunks (softac.run.device_transitions), one formula."""
    n = batch.shape[0]
    batch_mean = batch.mean(axis=0)
    weight = count * 1.0  # a float: on the device count * n would overflow int32 past 2^31
    total = weight + n
    delta = batch_mean - mean
    return (count + n, mean + delta * (n / total),
            m2 + ((batch - batch_mean) ** 2).sum(axis=0) + delta ** 2 * (weight * n / total))


class RunningObsNorm:
    """Running mean/variance of observation vectors, merged batch by batch (Chan, Golub & LeVeque 1979),
    in float64 so that a long run's statistics do not drift with rounding."""

    def __init__(self, dim: int, clip: float = 10.0):
        self.dim = dim
        self.clip = float(clip)
        self.count = 0
        self.mean = np.zeros(dim, np.float64)
        self.m2 = np.zeros(dim, np.float64)  # sum of squared deviations from the mean

    @property
    def var(self) -> np.ndarray:
        return self.m2 / self.count if self.count > 0 else np.ones(self.dim, np.float64)

    def update(self, batch: np.ndarray) -> None:
        batch = np.asarray(batch, np.float64).reshape(-1, self.dim)
        if batch.shape[0] == 0:
            return
        self.count, self.mean, self.m2 = merged_moments(self.count, self.mean, self.m2, batch)

    def normalize(self, obs: np.ndarray) -> np.ndarray:
        """float32 observations (any leading shape) in normalised units."""
        mean = self.mean.astype(np.float32)
        std = np.sqrt(self.var + EPSILON).astype(np.float32)
        return np.clip((np.asarray(obs, np.float32) - mean) / std, -self.clip, self.clip)

    def state_dict(self) -> dict[str, np.ndarray]:
        return {"count": np.asarray(self.count, np.int64), "mean": self.mean.copy(), "m2": self.m2.copy()}

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        mean, m2 = np.asarray(state["mean"], np.float64), np.asarray(state["m2"], np.float64)
        if mean.shape != (self.dim,) or m2.shape != (self.dim,):
            raise SoftacError(f"observation statistics are for {mean.shape[-1] if mean.ndim else 0} values, "
                              f"this agent's observations have {self.dim}")
        self.count = int(state["count"])
        self.mean, self.m2 = mean.copy(), m2.copy()


def return_divisor(var, max_abs, mode: str, v_max: float, xp=np):
    """What reward_scale divides rewards by, from the running return's variance and largest |G|: `std`, XQC's
    sqrt(var) + eps; `std_max`, FlashSAC's max(sqrt(var + eps), G_max / v_max). NumPy's float64 in
    RunningReturnScale, JAX's float32 inside device collection's chunks, one formula."""
    eps = RunningReturnScale.EPSILON
    return xp.sqrt(var) + eps if mode == "std" else xp.maximum(xp.sqrt(var + eps), max_abs / v_max)


class RunningReturnScale:
    """Reward scaling for critics on a fixed support (`reward_scale`): rewards divided by the spread of the
    discounted return, so that the returns fit the support whatever the env's reward units (SimbaV2's reward
    normaliser, as XQC and FlashSAC use it). Each env's running return G <- gamma (1 - done) G + r is updated
    with every training step (done: the step ended its episode, as those authors' code has it), and the
    mean and variance of all the G seen are merged as RunningObsNorm merges observations; `std` divides by
    sigma_G + 1e-8 (XQC's), `std_max` by max(sqrt(var_G + 1e-8), G_max / v_max) with G_max the largest |G| seen
    (FlashSAC's), which keeps the largest return inside the support. Batches are scaled when sampled, with the
    scale of that moment; the statistics are saved in every checkpoint."""

    EPSILON = 1e-8

    def __init__(self, n_envs: int, gamma: float, mode: str, v_max: float):
        self.gamma, self.mode, self.v_max = float(gamma), mode, float(v_max)
        self.returns = np.zeros(n_envs, np.float64)
        self.stats = RunningObsNorm(1)
        self.max_abs = 0.0

    def update(self, rewards: np.ndarray, dones: np.ndarray) -> None:
        self.returns = self.gamma * (1.0 - np.asarray(dones, np.float64)) * self.returns + np.asarray(rewards,
                                                                                                      np.float64)
        self.stats.update(self.returns[:, None])
        self.max_abs = max(self.max_abs, float(np.max(np.abs(self.returns))))

    @property
    def scale(self) -> float:
        """What rewards are divided by now (1 before any step)."""
        if self.stats.count == 0:
            return 1.0
        return float(return_divisor(float(self.stats.var[0]), self.max_abs, self.mode, self.v_max))

    def scale_rewards(self, rewards: np.ndarray) -> np.ndarray:
        return (np.asarray(rewards, np.float64) / self.scale).astype(np.float32)

    def state_dict(self) -> dict[str, np.ndarray]:
        return {**self.stats.state_dict(), "returns": self.returns.copy(), "max_abs": np.asarray(self.max_abs)}

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        returns = np.asarray(state["returns"], np.float64)
        if returns.shape != self.returns.shape:
            raise SoftacError(f"reward statistics are for {returns.size} envs, this run steps {self.returns.size}")
        self.stats.load_state_dict({k: np.asarray(state[k]).reshape(-1) if k != "count" else state[k]
                                    for k in ("count", "mean", "m2")})
        self.returns, self.max_abs = returns.copy(), float(state["max_abs"])
