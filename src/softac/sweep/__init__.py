"""`softac sweep`: many runs at once on Ray Tune (seeds x a grid, or a Tune search), locally or on a cluster.

Each trial is an ordinary run directory DIR/<trial>, trained by its own `softac train` process that the
Ray trial starts and watches; each new row of its eval.csv is reported to Tune, which is what a scheduler
such as ASHA acts on. Nothing about a trial lives only in Ray: whether it is finished is read from its run
directory (RUN/summary.json), so running the same command again, or `softac sweep --resume DIR`, trains
only what is missing and continues interrupted trials from their last checkpoint.

When the trials are done, DIR/summary.csv (a row per trial), DIR/summary.md (mean +- std and 95% CI per
configuration) and DIR/plots/ are written from the run directories; while they run, also after trials end
(at most every 30 s), so a long sweep shows its finished trials.

The package, one module per job: `spec` (what a sweep is, parsing and checking it), `trial` (the process
one Ray trial runs and watches), `driver` (Ray and Tune), `results` (rows, tables and summary files).
The statistics over seeds live in `softac.outputs.seed_stats`, the peers' adapters in `softac.peers`.
"""

from softac.sweep.spec import (DEFAULT_SPACE, FRAMEWORKS, INSTALL_RAY, LOG_DIR, METRIC, PLOT_DIR, RAY_DIR, SEARCHES,
                               SPACE_KINDS, SPEC_FILE, SweepSpec, check_space, default_threshold, grid_points,
                               grid_trials, load_space, load_spec, parse_grid, parse_seeds, planned_trials,
                               prepare_out_dir, trial_name, validate, value_text)
from softac.sweep.trial import read_evals, run_trial, trial_command, trial_process_env, trial_state
from softac.sweep.results import (SUCCESS_THRESHOLD, aggregate, check_command, ended_trials, markdown_table,
                                  trial_dirs, trial_rows, unfinished_trials, write_summaries)
from softac.sweep.driver import run_sweep

__all__ = ["DEFAULT_SPACE", "FRAMEWORKS", "INSTALL_RAY", "LOG_DIR", "METRIC", "PLOT_DIR", "RAY_DIR", "SEARCHES",
           "SPACE_KINDS", "SPEC_FILE", "SUCCESS_THRESHOLD", "SweepSpec", "aggregate", "check_command", "check_space",
           "default_threshold", "ended_trials", "grid_points", "grid_trials", "load_space", "load_spec",
           "markdown_table", "parse_grid", "parse_seeds", "planned_trials", "prepare_out_dir", "read_evals",
           "run_sweep", "run_trial", "trial_command", "trial_dirs", "trial_name", "trial_process_env", "trial_rows",
           "trial_state", "unfinished_trials", "validate", "value_text", "write_summaries"]
