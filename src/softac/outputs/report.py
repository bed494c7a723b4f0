"""`softac report RUN`: one self-contained HTML page (figures and video inlined, no network requests)."""

from __future__ import annotations

import base64
import html
import json
import time
from pathlib import Path
from typing import Any

from softac.run.csv_logs import read_csv
from softac.outputs.plots import load_baselines, load_run_config, plot_runs

# Marks the page once every image and video has loaded; a headless browser test reads these attributes.
LOAD_CHECK = """
window.softacErrors = [];
window.addEventListener('error', e => { window.softacErrors.push(String(e.message || e.type)); });
window.addEventListener('load', () => {
  const imgs = Array.from(document.images);
  document.body.dataset.imagesTotal = imgs.length;
  document.body.dataset.imagesLoaded = imgs.filter(i => i.complete && i.naturalWidth > 0).length;
  document.body.dataset.errors = window.softacErrors.length;
});
"""

STYLE = """
body { font-family: system-ui, -apple-system, 'Segoe UI', sans-serif; margin: 0 auto; max-width: 1100px;
       padding: 1.5rem; color: #1d2430; line-height: 1.45; }
h1 { margin-bottom: .2rem; } h2 { margin-top: 2rem; border-bottom: 1px solid #dde; padding-bottom: .2rem; }
.sub { color: #5a6475; margin-top: 0; }
.cards { display: flex; gap: 1rem; flex-wrap: wrap; }
.card { background: #f4f6fa; border-radius: 8px; padding: .7rem 1rem; min-width: 150px; }
.card b { display: block; font-size: 1.35rem; }
img, video { max-width: 100%; border: 1px solid #e3e6ee; border-radius: 6px; }
table { border-collapse: collapse; font-size: .92rem; }
th, td { text-align: left; padding: .25rem .7rem; border-bottom: 1px solid #eceef3; }
th { background: #f4f6fa; }
.cols { columns: 2; column-gap: 2rem; } .cols table { width: 100%; }
code { background: #f4f6fa; padding: 0 .25rem; border-radius: 3px; }
"""


def _data_uri(path: Path, mime: str) -> str:
    return f"data:{mime};base64," + base64.b64encode(path.read_bytes()).decode()


def _table(headers: list[str], rows: list[list[Any]]) -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in headers)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _fmt(value: Any) -> str:
    try:
        f = float(value)
    except (TypeError, ValueError):
        return str(value)
    return f"{f:.1f}" if abs(f) >= 10 else f"{f:.3g}"


def evaluation_table(evals: list[dict[str, str]]) -> str:
    """eval.csv's rows as an HTML table: step, mean return, std, episodes, and the success rate where the env
    reports one (the report's, and softac.show's in a notebook)."""
    if not evals:
        return "<p>No evaluation yet (eval_interval=0 or the run is young).</p>"
    success = any(r.get("success_rate") for r in evals)
    return _table(["step", "mean return", "std", "episodes"] + (["success rate"] if success else []),
                  [[r["step"], _fmt(r["mean_return"]), _fmt(r["std_return"]), r["episodes"]]
                   + ([_fmt(r.get("success_rate") or "")] if success else []) for r in evals])


def latest_video(run: Path) -> Path | None:
    """The run's newest video in RUN/videos, or None."""
    videos = sorted((run / "videos").glob("*.mp4"), key=lambda p: p.stat().st_mtime)
    return videos[-1] if videos else None


def _segments(config: dict[str, Any]) -> list[dict[str, Any]]:
    """config.yaml's training segments; a run written before they were kept has its one record at the top."""
    return config.get("segments") or [{"start_step": 0, **{k: config[k] for k in ("machine", "cpus", "versions",
                                                                                  "resolved_matmul_dtype")
                                                           if k in config}}]


