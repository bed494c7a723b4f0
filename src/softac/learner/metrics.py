"""The update's metrics, named once: in progress.csv's column order (DESIGN.md's run directory), each with the
gradient steps it is the mean over (the critic's or the actor's: under policy_delay the actor's metrics are
means over actor steps only, issue 42). The update computes them (sac.py, losses.py) and sums them here, the
progress rows and the loggers write them (softac.run.csv_logs), the plots draw them. JAX only where the sums
start: the CSV and plot readers import this module too."""

from __future__ import annotations

from typing import Any

# name -> the steps it is a mean over
METRICS = {"critic_loss": "critic", "actor_loss": "actor", "alpha": "critic", "alpha_loss": "actor",
           "q1_mean": "critic", "q2_mean": "critic", "log_prob_mean": "actor"}
CRITIC_METRICS = tuple(name for name, steps in METRICS.items() if steps == "critic")
POLICY_METRICS = tuple(name for name, steps in METRICS.items() if steps == "actor")


# ---- sums over many updates ----------------------------------------------------------------------------
# Each metric is summed over the gradient steps that computed it and divided once, when a progress row is
# written (issue 42): the actor's over actor steps only, so a row under policy_delay never shows a step that
# did not update the actor, and each row is the interval's mean as SB3 and CleanRL log it.
CRITIC_STEPS, ACTOR_STEPS = "critic_steps", "actor_steps"


def zero_totals() -> dict[str, Any]:
    """Sums of every metric and the counts of critic and actor steps behind them, all zero."""
    import jax.numpy as jnp

    return {name: jnp.zeros((), jnp.float32) for name in (*CRITIC_METRICS, *POLICY_METRICS, CRITIC_STEPS, ACTOR_STEPS)}


def add_to_totals(totals: dict, metrics: dict, counter: str) -> dict:
    return {**totals, **{k: totals[k] + v for k, v in metrics.items()}, counter: totals[counter] + 1.0}


def metric_means(totals: dict[str, Any]) -> dict[str, float]:
    """The mean of each metric over the steps that computed it; a metric no step computed is left out."""
    means = {}
    for names, counter in ((CRITIC_METRICS, CRITIC_STEPS), (POLICY_METRICS, ACTOR_STEPS)):
        count = float(totals[counter])
        if count > 0:
            means.update({k: float(totals[k]) / count for k in names})
    return means
