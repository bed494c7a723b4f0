"""Figures from run directories: learning curves, the 2x3 metric grid, multi-seed comparisons.

Everything reads the run directory's CSV files, so it works on finished, running and
interrupted runs alike, with Matplotlib's non-interactive Agg backend (no display needed).
"""

from __future__ import annotations

import dataclasses
import json
import textwrap
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from softac.config.sac_config import RECORD_ONLY_KEYS
from softac.errors import SoftacError
from softac.run.csv_logs import read_csv
from softac.outputs.seed_stats import interquartile_mean, iqm_band, stratified_bootstrap_iqm

METRIC_GRID = [  # (column, title), the notebooks' 2x3 grid
    ("critic_loss", "critic loss"),
    ("actor_loss", "actor loss"),
    ("alpha", "entropy coefficient (alpha)"),
    (("q1_mean", "q2_mean"), "Q1 / Q2 mean"),
    ("log_prob_mean", "log-prob mean"),
    ("alpha_loss", "alpha loss"),
]
LEGEND_INSIDE_CHARS = 50  # longer legend labels go below the axes, or they squeeze the plot to a sliver
BASELINE_STYLES = {"random": ":", "zero": "-.", "heuristic": "--"}


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _floats(rows: list[dict[str, str]], key: str) -> np.ndarray:
    out = []
    for r in rows:
        try:
            out.append(float(r.get(key, "") or "nan"))
        except ValueError:
            out.append(float("nan"))
    return np.asarray(out, float)


def moving_average(values: np.ndarray, window: int) -> np.ndarray:
    """Trailing mean over up to `window` values (shorter at the start, so the curve starts at step 0)."""
    if len(values) == 0:
        return values
    csum = np.cumsum(np.insert(values, 0, 0.0))
    idx = np.arange(1, len(values) + 1)
    start = np.maximum(idx - window, 0)
    return (csum[idx] - csum[start]) / (idx - start)


def run_label(run: Path) -> str:
    config = load_run_config(run)
    return f"{config.get('env_id', '?')} seed {config.get('seed', '?')}"


def load_run_config(run: Path) -> dict[str, Any]:
    path = run / "config.yaml"
    if not path.exists():
        raise SoftacError(f"{run} is not a softac run directory (no config.yaml)")
    try:
        return yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError:
        raise SoftacError(f"{path} is unreadable") from None


def load_baselines(run: Path) -> dict[str, Any] | None:
    path = run / "baselines.json"
    if path.exists():
        try:
            return json.loads(path.read_text()).get("baselines")
        except (json.JSONDecodeError, AttributeError):
            return None
    return None


def _draw_baselines(ax, baselines: dict[str, Any] | None) -> None:
    for name, stats in (baselines or {}).items():
        ax.axhline(stats["mean_return"], color="grey", lw=1.2, ls=BASELINE_STYLES.get(name, ":"),
                   label=f"{name} baseline ({stats['mean_return']:.1f})")


