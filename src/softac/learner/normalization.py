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
        n = batch.shape[0]
        if n == 0:
            return
        batch_mean = batch.mean(axis=0)
        batch_m2 = np.square(batch - batch_mean).sum(axis=0)
        total = self.count + n
        delta = batch_mean - self.mean
        self.mean = self.mean + delta * (n / total)
        self.m2 = self.m2 + batch_m2 + np.square(delta) * (self.count * n / total)
        self.count = total

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
