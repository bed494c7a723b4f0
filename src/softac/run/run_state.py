"""`RunState`: a run's progress beside the learner's parameters, checkpointed as one unit.

The learner (`sac.SACState`: networks, targets, optimisers, alpha, its key) says what the agent knows;
the run state says where its training stands: the step and episode counters, the random streams the
loop draws from (exploration noise, evaluation noise, replay sampling and warm-up actions), the best
and last evaluation, the returns behind the progress bar, and the run directory it belongs to. The
agent owns one; the training loop reads and advances it; a checkpoint saves and restores all of it, so
a resumed run continues exactly where a straight one would be.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from softac.errors import SoftacError
from softac.replay.exploration import ColoredNoise, RepeatedNoise, SdeNoise
from softac.run.run_dir import check_new_run_dir, checkpoint_path, holds_run, run_of_last_checkpoint


@dataclass
class RunState:
    act_key: Any  # raw uint32[2] JAX key: exploration noise while training
    predict_key: Any  # raw uint32[2] JAX key: stochastic predict() and evaluation, kept apart from training
    rng: np.random.Generator  # replay sampling, warm-up actions and random_action_prob
    num_steps: int = 0
    num_episodes: int = 0
    train_time_s: float = 0.0
    best_eval: float | None = None
    best_step: int | None = None
    last_eval: float | None = None
    last_eval_step: int | None = None
    recent_returns: list[float] = field(default_factory=list)  # the last episodes' returns (progress bar, logs)
    recent_successes: list[float] = field(default_factory=list)  # their successes, where the env reports them
    last_success: float | None = None  # the last evaluation's success rate (envs that report success)
    # the run directory this state is the latest of (loaded from its checkpoints/last, or last trained into):
    # the only run it may go on writing into; any other directory must hold no run (never overwritten)
    run_dir: Path | None = None
    restored_from: Path | None = None  # the checkpoint directory it was loaded from
    # pink: each env's noise sequence; gsde: its exploration matrix; repeat: the held noise (else the act_key's)
    noise: ColoredNoise | SdeNoise | RepeatedNoise | None = None

    @classmethod
    def new(cls, seed: int, noise: ColoredNoise | SdeNoise | RepeatedNoise | None = None) -> "RunState":
        import jax.numpy as jnp

        keys = np.random.default_rng([seed, 0xAC7]).integers(0, 2**32, (2, 2), dtype=np.uint32)
        return cls(act_key=jnp.asarray(keys[0]), predict_key=jnp.asarray(keys[1]), rng=np.random.default_rng(seed),
                   noise=noise)

    def checkpoint_parts(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """The checkpoint's meta entries and arrays for this state (the format of checkpoint version 1)."""
        meta = {
            "num_steps": self.num_steps,
            "num_episodes": self.num_episodes,
            "train_time_s": self.train_time_s,
            "numpy_rng": self.rng.bit_generator.state,
            "trainer": {"best_eval": self.best_eval, "best_step": self.best_step, "last_eval": self.last_eval,
                        "last_eval_step": self.last_eval_step, "recent_returns": list(self.recent_returns),
                        "recent_successes": list(self.recent_successes), "last_success": self.last_success},
        }
        arrays = {"act_key": np.asarray(self.act_key), "predict_key": np.asarray(self.predict_key)}
        if self.noise is not None:
            meta["exploration_noise"], noise_arrays = self.noise.checkpoint_parts()
            arrays.update({f"noise/{name}": value for name, value in noise_arrays.items()})
        return meta, arrays

    def restore(self, meta: dict[str, Any], arrays: dict[str, np.ndarray], where: Path | str = "") -> None:
        """Take the state a checkpoint saved; `where` is its directory (a run's checkpoints/last makes this
        state that run's latest, so it may go on writing into it)."""
        import jax.numpy as jnp

        self.act_key = jnp.asarray(arrays["act_key"])
        self.predict_key = jnp.asarray(arrays["predict_key"])
        self.num_steps = int(meta["num_steps"])
        self.num_episodes = int(meta["num_episodes"])
        self.train_time_s = float(meta.get("train_time_s", 0.0))
        self.rng.bit_generator.state = meta["numpy_rng"]
        if self.noise is not None and meta.get("exploration_noise") is not None:
            self.noise.restore(meta["exploration_noise"], {name.removeprefix("noise/"): value
                                                           for name, value in arrays.items()
                                                           if name.startswith("noise/")})
        trainer = meta.get("trainer") or {}
        self.best_eval, self.best_step = trainer.get("best_eval"), trainer.get("best_step")
        self.last_eval, self.last_eval_step = trainer.get("last_eval"), trainer.get("last_eval_step")
        self.recent_returns = list(trainer.get("recent_returns", []))
        self.recent_successes = list(trainer.get("recent_successes", []))
        self.last_success = trainer.get("last_success")
        self.restored_from = Path(where).resolve() if where else None
        self.run_dir = run_of_last_checkpoint(self.restored_from) if self.restored_from else None

    def check_may_write(self, run: Path) -> None:
        """Training writes only into a new directory or the run this state is the latest of: a loaded agent
        never writes over another run, nor rewinds its own from an older (best) checkpoint. Its own run
        includes one killed (kill -9, power loss) before its first periodic checkpoint, continued from the
        step-0 checkpoint."""
        if self.run_dir == run.resolve():
            return
        if self.num_steps > 0 and holds_run(run):
            raise SoftacError(f"{run} already holds a run that this agent is not the latest state of (it was "
                              f"loaded from {self.restored_from or 'elsewhere'}); train into a new directory, or "
                              f"load {checkpoint_path(run, 'last')} to continue that run")
        check_new_run_dir(run)