def plot_learning_curve(run: Path, out: Path, baselines: dict[str, Any] | None = None) -> Path:
    plt = _pyplot()
    episodes = read_csv(run / "episodes.csv")
    evals = read_csv(run / "eval.csv")
    fig, ax = plt.subplots(figsize=(9, 5), constrained_layout=True)
    if episodes:
        steps, returns = _floats(episodes, "step"), _floats(episodes, "return")
        window = max(1, min(50, len(returns) // 10 or 1))
        ax.plot(steps, returns, color="tab:blue", alpha=0.25, lw=0.8, label="training episode return")
        ax.plot(steps, moving_average(returns, window), color="tab:blue", lw=2,
                label=f"moving average ({window} episodes)")
    if evals:
        steps, mean, std = _floats(evals, "step"), _floats(evals, "mean_return"), _floats(evals, "std_return")
        ax.errorbar(steps, mean, yerr=std, color="tab:orange", marker="o", ms=4, capsize=3, lw=1.5,
                    label="deterministic evaluation (mean ± std)")
    _draw_baselines(ax, baselines)
    if not episodes and not evals:
        ax.text(0.5, 0.5, "no episodes finished yet", ha="center", va="center", transform=ax.transAxes)
    return _finish_curve(plt, fig, ax, out, "episode return", f"Learning curve: {run_label(run)}")


def reports_success(run: Path) -> bool:
    """Whether a run's env reports success (goal envs): a value in eval.csv's or episodes.csv's success column."""
    return (any(r.get("success_rate") for r in read_csv(run / "eval.csv"))
            or any(r.get("success") for r in read_csv(run / "episodes.csv")))


def plot_success_curve(run: Path, out: Path) -> Path:
    """A goal env's success rate: the training episodes' (moving average) and each evaluation's."""
    plt = _pyplot()
    episodes = [r for r in read_csv(run / "episodes.csv") if r.get("success")]
    evals = [r for r in read_csv(run / "eval.csv") if r.get("success_rate")]
    fig, ax = plt.subplots(figsize=(9, 5), constrained_layout=True)
    if episodes:
        success = _floats(episodes, "success")
        window = max(1, min(50, len(success) // 10 or 1))
        ax.plot(_floats(episodes, "step"), moving_average(success, window), color="tab:blue", lw=2,
                label=f"training episodes (moving average of {window})")
    if evals:
        ax.plot(_floats(evals, "step"), _floats(evals, "success_rate"), color="tab:orange", marker="o", ms=4,
                lw=1.5, label="deterministic evaluation")
    ax.set_ylim(-0.03, 1.03)
    return _finish_curve(plt, fig, ax, out, "success rate", f"Success rate: {run_label(run)}")


def plot_metric_grid(run: Path, out: Path) -> Path:
    plt = _pyplot()
    rows = [r for r in read_csv(run / "progress.csv") if r.get("critic_loss")]
    fig, axes = plt.subplots(2, 3, figsize=(14, 7.5), constrained_layout=True)
    steps = _floats(rows, "step")
    for ax, (column, title) in zip(axes.flat, METRIC_GRID):
        columns = column if isinstance(column, tuple) else (column,)
        marker = "o" if len(rows) < 30 else None  # few rows: show where the points are
        for i, name in enumerate(columns):
            ax.plot(steps, _floats(rows, name), lw=1.5, marker=marker, ms=3, color=f"C{i}",
                    label=name.replace("_mean", "").upper() if len(columns) > 1 else None)
        if len(columns) > 1:
            ax.legend(fontsize=9)
        alpha = _floats(rows, "alpha") if column == "alpha" and rows else None
        if alpha is not None and np.nanmin(alpha) > 0 and np.nanmax(alpha) / np.nanmin(alpha) > 10:
            ax.set_yscale("log")  # alpha often falls by orders of magnitude
        if not rows:
            ax.text(0.5, 0.5, "no updates logged yet", ha="center", va="center", transform=ax.transAxes)
        ax.set_title(title)
        ax.set_xlabel("environment steps")
        ax.grid(alpha=0.3)
    fig.suptitle(f"Training metrics: {run_label(run)}", fontsize=13)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out


def _config_key(config: dict[str, Any]) -> str:
    """What tells configurations apart: everything but the seed and bookkeeping."""
    ignore = {"seed", "total_steps", "device", "loggers", *RECORD_ONLY_KEYS}
    return json.dumps({k: v for k, v in sorted(config.items()) if k not in ignore}, sort_keys=True, default=str)


def _describe_differences(configs: list[dict[str, Any]]) -> list[str]:
    """Label each configuration by the keys that vary; runs of other frameworks (SB3, SBX) by their name,
    since their configs share few keys with softac's."""
    frameworks = [c.get("framework", "softac") for c in configs]
    labels = []
    for c, framework in zip(configs, frameworks):
        same = [o for o, f in zip(configs, frameworks) if f == framework]
        keys = sorted({k for o in same for k in o if k not in ("seed", "loggers") and k not in RECORD_ONLY_KEYS})
        varying = [k for k in keys if len({json.dumps(o.get(k), default=str) for o in same}) > 1]
        parts = ([framework] if len(set(frameworks)) > 1 else []) + [f"{k}={_short(c.get(k))}" for k in varying]
        labels.append(", ".join(parts) if parts else str(c.get("env_id", "runs")))
    return labels


def _short(value: Any) -> str:
    """A config value for a legend: floats to 4 significant digits (searches produce 0.00036875529945204906)."""
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list):
        return "x".join(map(str, value))
    return str(value)


def _with_defaults(config: dict[str, Any]) -> dict[str, Any]:
    """A softac run's config with the keys added since it was written at their defaults (what it ran with),
    so that a run made before a key existed groups with new runs of the same settings."""
    if config.get("framework", "softac") != "softac":
        return config
    from softac.config.sac_config import SACConfig

    return {**SACConfig().to_dict(), **config}


def group_runs(runs: list[Path], names: dict[Path, str] | None = None) -> tuple[list[str], list[list[Path]]]:
    """Runs grouped by configuration (all but the seed), with a label for each group; with `names` (run ->
    the configuration's name, e.g. "softac crossq preset"), grouped and labelled by those names."""
    if names is not None:
        named: dict[str, list[Path]] = {}
        for run in runs:
            named.setdefault(names[run], []).append(run)
        return list(named), list(named.values())
    configs = [_with_defaults(load_run_config(r)) for r in runs]
    groups: dict[str, list[int]] = {}
    for i, c in enumerate(configs):
        groups.setdefault(_config_key(c), []).append(i)
    labels = _describe_differences([configs[idx[0]] for idx in groups.values()])
    return labels, [[runs[i] for i in members] for members in groups.values()]


def aligned_eval_curves(runs: list[Path], column: str = "mean_return") -> tuple[np.ndarray, np.ndarray]:
    """An eval.csv column (mean returns, or success rates) of several runs on a common step grid (linear
    interpolation, no extrapolation)."""
    curves = []
    for run in runs:
        rows = [r for r in read_csv(run / "eval.csv") if r.get(column)]
        if rows:
            curves.append((_floats(rows, "step"), _floats(rows, column)))
    if not curves:
        return np.array([]), np.zeros((0, 0))
    grid = np.unique(np.concatenate([s for s, _ in curves]))
    values = np.full((len(curves), len(grid)), np.nan)
    for i, (s, v) in enumerate(curves):
        inside = (grid >= s.min()) & (grid <= s.max())
        values[i, inside] = np.interp(grid[inside], s, v)
    return grid, values


def plot_comparison(runs: list[Path], out: Path, baselines: dict[str, Any] | None = None,
                    names: dict[Path, str] | None = None, column: str = "mean_return") -> Path:
    """One colour per configuration: each seed's curve faintly, the IQM across seeds, and its 95%
    percentile-bootstrap band (which stays within the seeds' values, where a t-interval of 2-3 seeds
    spans the axis). `names`: see group_runs. `column`: eval.csv's mean_return, or success_rate."""
    plt = _pyplot()
    labels, groups = group_runs(runs, names)
    fig, ax = plt.subplots(figsize=(9, 5), constrained_layout=True)
    observed: list[float] = []
    success = column == "success_rate"
    if success:
        baselines = None
    for colour, (label, members) in enumerate(zip(labels, groups)):
        grid, values = aligned_eval_curves(members, column)
        if len(grid) == 0:
            continue
        observed.extend(values[~np.isnan(values)].tolist())
        for seed_curve in values:
            ax.plot(grid, seed_curve, color=f"C{colour}", lw=0.8, alpha=0.3)
        iqm, low, high = iqm_band(values)
        seeds = f"{len(members)} seed{'s' if len(members) > 1 else ''}"
        ax.plot(grid, iqm, color=f"C{colour}", lw=2, label=f"{label} ({seeds})")
        if len(members) > 1:
            ax.fill_between(grid, low, high, color=f"C{colour}", alpha=0.18, lw=0)
    _draw_baselines(ax, baselines)
    observed.extend(b["mean_return"] for b in (baselines or {}).values())
    if success:
        ax.set_ylim(-0.03, 1.03)
        return _finish_curve(plt, fig, ax, out, "deterministic eval success rate",
                             "Evaluation success rate: IQM across seeds, 95% bootstrap band, each seed faint")
    if observed:
        lo, hi = min(observed), max(observed)
        pad = 0.08 * (hi - lo or abs(hi) or 1.0)
        ax.set_ylim(lo - pad, hi + pad)
    return _finish_curve(plt, fig, ax, out, "deterministic eval return",
                         "Evaluation return: IQM across seeds, 95% bootstrap band, each seed faint")


def _finish_curve(plt, fig, ax, out: Path, ylabel: str, title: str) -> Path:
    """Labels, grid and legend of a return-over-steps figure, then save it to `out`."""
    ax.set_xlabel("environment steps")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    handles, labels = ax.get_legend_handles_labels()
    if max(map(len, labels), default=0) > LEGEND_INSIDE_CHARS:  # many varying keys: wrapped, below the axes
        ax.legend(handles, [textwrap.fill(label, 110) for label in labels], loc="upper center",
                  bbox_to_anchor=(0.5, -0.13), fontsize=8)
    elif handles:  # runs that failed before their first evaluation draw nothing
        ax.legend(loc="best", fontsize=9)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def plot_final_returns(runs: list[Path], out: Path, names: dict[Path, str] | None = None) -> Path:
    """Each configuration's final eval return: one dot per seed, the IQM with its 95% bootstrap interval."""
    plt = _pyplot()
    labels, groups = group_runs(runs, names)
    finals = []
    for members in groups:
        values = []
        for run in members:
            rows = read_csv(run / "eval.csv")
            if rows:
                values.append(_floats(rows[-1:], "mean_return")[0])
        finals.append(np.asarray(values, float))
    order = sorted(range(len(groups)), key=lambda i: interquartile_mean(finals[i]) if len(finals[i]) else -np.inf)
    fig, ax = plt.subplots(figsize=(9, max(2.5, 0.45 * len(groups) + 1.5)), constrained_layout=True)
    for row, i in enumerate(order):
        values = finals[i]
        if len(values) == 0:
            continue
        ax.scatter(values, np.full(len(values), row), color=f"C{i % 10}", alpha=0.6, s=25, zorder=3)
        iqm, low, high = stratified_bootstrap_iqm([values], reps=2_000)
        ax.errorbar(iqm, [row], xerr=[[iqm - low], [high - iqm]], fmt="D", color="black", ms=6, capsize=4,
                    zorder=4)
    ax.set_yticks(range(len(order)), [f"{labels[i]} ({len(groups[i])})" for i in order], fontsize=8)
    ax.set_xlabel("final deterministic eval return (dots: seeds; diamond and bar: IQM and 95% bootstrap interval)")
    ax.set_title("Final evaluation return per configuration")
    ax.grid(alpha=0.3, axis="x")
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def plot_aggregate(scores: dict[str, tuple[float, float, float]], out: Path, title: str, xlabel: str) -> Path:
    """One bar per configuration: a point estimate with its interval, e.g. the IQM of normalised scores
    across envs with its stratified-bootstrap 95% interval ({name: (value, low, high)})."""
    plt = _pyplot()
    names = list(scores)
    fig, ax = plt.subplots(figsize=(11, max(2.2, 0.55 * len(names) + 1.5)), constrained_layout=True)
    for row, name in enumerate(names):
        value, low, high = scores[name]
        ax.barh(row, value, color=f"C{row % 10}", alpha=0.75)
        ax.errorbar(value, row, xerr=[[value - low], [high - value]], fmt="none", ecolor="black", capsize=5)
        ax.text(high, row, f"  {value:.2f} [{low:.2f}, {high:.2f}]", va="center", fontsize=8)
    ax.set_yticks(range(len(names)), names, fontsize=9)
    ax.invert_yaxis()
    ax.set_xlabel(xlabel)
    ax.set_title(title)
    ax.grid(alpha=0.3, axis="x")
    ax.set_xlim(min(0.0, *(low for _, low, _ in scores.values())), max(high for _, _, high in scores.values()) * 1.45)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


# Kelly's colours of maximum contrast (1965) without white and black, the pale ones last: each configuration on the
# front one colour of its own, none a shade of another's (matplotlib's cycle has ten, and tab20 pairs shades of a hue)
FRONT_COLOURS = ("#BE0032", "#0067A5", "#008856", "#875692", "#F38400", "#882D17", "#E68FAC", "#848482", "#604E97",
                 "#F6A600", "#B3446C", "#8DB600", "#654522", "#E25822", "#2B3D26", "#F3C300", "#A1CAF1", "#C2B280",
                 "#F99379", "#DCD300")
# matplotlib's 15 filled markers, then five filled stars and polygons (sides, style 0 polygon or 1 star, angle)
FRONT_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*", "h", "<", ">", "p", "d", "H", "8", (6, 1, 0), (4, 1, 45),
                 (8, 1, 0), (7, 0, 0), (3, 1, 0))
# a machine's points differ by fill (a run's one-core seconds compare only on one machine); hollow is kept for
# points whose wall time comes from disturbed trials
FRONT_FILLS = ("full", "top", "right", "bottom", "left")


@dataclasses.dataclass(frozen=True)
class FrontPoint:
    """One configuration on one env: the mean final return over its seeds and their standard deviation, its median
    wall seconds per run (None: not drawn), whether those seconds come from undisturbed trials, the machine they
    ran on (a short name) and whether that was a GPU (its seconds are a GPU's, not one CPU core's)."""
    mean: float
    sd: float
    seconds: float | None
    timed: bool = True
    machine: str = ""
    gpu: bool = False


def front_styles(names: list[str]) -> dict[str, tuple[str, str]]:
    """A colour and a marker of its own for each configuration (in the order given), so that no two share either;
    past len(FRONT_COLOURS) configurations a front is unreadable, so that is refused."""
    if len(names) > len(FRONT_COLOURS):
        raise SoftacError(f"the front draws at most {len(FRONT_COLOURS)} configurations with a colour and marker "
                          f"each; {len(names)} given")
    return {name: (FRONT_COLOURS[i], FRONT_MARKERS[i]) for i, name in enumerate(names)}


def plot_front(points: dict[str, dict[str, FrontPoint]], published: dict[str, dict[str, float]],
               out: Path, title: str) -> Path:
    """Return against wall time, one panel per env ({env: {configuration: FrontPoint}}): each configuration a
    point at (median wall seconds, mean final return) with its spread over seeds as a vertical bar, in a colour and
    a marker of its own (the legend's key; `configuration` is best a short label, with the long description
    beside the figure); the machine by the marker's fill, a GPU's point with a black rim, a point whose seconds come
    from disturbed trials hollow; a point without seconds is left out. Every panel shares one log time axis and
    draws each published method's mean ({env: {method: mean}}) as a grey dashed line labelled at the right, the
    best one there solid and black."""
    plt = _pyplot()
    from matplotlib import ticker

    envs = list(points)
    cols = min(3, len(envs))
    rows = (len(envs) + cols - 1) // cols
    names = list(dict.fromkeys(name for env in envs for name in sorted(points[env])))
    styles = front_styles(names)
    machines = sorted({p.machine for env in envs for p in points[env].values()})
    fills = {m: FRONT_FILLS[i % len(FRONT_FILLS)] for i, m in enumerate(machines)}
    methods = sorted({m for lines in published.values() for m in lines})
    dashes = {m: (0, (5, 1.5 + 1.2 * i)) for i, m in enumerate(methods)}
    seconds = [p.seconds for env in envs for p in points[env].values() if p.seconds]
    low_s, high_s = (min(seconds) / 1.4, max(seconds) * 1.4) if seconds else (10.0, 10_000.0)
    legend_rows = -(-(len(names) + len(machines) + 2) // 3)
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 4.0 * rows + 0.25 * legend_rows), squeeze=False,
                             layout="constrained")
    any_hollow = False
    for ax, env in zip(axes.flat, envs):
        for name, p in sorted(points[env].items()):
            if p.seconds is None:
                continue
            colour, marker = styles[name]
            any_hollow |= not p.timed
            ax.errorbar(p.seconds, p.mean, yerr=p.sd, fmt=marker, color=colour, capsize=3, markersize=8,
                        fillstyle="full" if not p.timed else fills[p.machine],
                        markerfacecolor="white" if not p.timed else colour,
                        markerfacecoloralt="white", markeredgecolor="black" if p.gpu else colour,
                        markeredgewidth=2.0 if p.gpu else 1.0, elinewidth=1.2, alpha=0.95)
        lines = sorted(published.get(env, {}).items(), key=lambda kv: kv[1])
        best = lines[-1][0] if lines else None
        for method, value in lines:
            ax.axhline(value, color="black" if method == best else "grey", linewidth=1.3 if method == best else 0.9,
                       linestyle="-" if method == best else dashes[method], zorder=0)
        low, high = ax.get_ylim()
        label_at = -np.inf
        for method, value in lines:  # labels at the right, nudged apart where two means nearly coincide
            label_at = max(value, label_at + 0.05 * (high - low))
            ax.annotate(f"{method} (best)" if method == best else method, (1.0, label_at),
                        xycoords=("axes fraction", "data"), xytext=(3, 0), textcoords="offset points", fontsize=7,
                        color="black" if method == best else "dimgrey", va="center")
        ax.set_xscale("log")
        ax.set_xlim(low_s, high_s)
        ax.xaxis.set_major_locator(ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(ticker.FuncFormatter(lambda v, _: f"{v:,.0f}"))
        ax.xaxis.set_minor_formatter(ticker.NullFormatter())
        ax.set_title(env)
        ax.set_xlabel("wall seconds per 100k-step run (log)")
        ax.set_ylabel("final eval return")
        ax.grid(alpha=0.3, which="major")
    for ax in list(axes.flat)[len(envs):]:
        ax.axis("off")
    handles = {name: plt.Line2D([], [], marker=styles[name][1], linestyle="", color=styles[name][0], markersize=8)
               for name in names}
    for machine in machines:
        gpu = any(p.gpu for env in envs for p in points[env].values() if p.machine == machine)
        handles[f"fill: {machine}" + (" (a GPU's seconds)" if gpu else " (one core's seconds)")] = plt.Line2D(
            [], [], marker="o", linestyle="", color="dimgrey", fillstyle=fills[machine], markerfacecoloralt="white",
            markeredgecolor="black" if gpu else "dimgrey", markeredgewidth=2.0 if gpu else 1.0, markersize=8)
    if any_hollow:
        handles["hollow: wall time from disturbed trials"] = plt.Line2D(
            [], [], marker="o", linestyle="", color="dimgrey", markerfacecolor="white", markersize=8)
    fig.legend(list(handles.values()), list(handles), loc="outside lower center", ncol=3, fontsize=8)
    fig.suptitle(title)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def plot_runs(runs: list[Path], out_dir: Path | None = None, names: dict[Path, str] | None = None) -> list[Path]:
    """All figures for one or more runs; returns the files written. `names`: see group_runs."""
    for run in runs:
        if not run.is_dir():
            raise SoftacError(f"no such run directory: {run}")
        load_run_config(run)
    written = []
    if len(runs) == 1:
        run = runs[0]
        out = out_dir or run / "plots"
        out.mkdir(parents=True, exist_ok=True)
        baselines = load_baselines(run)
        written.append(plot_learning_curve(run, out / "learning_curve.png", baselines))
        written.append(plot_metric_grid(run, out / "metrics.png"))
        if reports_success(run):
            written.append(plot_success_curve(run, out / "success.png"))
    else:
        if out_dir is None:
            raise SoftacError("plotting several runs needs --out DIR")
        out_dir.mkdir(parents=True, exist_ok=True)
        known = [b for b in (load_baselines(r) for r in runs) if b]
        written.append(plot_comparison(runs, out_dir / "comparison.png", known[0] if known else None, names))
        if any(map(reports_success, runs)):
            written.append(plot_comparison(runs, out_dir / "success_comparison.png", names=names,
                                           column="success_rate"))
        for run in runs:
            sub = out_dir / run.name
            sub.mkdir(exist_ok=True)
            written.append(plot_learning_curve(run, sub / "learning_curve.png", load_baselines(run)))
    return written