def build_report(run: Path, out: Path | None = None, video: Path | None = None) -> Path:
    config = load_run_config(run)
    figures = plot_runs([run])
    evals = read_csv(run / "eval.csv")
    episodes = read_csv(run / "episodes.csv")
    progress = read_csv(run / "progress.csv")
    baselines = load_baselines(run) or {}
    if video is None:
        video = latest_video(run)

    best = max((float(r["mean_return"]) for r in evals), default=None)
    last = float(evals[-1]["mean_return"]) if evals else None
    steps = progress[-1]["step"] if progress else "0"
    time_s = float(progress[-1]["time_s"]) if progress else 0.0
    cards = [("environment", config.get("env_id", "?")), ("steps", f"{int(float(steps)):,}"),
             ("training time", f"{time_s:.0f} s"), ("episodes", f"{len(episodes):,}"),
             ("best eval return", _fmt(best) if best is not None else "n/a"),
             ("last eval return", _fmt(last) if last is not None else "n/a")]
    successes = [float(r["success_rate"]) for r in evals if r.get("success_rate")]
    if successes:  # a goal env
        cards += [("best success rate", f"{max(successes):.2f}"), ("last success rate", f"{successes[-1]:.2f}")]
    parts = [f"<h1>softac run report</h1><p class='sub'>{html.escape(str(run))} &middot; generated "
             f"{time.strftime('%Y-%m-%d %H:%M')}</p>",
             "<div class='cards'>" + "".join(f"<div class='card'>{html.escape(k)}<b>{html.escape(v)}</b></div>"
                                             for k, v in cards) + "</div>"]
    captions = {"learning_curve.png": "Learning curve", "metrics.png": "Training metrics",
                "success.png": "Success rate"}
    for fig in figures:
        parts.append(f"<h2>{captions.get(fig.name, fig.stem)}</h2>"
                     f"<img alt='{html.escape(captions.get(fig.name, fig.stem))}' src='{_data_uri(fig, 'image/png')}'>")
    parts.append("<h2>Evaluations</h2>" + evaluation_table(evals))
    parts.append("<h2>Baselines</h2>")
    if baselines:
        rows = [[name, _fmt(s["mean_return"]), _fmt(s["std_return"]), s["episodes"]] for name, s in baselines.items()]
        parts.append(_table(["policy", "mean return", "std", "episodes"], rows))
    else:
        parts.append("<p>No baselines recorded: <code>softac baselines --env ENV --out RUN</code> adds them.</p>")
    if video is not None and video.exists():
        parts.append(f"<h2>Video</h2><p>{html.escape(video.name)}</p>"
                     f"<video controls muted loop playsinline preload='metadata' "
                     f"src='{_data_uri(video, 'video/mp4')}'></video>")
    shown = {k: v for k, v in config.items() if k not in ("versions", "machine", "segments")}
    cfg_rows = [[k, json.dumps(v) if isinstance(v, (list, dict)) else v] for k, v in shown.items()]
    parts.append("<h2>Configuration</h2><div class='cols'>" + _table(["key", "value"], cfg_rows) + "</div>")
    parts.append("<h2>Versions and machine</h2><p>Each stretch of training (a resumed run may have gone on "
                 "elsewhere), as config.yaml records it.</p>" + _table(
                     ["from step", "started", "host", "machine", "CPUs", "matmuls", "versions"],
                     [[s.get("start_step", ""), s.get("started", ""), s.get("host", ""),
                       s.get("machine") or "not recorded",
                       f"{s.get('cpus', '')}{' (shared with another pinned run)' if s.get('cpus_shared') else ''}",
                       s.get("resolved_matmul_dtype", ""),
                       ", ".join(f"{k} {v}" for k, v in (s.get("versions") or {}).items())]
                      for s in _segments(config)]))
    page = ("<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
            "<meta name='viewport' content='width=device-width, initial-scale=1'>"
            f"<title>softac report: {html.escape(str(config.get('env_id', '')))}</title>"
            f"<style>{STYLE}</style><script>{LOAD_CHECK}</script></head><body>"
            + "\n".join(parts) + "</body></html>")
    out = out or run / "report.html"
    from softac.run.run_dir import write_atomic

    write_atomic(out, page.encode())
    return out
