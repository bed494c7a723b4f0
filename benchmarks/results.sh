#!/usr/bin/env bash
# Regenerates the sweeps behind docs/results.md: softac's presets on 5 seeds, Stable-Baselines3's SAC at its
# defaults on 3 seeds, same step budgets, same evaluation (10 deterministic episodes), one trial per CPU.
# Needs the [ray] and [bench] extras (make bench, then pip install -e '.[ray]'). Rerunning continues where it
# stopped (finished trials are not redone). Then: python benchmarks/results_doc.py $SWEEPS
set -euo pipefail
SOFTAC=${SOFTAC:-.venv/bin/softac}
SWEEPS=${SWEEPS:-sweeps}
$SOFTAC sweep --env InvertedPendulum-v5 --seeds 5 --steps 20000 --threshold 1000 --out $SWEEPS/InvertedPendulum-v5-softac
$SOFTAC sweep --env InvertedPendulum-v5 --seeds 3 --steps 20000 --threshold 1000 --framework sb3 --out $SWEEPS/InvertedPendulum-v5-sb3
$SOFTAC sweep --env InvertedPendulum-v4 --seeds 5 --steps 20000 --threshold 1000 --out $SWEEPS/InvertedPendulum-v4-softac
$SOFTAC sweep --env InvertedPendulum-v4 --seeds 3 --steps 20000 --threshold 1000 --framework sb3 --out $SWEEPS/InvertedPendulum-v4-sb3
$SOFTAC sweep --env Pusher-v5 --seeds 5 --steps 30000 --threshold -40 --out $SWEEPS/Pusher-v5-softac
$SOFTAC sweep --env Pusher-v5 --seeds 3 --steps 30000 --threshold -40 --framework sb3 --out $SWEEPS/Pusher-v5-sb3
