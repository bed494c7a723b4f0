"""The update's metrics, named once: in progress.csv's column order (DESIGN.md's run directory), each with the
gradient steps it is the mean over (the critic's or the actor's: under policy_delay the actor's metrics are
means over actor steps only, issue 42). The update computes them (sac.py, losses.py), the progress rows and the
loggers write them (softac.run.csv_logs), the plots draw them. No JAX here: the CSV and plot readers import it."""

# name -> the steps it is a mean over
METRICS = {"critic_loss": "critic", "actor_loss": "actor", "alpha": "critic", "alpha_loss": "actor",
           "q1_mean": "critic", "q2_mean": "critic", "log_prob_mean": "actor"}
CRITIC_METRICS = tuple(name for name, steps in METRICS.items() if steps == "critic")
POLICY_METRICS = tuple(name for name, steps in METRICS.items() if steps == "actor")
