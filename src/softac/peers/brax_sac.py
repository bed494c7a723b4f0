"""Brax's own SAC trainer (`brax.training.agents.sac`, installed with the `[playground]` extra) as a peer, like for
like with softac's device loop on the same MuJoCo Playground env at the same settings (issue 67):
`softac sweep --env playground:NAME --framework brax-sac --preset brax-sac`.

Brax's trainer is one call that runs its whole loop (env steps, replay inserts and `lax.scan`s of gradient steps
in pmapped epochs), evaluates between epochs with its own evaluator and reports through `progress_fn`; this
module turns a softac config into its keywords (settings.brax_sac_settings, refusing what Brax cannot take) and its
reports into a softac-style run directory (`BraxSACRun`: config.yaml, progress.csv, eval.csv, summary.json).

How it is measured, and where it is not softac's protocol:
- evaluation is Brax's: `eval_episodes` deterministic episodes at once (`deterministic_eval`), each from a fresh
  start state (softac's device evaluation starts from the same states each time); Brax spaces its evaluations
  evenly over the run after the replay's prefill, so their steps are Brax's, not multiples of eval_interval;
- steps count the agent's actions, as softac's (Brax counts simulator frames: divided by the action repeat);
- no checkpoints: Brax 0.14's trainer cannot continue a run (it restores a policy, not its critics, optimiser
  states or replay), so a stopped run starts over when run again;
- brax 0.14.2 calls `jax.device_put_replicated`, which JAX 0.10 removed (AttributeError at its first step):
  `replicate_for_pmap` puts it back for the peer's process, as the stack of copies on the local devices it
  was (`with_device_put_replicated`).
"""

from __future__ import annotations

import functools
import time
from pathlib import Path
from typing import Any

from softac.config.sac_config import SACConfig
from softac.peers.settings import brax_sac_settings

BRAX_TRAINING_METRICS = ("critic_loss", "actor_loss", "alpha", "alpha_loss")  # progress.csv's columns it reports


def network_factory(network: dict[str, Any]):
    """Brax's make_sac_networks with the settings' widths, activation and LayerNorms."""
    import jax
    from brax.training.agents.sac import networks

    return functools.partial(networks.make_sac_networks, hidden_layer_sizes=tuple(network["hidden_layer_sizes"]),
                             activation=getattr(jax.nn, network["activation"]),
                             q_network_layer_norm=network["q_network_layer_norm"],
                             policy_network_layer_norm=network["policy_network_layer_norm"])


def with_device_put_replicated() -> None:
    """jax.device_put_replicated for brax 0.14.2 under a JAX without it (removed in JAX 0.10): each leaf stacked
    once per device, on those devices, the leading axis that pmap splits (what the removed function returned)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    if hasattr(jax, "device_put_replicated"):
        return

    def replicate_for_pmap(tree: Any, devices: list) -> Any:
        mesh = jax.sharding.Mesh(np.asarray(devices), ("devices",))
        sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("devices"))
        return jax.tree_util.tree_map(
            lambda leaf: jax.device_put(jnp.stack([jnp.asarray(leaf)] * len(devices)), sharding), tree)

    jax.device_put_replicated = replicate_for_pmap


def check_playground_env(env_id: str, named: str = "brax-sac") -> None:
    """Brax's trainer takes a Brax env: a Playground id, else one line (SoftacError) naming `named`."""
    from softac.config.names import is_playground_id
    from softac.errors import SoftacError

    if not is_playground_id(env_id):
        raise SoftacError(f"{named} trains MuJoCo Playground's envs (--env playground:NAME), not {env_id}")


