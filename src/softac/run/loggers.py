"""Where a run's metrics go: one `Logger` interface, several backends.

The training loop hands every logger the same records, each a dict of numbers at an env step:

    "train"    a row every log_interval steps (progress.csv's columns: fps, losses, alpha, ...)
    "rollout"  a finished training episode (episodes.csv: return, length; success where the env reports it)
    "eval"     an evaluation (eval.csv: mean_return, std_return, episodes; success_rate where reported)

The CSV files are always written (plots, reports, sweeps and resume read them). TensorBoard (the default),
Weights & Biases and MLflow are chosen with the `loggers` config key (`--logger tensorboard,wandb`); any
object with `log(kind, values, step)` and `close()` can be passed to `agent.learn(loggers=[...])`.
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import sys
from pathlib import Path
from typing import Any

from softac.errors import SoftacError
from softac.run.csv_logs import EPISODE_COLUMNS, EVAL_COLUMNS, PROGRESS_COLUMNS, CsvLog
from softac.run.run_dir import write_atomic

KINDS = ("train", "rollout", "eval")
# the package each backend imports, and the extra that installs it
BACKEND_PACKAGES = {"tensorboard": ("tensorboardX", "softac"), "wandb": ("wandb", "softac[wandb]"),
                    "mlflow": ("mlflow", "softac[mlflow]")}
LOGGER_IDS_FILE = "loggers.json"  # the W&B and MLflow run ids, so a resumed run continues the same runs


class Logger:
    """The interface: subclass it (or write any class with these two methods) for your own backend."""

    def log(self, kind: str, values: dict[str, float], step: int) -> None:
        """One record: `kind` is train, rollout or eval; `values` are plain numbers; `step` the env step."""

    def close(self) -> None:
        """The run is over (or interrupted): flush and release."""


def check_backends_installed(names: list[str]) -> None:
    """Before a run starts: a chosen backend whose package is missing is bad input, not a failed run."""
    for name in names:
        package, extra = BACKEND_PACKAGES[name]
        if importlib.util.find_spec(package) is None:
            raise SoftacError(f"logger {name} needs the {package} package: pip install '{extra}'")


def _numbers(values: dict[str, Any]) -> dict[str, float]:
    """The values a metrics backend can plot: finite numbers, step left out (it is the x axis)."""
    return {k: float(v) for k, v in values.items()
            if k != "step" and isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)}


class CsvLogger(Logger):
    """progress.csv, episodes.csv and eval.csv; on resume, rows past the checkpoint's step are dropped."""

    COLUMNS = {"train": PROGRESS_COLUMNS, "rollout": EPISODE_COLUMNS, "eval": EVAL_COLUMNS}
    FILES = {"train": "progress.csv", "rollout": "episodes.csv", "eval": "eval.csv"}

    def __init__(self, run_dir: Path, resume_step: int | None = None):
        self.files = {kind: CsvLog(run_dir / self.FILES[kind], self.COLUMNS[kind], resume_step) for kind in KINDS}

    def log(self, kind: str, values: dict[str, float], step: int) -> None:
        self.files[kind].write({"step": step, **values})

    def close(self) -> None:
        for log in self.files.values():
            log.close()


class TensorBoardLogger(Logger):
    """RUN/tb/: train/*, eval/mean_return and eval/std_return, rollout/episode_return and episode_length."""

    TAGS = {"rollout": {"return": "episode_return", "length": "episode_length", "success": "episode_success"},
            "eval": {"mean_return": "mean_return", "std_return": "std_return", "success_rate": "success_rate"}}

    def __init__(self, run_dir: Path):
        from tensorboardX import SummaryWriter

        self.writer = SummaryWriter(str(run_dir / "tb"), flush_secs=10)

    def log(self, kind: str, values: dict[str, float], step: int) -> None:
        names = self.TAGS.get(kind)
        for key, value in _numbers(values).items():
            if names is None or key in names:
                self.writer.add_scalar(f"{kind}/{names[key] if names else key}", value, step)

    def close(self) -> None:
        self.writer.close()


def _read_ids(run_dir: Path) -> dict[str, Any]:
    try:
        return json.loads((run_dir / LOGGER_IDS_FILE).read_text())
    except (OSError, ValueError):
        return {}


def _write_id(run_dir: Path, backend: str, value: dict[str, Any]) -> None:
    ids = {**_read_ids(run_dir), backend: value}
    write_atomic(run_dir / LOGGER_IDS_FILE, json.dumps(ids, indent=1).encode())


def _wandb_has_api_key() -> bool:
    if os.environ.get("WANDB_API_KEY"):
        return True
    import netrc

    try:
        return netrc.netrc().authenticators("api.wandb.ai") is not None
    except (OSError, netrc.NetrcParseError):
        return False


