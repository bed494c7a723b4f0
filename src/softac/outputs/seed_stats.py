"""Statistics over seeds, shared by the plots and the sweeps' tables.

Few seeds are the rule here (3-5), so intervals use Student's t (its quantiles from scipy, which JAX
already installs), and summaries add the interquartile mean that rliable reports (Agarwal et al. 2021,
"Deep RL at the Edge of the Statistical Precipice"): robust to one outlying seed, less noisy than a median.
Across several envs, and for curves, the IQM comes with rliable's stratified percentile bootstrap: runs
are resampled with replacement within each env, so the interval never leaves the range of what was
observed (a t-interval of 2-3 seeds can span the whole axis).
"""

from __future__ import annotations

import math
from typing import Iterable, NamedTuple

import numpy as np


def t_critical_95(n: int) -> float:
    """Two-sided 95% Student-t quantile for n samples (n - 1 degrees of freedom; at least 1)."""
    from scipy import stats as scipy_stats  # here, not at import: scipy.stats takes ~0.5 s to load

    return float(scipy_stats.t.ppf(0.975, max(int(n) - 1, 1)))


def interquartile_mean(values: Iterable[float]) -> float:
    """Mean of the middle half: a quarter of the values cut from each end (none of 3, one of 4-7 from each
    end, ...), as rliable's IQM; with fewer than 4 values it is the plain mean."""
    return float(trimmed_means(np.asarray(list(values), float)[None, :])[0])


class SeedSummary(NamedTuple):
    mean: float
    std: float  # sample standard deviation (ddof 1); 0 for one value
    ci_half: float  # half width of the 95% Student-t interval of the mean; 0 for one value
    iqm: float
    n: int


def ci_half_width(std: float, n: int) -> float:
    """Half width of the 95% Student-t interval of a mean of n values with sample std `std`; 0 for n < 2."""
    return t_critical_95(n) * std / math.sqrt(n) if n > 1 else 0.0


def summarize_seeds(values: Iterable[float]) -> SeedSummary:
    """Mean, std, 95% interval half width and IQM of one value per seed."""
    arr = np.asarray(list(values), float)
    if arr.size == 0:
        raise ValueError("no values to summarise")
    std = float(arr.std(ddof=1)) if arr.size > 1 else 0.0
    return SeedSummary(float(arr.mean()), std, ci_half_width(std, arr.size), interquartile_mean(arr), int(arr.size))


def mean_and_ci(values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per column of a [seeds, points] array with NaN for missing points: the mean, the 95% interval's
    half width (Student t over the seeds present) and the number of seeds present."""
    n = np.sum(~np.isnan(values), axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.nanmean(values, axis=0)
        std = np.nanstd(values, axis=0, ddof=1) if values.shape[0] > 1 else np.zeros(values.shape[1])
        half = np.array([ci_half_width(float(s), int(k)) for s, k in zip(np.nan_to_num(std), n)])
    return mean, half, n


def trimmed_means(samples: np.ndarray) -> np.ndarray:
    """The IQM of each row of a [rows, values] array (scipy's trim_mean, as rliable)."""
    from scipy import stats as scipy_stats

    return np.asarray(scipy_stats.trim_mean(samples, 0.25, axis=1), float)


def _bootstrap_iqm(tasks: list[np.ndarray], reps: int, level: float,
                   rng: np.random.Generator) -> tuple[float, float, float]:
    """The pooled IQM of `tasks` (non-empty arrays) and its stratified percentile-bootstrap interval."""
    point = interquartile_mean(np.concatenate(tasks))
    resampled = np.concatenate([t[rng.integers(0, t.size, size=(reps, t.size))] for t in tasks], axis=1)
    low, high = np.percentile(trimmed_means(resampled), [50 * (1 - level), 50 * (1 + level)])
    return point, float(low), float(high)


def stratified_bootstrap_iqm(runs_per_task: list[Iterable[float]], reps: int = 20_000, level: float = 0.95,
                             seed: int = 0) -> tuple[float, float, float]:
    """The IQM over every run of every task (one final score per run; tasks may have different numbers of
    runs) and its stratified-bootstrap percentile interval: each of `reps` resamples draws, for each task
    separately, as many runs as it has, with replacement (rliable's StratifiedBootstrap)."""
    tasks = [np.asarray(list(runs), float) for runs in runs_per_task]
    if not tasks or any(t.size == 0 for t in tasks):
        raise ValueError("every task needs at least one run")
    return _bootstrap_iqm(tasks, reps, level, np.random.default_rng(seed))


def iqm_band(values: np.ndarray, reps: int = 2_000, level: float = 0.95,
             seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per column of a [seeds, points] array with NaN for missing points: the IQM over the seeds present
    and its percentile-bootstrap interval (seeds resampled with replacement; one random stream across the
    columns). With one seed the band is that seed's value."""
    rng = np.random.default_rng(seed)
    columns = values.shape[1] if values.ndim == 2 else 0
    iqm, low, high = (np.full(columns, np.nan) for _ in range(3))
    for j in range(columns):
        present = values[~np.isnan(values[:, j]), j]
        if present.size:
            iqm[j], low[j], high[j] = _bootstrap_iqm([present], reps, level, rng)
    return iqm, low, high
