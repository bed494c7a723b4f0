"""Statistics over seeds, shared by the plots and the sweeps' tables.

Few seeds are the rule here (3-5), so intervals use Student's t (its quantiles from scipy, which JAX
already installs), and summaries add the interquartile mean that rliable reports (Agarwal et al. 2021,
"Deep RL at the Edge of the Statistical Precipice"): robust to one outlying seed, less noisy than a median.
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
    from scipy import stats as scipy_stats

    return float(scipy_stats.trim_mean(np.asarray(list(values), float), 0.25))


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