class WandbLogger(Logger):
    """A W&B run per softac run, its files in RUN/wandb. Offline (sync later with `wandb sync RUN/wandb/...`)
    when WANDB_MODE=offline or no API key is set up; the project is $WANDB_PROJECT, else softac. A resumed
    softac run continues the same W&B run; metrics use env_step as their x axis."""

    def __init__(self, run_dir: Path, config: dict[str, Any]):
        import wandb

        mode = os.environ.get("WANDB_MODE") or ("online" if _wandb_has_api_key() else "offline")
        previous = _read_ids(run_dir).get("wandb", {})
        self.run = wandb.init(project=os.environ.get("WANDB_PROJECT", "softac"), name=run_dir.name,
                              id=previous.get("id"), resume="allow" if previous else None, dir=str(run_dir),
                              config=config, mode=mode, reinit="create_new",
                              settings=wandb.Settings(console="off", silent=True))
        _write_id(run_dir, "wandb", {"id": self.run.id, "mode": mode})
        if mode == "offline" and not os.environ.get("WANDB_MODE"):
            print(f"wandb: no API key set up, logging offline to {run_dir / 'wandb'}; upload later with "
                  f"`wandb sync {run_dir / 'wandb'}/offline-run-*`", file=sys.stderr)
        self.run.define_metric("env_step")
        self.run.define_metric("*", step_metric="env_step")

    def log(self, kind: str, values: dict[str, float], step: int) -> None:
        self.run.log({**{f"{kind}/{k}": v for k, v in _numbers(values).items()}, "env_step": step})

    def close(self) -> None:
        self.run.finish()


class MlflowLogger(Logger):
    """An MLflow run per softac run, in experiment $MLFLOW_EXPERIMENT_NAME (else softac) at MLflow's tracking
    URI ($MLFLOW_TRACKING_URI, else MLflow's default: ./mlflow.db or ./mlruns); the config goes in as params.
    A resumed softac run continues the same MLflow run."""

    def __init__(self, run_dir: Path, config: dict[str, Any]):
        import mlflow

        self.client = mlflow.MlflowClient()
        previous = _read_ids(run_dir).get("mlflow", {})
        if previous.get("run_id") and previous.get("tracking_uri") == mlflow.get_tracking_uri():
            self.run_id = previous["run_id"]
            self.client.update_run(self.run_id, status="RUNNING")
        else:
            name = os.environ.get("MLFLOW_EXPERIMENT_NAME", "softac")
            experiment = self.client.get_experiment_by_name(name)
            experiment_id = experiment.experiment_id if experiment else self.client.create_experiment(name)
            run = self.client.create_run(experiment_id, run_name=run_dir.name, tags={"softac.run_dir": str(run_dir)})
            self.run_id = run.info.run_id
            for key, value in config.items():  # MLflow params are strings of at most 6000 characters
                self.client.log_param(self.run_id, key, str(value)[:6000])
        _write_id(run_dir, "mlflow", {"run_id": self.run_id, "tracking_uri": mlflow.get_tracking_uri()})
        print(f"mlflow: run {self.run_id} at {mlflow.get_tracking_uri()} (`mlflow ui --backend-store-uri "
              f"{mlflow.get_tracking_uri()}` shows it)", file=sys.stderr)

    def log(self, kind: str, values: dict[str, float], step: int) -> None:
        import time

        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        metrics = [Metric(f"{kind}/{k}", v, now, step) for k, v in _numbers(values).items()]
        if metrics:
            self.client.log_batch(self.run_id, metrics=metrics)

    def close(self) -> None:
        self.client.set_terminated(self.run_id)


class Loggers(Logger):
    """Several loggers as one: what the training loop writes to."""

    def __init__(self, loggers: list[Any]):
        self.loggers = list(loggers)

    def log(self, kind: str, values: dict[str, float], step: int) -> None:
        for logger in self.loggers:
            logger.log(kind, values, step)

    def close(self) -> None:
        errors = []
        for logger in self.loggers:  # every backend gets closed even when one of them fails to
            try:
                logger.close()
            except Exception as exc:
                errors.append(exc)
        if errors:
            raise errors[0]


def run_loggers(run_dir: Path, backends: list[str], config: dict[str, Any], resume_step: int) -> list[Logger]:
    """The run directory's CSV files and the chosen backends."""
    made: list[Logger] = [CsvLogger(run_dir, resume_step)]
    for name in backends:
        try:
            if name == "tensorboard":
                made.append(TensorBoardLogger(run_dir))
            elif name == "wandb":
                made.append(WandbLogger(run_dir, config))
            elif name == "mlflow":
                made.append(MlflowLogger(run_dir, config))
        except Exception as exc:
            Loggers(made).close()
            raise SoftacError(f"logger {name} could not start: {type(exc).__name__}: {exc}".splitlines()[0]) from None
    return made