class BraxSACRun:
    """One Brax SAC run into a softac-style run directory, at the settings a sweep's --preset and --set make; its
    rows come once an epoch of Brax's trainer, whatever log_interval says."""

    def __init__(self, env_id: str, seed: int, steps: int, out: Path, eval_interval: int, eval_episodes: int,
                 config: SACConfig, sweep: dict[str, Any], target_return: float | None = None) -> None:
        from softac.errors import SoftacError

        check_playground_env(env_id)
        if eval_interval <= 0:
            raise SoftacError("brax-sac evaluates with Brax's evaluator between its epochs: eval_interval must be > 0")
        if target_return is not None:
            raise SoftacError("brax-sac runs its whole budget in one call of Brax's trainer: no --target-return")
        self.env_id, self.seed, self.steps, self.out = env_id, seed, steps, out
        self.eval_interval, self.eval_episodes = eval_interval, eval_episodes
        self.config, self.sweep = config, sweep

    def run(self) -> dict[str, Any]:
        from brax.training.agents.sac import train as brax_sac
        from mujoco_playground import wrapper

        from softac.envs import playground
        from softac.errors import SoftacError
        from softac.peers.models import peer_version
        from softac.run.csv_logs import TrainRows
        from softac.run.loggers import CsvLogger
        from softac.run.run_dir import write_config, write_summary

        with_device_put_replicated()
        name = playground.env_name_of(playground.resolve(self.env_id))
        env, env_config, _, _ = playground.load(name)
        # softac's action_repeat on top of the env's own (playground.device_env): frames per agent step
        repeat = max(1, int(getattr(env_config, "action_repeat", 1))) * self.config.action_repeat
        try:
            settings = brax_sac_settings(self.config, int(env.action_size))
        except ValueError as exc:
            raise SoftacError(f"brax-sac: {exc}") from None
        network = settings.pop("network")
        num_evals = max(self.steps // self.eval_interval, 1) + 1
        write_config(self.out, {"framework": "brax-sac", "env_id": self.env_id, "seed": self.seed,
                                "total_steps": self.steps, "algorithm": "SAC", "settings": "sweep",
                                "about": "Brax's SAC trainer (brax.training.agents.sac) at the sweep's settings",
                                "eval_interval": self.eval_interval, "eval_episodes": self.eval_episodes,
                                "softac_settings": self.sweep, "brax": {**settings, "network": network,
                                                                         "action_repeat": repeat,
                                                                         "num_evals": num_evals}},
                     {"versions": {"brax-sac": peer_version("brax-sac")}})
        logs = CsvLogger(self.out, resume_step=-1)  # a run started over: no rows of an earlier attempt
        rows, record = TrainRows(0), {"step": 0, "last": None, "best": None, "best_step": None}
        t0 = time.perf_counter()

        def progress(frames: int, metrics: dict[str, Any]) -> None:
            step = record["step"] = int(frames) // repeat
            if "eval/episode_reward" in metrics:
                mean = float(metrics["eval/episode_reward"])
                logs.log("eval", {"mean_return": mean, "std_return": float(metrics["eval/episode_reward_std"]),
                                  "episodes": self.eval_episodes}, step)
                record["last"] = mean
                if record["best"] is None or mean > record["best"]:
                    record["best"], record["best_step"] = mean, step
            if step > 0:  # Brax reports no training episodes; its losses and alpha are the epoch's means
                row = {k: v for k, v in rows.row(step, time.perf_counter() - t0, 0).items()
                       if k not in ("step", "episodes", "return_mean")}
                row.update({key: float(metrics[f"training/{key}"]) for key in BRAX_TRAINING_METRICS
                            if f"training/{key}" in metrics})
                logs.log("train", row, step)

        try:
            brax_sac.train(env, num_timesteps=self.steps * repeat, episode_length=int(env_config.episode_length),
                           wrap_env_fn=wrapper.wrap_for_brax_training, action_repeat=repeat,
                           num_eval_envs=self.eval_episodes, seed=self.seed, num_evals=num_evals,
                           network_factory=network_factory(network), progress_fn=progress, **settings)
        finally:
            logs.close()
        elapsed = time.perf_counter() - t0
        summary = {"steps": record["step"], "episodes": None, "train_time_s": elapsed, "wall_s": elapsed,
                   "last_eval": record["last"], "best_eval": record["best"], "best_step": record["best_step"],
                   "stopped_early": False, "stop_reason": "steps", "total_steps": self.steps,
                   "framework": "brax-sac"}
        write_summary(self.out, summary)
        return summary
