"""The peers softac is compared with: how to make them, and three ways to run them (a throughput probe,
a run to a target return, and a whole run that writes a softac-style run directory, evaluated exactly as
softac evaluates). `softac bench` and `softac sweep --framework PEER` run each in its own process through
this module's entry point:

    python -m softac.peers run|throughput|solve PEER --env ENV [...]

which prints one JSON line (`python -m softac.peers.bench ...`, the older form, still works). PEER is one of
`PEERS`: Stable-Baselines3's SAC and SBX's SAC at their defaults, SBX's CrossQ at its defaults, SBX's
CrossQ at the settings of softac's `crossq` preset (like for like with the suite's presets), for goal envs
SB3's and SBX's SAC with SB3's HerReplayBuffer (these need the `[bench]` extra), and Brax's own SAC trainer on
MuJoCo Playground's envs (`brax-sac`, brax_sac.py; the `[playground]` extra)."""


from __future__ import annotations

# the package's parts: what each peer is and how its model is made (models), its checkpoints (checkpoints), and
# the runs and the process entry point (runs; `python -m softac.peers` runs __main__.py)
from softac.peers.checkpoints import load_peer_checkpoint, save_peer_checkpoint
from softac.peers.models import (HER_LEARNING_STARTS, HER_SETTINGS, PEERS, THROUGHPUT_LEARNING_STARTS, Peer,
                                 check_her_env, crossq_settings, missing_peers, normalized_env, peer_env, peer_model,
                                 peer_settings, peer_version, sweep_config, without_log_dir)
from softac.peers.runs import PeerRun, arguments, main, peer_run, peer_solve, peer_throughput

__all__ = ["PEERS", "Peer", "PeerRun", "HER_LEARNING_STARTS", "HER_SETTINGS", "THROUGHPUT_LEARNING_STARTS",
           "arguments", "check_her_env", "crossq_settings", "load_peer_checkpoint", "main", "missing_peers",
           "normalized_env", "peer_env", "peer_model", "peer_run", "peer_settings", "peer_solve", "peer_throughput",
           "peer_version", "save_peer_checkpoint", "sweep_config", "without_log_dir"]
