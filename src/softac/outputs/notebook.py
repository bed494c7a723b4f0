"""What a run looks like inside Jupyter (issue 45): `softac.show(run)` or `agent.show()` puts a run's learning
curve, metric grid, evaluation table and video in the notebook, as `softac plot`, `softac eval` and
`softac video` write them to files; outside a notebook it writes the same files and prints where they are."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from softac.errors import SoftacError
from softac.run.csv_logs import in_notebook, read_csv
from softac.outputs.report import evaluation_table, latest_video


def run_of(run_or_agent: Any) -> Path:
    """A run directory: the path given, or the run an agent last trained into (or was loaded from)."""
    if isinstance(run_or_agent, (str, Path)):
        run = Path(run_or_agent)
        if not (run / "config.yaml").exists():
            raise SoftacError(f"{run} is not a run directory (no config.yaml)")
        return run
    run = getattr(getattr(run_or_agent, "run_state", None), "run_dir", None)
    if run is None:
        raise SoftacError("this agent has no run directory to show: train it with learn(steps, run_dir=...) "
                          "(or load it from a run)")
    return Path(run)


def show(run_or_agent: Any, plots: bool = True, evaluations: bool = True, video: bool | None = None) -> list[Path]:
    """Show a run in the notebook: its learning curve and metric grid (`softac plot`), its evaluations as a
    table, and a video: the newest in RUN/videos (video=None), one recorded now if there is none (True; an
    agent, not a path, records it), or none (False). Takes a run directory or an agent (the run it trained into). Outside Jupyter, prints the
    files. Returns the files shown."""
    run = run_of(run_or_agent)
    shown: list[Path] = []
    if plots:
        from softac.outputs.plots import plot_runs

        shown += [path for path in plot_runs([run]) if path.suffix == ".png"]
    clip = latest_video(run) if video is not False else None
    if clip is None and video:
        from softac.outputs.video import record

        agent = run_or_agent
        if isinstance(agent, (str, Path)):
            raise SoftacError(f"{run} has no video yet: pass the agent (softac.SAC.load(run)) to record one, or "
                              "run `softac video RUN`")
        clip = run / "videos" / f"step{agent.num_steps}.mp4"
        record(agent, clip, max_steps=1000)
    if clip is not None:
        shown.append(clip)
    if not in_notebook():
        for path in shown:
            print(path)
        return shown
    from IPython.display import HTML, Image, Video, display

    for path in shown:
        if path.suffix == ".png":
            display(Image(filename=str(path)))
    if evaluations and (run / "eval.csv").exists():
        display(HTML(evaluation_table(read_csv(run / "eval.csv"))))
    if clip is not None:
        display(Video(str(clip), embed=True, html_attributes="controls loop", width=480))
    return shown
