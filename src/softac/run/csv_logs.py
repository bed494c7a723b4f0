"""The run directory's CSV files (written through softac.run.loggers.CsvLogger, read by plots and reports) and the
progress bar."""

from __future__ import annotations

import collections
import csv
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from softac.learner.metrics import METRICS
from softac.run.run_dir import write_atomic

# success columns stay empty for envs that report no success (info["is_success"]); a file written before they
# existed keeps its own header when its run is resumed (CsvLog)
PROGRESS_COLUMNS = ["step", "time_s", "fps", "episodes", "return_mean", *METRICS, "success_rate"]
EPISODE_COLUMNS = ["step", "return", "length", "success"]
EVAL_COLUMNS = ["step", "mean_return", "std_return", "episodes", "success_rate"]
RECENT_EPISODES = 20  # the training episodes behind progress.csv's return_mean and the progress bar


class TrainRows:
    """progress.csv's bookkeeping columns, with one meaning for softac and the peers it is compared with:
    `time_s` the run's seconds so far (evaluations included), `fps` env steps per second since the previous
    row, `episodes` the training episodes finished so far, `return_mean` the mean return of the last
    RECENT_EPISODES of them, `success_rate` the share of those that succeeded (envs that report success)."""

    def __init__(self, step: int, recent_returns: list[float] | tuple[float, ...] = (),
                 recent_successes: list[float] | tuple[float, ...] = ()):
        self.recent: collections.deque[float] = collections.deque(recent_returns, maxlen=RECENT_EPISODES)
        self.successes: collections.deque[float] = collections.deque(recent_successes, maxlen=RECENT_EPISODES)
        self.last_step, self.last_time = step, time.perf_counter()

    def episode_finished(self, episode_return: float, success: float | None = None) -> None:
        self.recent.append(episode_return)
        if success is not None:
            self.successes.append(float(success))

    def recent_mean(self) -> float | None:
        return float(np.mean(self.recent)) if self.recent else None

    def success_rate(self) -> float | None:
        return float(np.mean(self.successes)) if self.successes else None

    def row(self, step: int, time_s: float, episodes: int) -> dict[str, Any]:
        now = time.perf_counter()
        fps = (step - self.last_step) / max(now - self.last_time, 1e-9)
        self.last_step, self.last_time = step, now
        mean, success = self.recent_mean(), self.success_rate()
        return {"step": step, "time_s": round(time_s, 3), "fps": round(fps, 1), "episodes": episodes,
                "return_mean": float("nan") if mean is None else mean,
                "success_rate": float("nan") if success is None else success}


class CsvLog:
    """Appends rows to a CSV file; on resume drops rows past the checkpoint's step."""

    def __init__(self, path: Path, columns: list[str], keep_until_step: int | None = None):
        self.path = path
        self.columns = _header_of(path) or columns  # a resumed run's file keeps the columns it began with
        if keep_until_step is not None and path.exists():
            self._truncate_after(keep_until_step)
        new = not path.exists() or path.stat().st_size == 0
        self.file = open(path, "a", newline="")
        self.writer = csv.writer(self.file)
        if new:
            self.writer.writerow(columns)
            self.file.flush()

    def _truncate_after(self, step: int) -> None:
        """Keep the header and the whole rows up to `step`: a kill can leave a half-written last row."""
        import io

        with open(self.path, newline="") as f:
            rows = list(csv.reader(f))
        if not rows:
            return
        whole = [r for r in rows[1:] if len(r) == len(self.columns) and _as_int(r[0]) is not None]
        kept = [self.columns] + [r for r in whole if _as_int(r[0]) <= step]
        text = io.StringIO()
        csv.writer(text).writerows(kept)
        write_atomic(self.path, text.getvalue().encode())

    def write(self, row: dict[str, Any]) -> None:
        self.writer.writerow([_fmt(row.get(c, "")) for c in self.columns])
        self.file.flush()

    def close(self) -> None:
        self.file.close()


def _header_of(path: Path) -> list[str] | None:
    try:
        with open(path, newline="") as f:
            return next(csv.reader(f), None) or None
    except OSError:
        return None


def _as_int(text: str) -> int | None:
    try:
        return int(float(text))
    except ValueError:
        return None


def _fmt(value: Any) -> Any:
    if isinstance(value, float):
        return "" if math.isnan(value) else f"{value:.6g}"
    return value


def read_csv(path: str | Path) -> list[dict[str, str]]:
    path = Path(path)
    if not path.exists():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def in_notebook() -> bool:
    """Whether this process is a Jupyter kernel (IPython's kernel shell), where stderr is not a terminal yet
    output shows live in the notebook."""
    ipython = sys.modules.get("IPython")
    if ipython is None:
        return False
    shell = ipython.get_ipython()
    return shell is not None and type(shell).__name__ == "ZMQInteractiveShell"


def notebook_bar_class() -> Any:
    """tqdm's notebook bar (a live widget) when this process is a Jupyter kernel with ipywidgets, else None."""
    if not in_notebook():
        return None
    try:
        import ipywidgets  # noqa: F401  (tqdm.notebook draws with it)
        from tqdm.notebook import tqdm as notebook_tqdm
    except ImportError:
        return None
    return notebook_tqdm


class Progress:
    """A tqdm bar on a terminal, tqdm's notebook bar in Jupyter (a kernel's stderr is not a terminal; a kernel
    without ipywidgets gets the terminal bar, which Jupyter redraws in place too); plain log lines every `every_s`
    seconds elsewhere (CI, files)."""

    def __init__(self, start: int, end: int, enabled: bool | None = None, every_s: float = 10.0):
        self.start, self.end = start, end
        notebook = enabled is not False and in_notebook()
        self.tty = (sys.stderr.isatty() or notebook) if enabled is None else enabled
        self.every_s = every_s
        self.t0 = time.perf_counter()
        self.last_line = self.t0
        self.bar = None
        self.info: dict[str, str] = {}
        if self.tty:
            from tqdm import tqdm

            bar = (notebook_bar_class() if notebook else None) or tqdm
            kwargs = {} if bar is not tqdm else {"dynamic_ncols": True, "file": sys.stderr}
            self.bar = bar(total=end - start, unit="step",
                           bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}, {rate_fmt}{postfix}]",
                           **kwargs)

    def update(self, step: int, **info: Any) -> None:
        for k, v in info.items():
            if v is not None:
                self.info[k] = f"{v:.1f}" if isinstance(v, float) else str(v)
        if self.bar is not None:
            self.bar.n = step - self.start
            self.bar.set_postfix(self.info, refresh=False)
            self.bar.update(0)
            return
        now = time.perf_counter()
        if now - self.last_line >= self.every_s:
            self.last_line = now
            self.line(step)

    def line(self, step: int) -> None:
        elapsed = time.perf_counter() - self.t0
        rate = (step - self.start) / elapsed if elapsed > 0 else 0.0
        eta = (self.end - step) / rate if rate > 0 else float("inf")
        extra = " ".join(f"{k}={v}" for k, v in self.info.items())
        eta_s = f"{eta:.0f}s" if math.isfinite(eta) else "?"
        print(f"step {step}/{self.end} | {rate:.0f} steps/s | eta {eta_s} | {extra}", file=sys.stderr, flush=True)

    def close(self, step: int) -> None:
        if self.bar is not None:
            self.bar.n = step - self.start
            self.bar.refresh()
            self.bar.close()
        else:
            self.line(step)
