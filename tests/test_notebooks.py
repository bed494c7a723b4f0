"""The notebooks in examples/ (issue 45) run as a user runs them, in a Jupyter kernel, with tiny step counts set
in their `parameters` cell; their outputs are what a user sees: a live progress bar widget, inline figures, the
evaluation table and the video."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
NOTEBOOKS = sorted(EXAMPLES.glob("*.ipynb"))
TINY = {"learning_starts": 100, "eval_interval": 200, "eval_episodes": 1, "hidden_sizes": [32, 32],
        "batch_size": 32, "buffer_size": 2000}


def execute(path: Path, cwd: Path, steps: int = 400) -> nbformat.NotebookNode:
    book = nbformat.read(path, as_version=4)
    params = [cell for cell in book.cells if "parameters" in cell.metadata.get("tags", [])]
    assert len(params) == 1, f"{path.name}: one cell tagged parameters"
    params[0].source = f"STEPS = {steps}\nEXTRA = {json.dumps(TINY)}"
    nbclient.NotebookClient(book, timeout=600, kernel_name="python3",
                            resources={"metadata": {"path": str(cwd)}}).execute()
    return book


def output_types(book: nbformat.NotebookNode) -> set[str]:
    kinds = set()
    for cell in book.cells:
        for out in cell.get("outputs", []):
            kinds.add(out["output_type"])
            kinds.update(out.get("data", {}))
    return kinds


def test_there_is_a_notebook_per_seed_document_and_one_on_a_custom_env():
    assert [p.name for p in NOTEBOOKS] == ["01_inverted_pendulum.ipynb", "02_agent_class.ipynb",
                                           "03_vector_envs.ipynb", "04_pusher.ipynb", "05_custom_env.ipynb",
                                           "06_offline_data.ipynb"]
    for path in NOTEBOOKS:  # committed without outputs: what a user opens is the code, not a stale run
        book = nbformat.read(path, as_version=4)
        assert all(not cell.get("outputs") for cell in book.cells if cell.cell_type == "code"), path.name


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_the_notebook_runs(path, tmp_path):
    from softac.base.opengl import working_gl_backend

    book = execute(path, tmp_path)
    kinds = output_types(book)
    assert "error" not in kinds
    if path.stem in ("01_inverted_pendulum", "04_pusher", "05_custom_env", "06_offline_data"):  # show(): figures
        assert {"image/png", "text/html"} <= kinds, kinds
        assert (tmp_path / "runs").is_dir()
    if path.stem == "06_offline_data":  # two Minari datasets written, one read back by id, two agents compared
        text = "".join(out.get("text", "") for cell in book.cells for out in cell.get("outputs", []))
        assert "10 episodes, 2000 steps" in text and "with the data: mean return" in text, text
        assert (tmp_path / "datasets" / "softac" / "pendulum-replay-v0" / "data" / "metadata.json").is_file()
    if path.stem == "01_inverted_pendulum":
        # learn()'s live bar is tqdm's notebook widget, and show(video=True) embeds the video
        assert "application/vnd.jupyter.widget-view+json" in kinds, kinds
        html = "".join(out["data"].get("text/html", "") for cell in book.cells for out in cell.get("outputs", [])
                       if "data" in out)
        assert "<table>" in html
        if working_gl_backend() is not None:
            assert "<video" in html
        assert "SAC(env='InvertedPendulum-v4', steps=400" in str(book.cells[3].outputs)  # the agent's repr


def test_show_outside_jupyter_writes_the_figures_and_says_where(tiny, tmp_path, capsys):
    """softac.show and agent.show in a script: the same figures, their paths printed; an agent with no run, or a
    run path asked for a video it lacks, is a one-line SoftacError."""
    import softac
    from softac import SAC, SoftacError
    from softac.run.csv_logs import read_csv
    from softac.outputs.report import evaluation_table

    agent = SAC(tiny(eval_interval=100, eval_episodes=1))
    with pytest.raises(SoftacError, match="no run directory to show: train it with learn"):
        agent.show()
    agent.learn(200, run_dir=tmp_path / "run", progress=False)
    assert repr(agent) == (f"SAC(env='softac_test_envs:Drift-v0', steps=200, episodes={agent.num_episodes}, "
                           f"last_eval={round(agent.run_state.last_eval, 2)}, run_dir='{tmp_path / 'run'}')")
    shown = agent.show()
    assert {p.name for p in shown} == {"learning_curve.png", "metrics.png"}
    assert capsys.readouterr().out.split() == [str(p) for p in shown]
    assert softac.show(tmp_path / "run", video=False) == shown
    table = evaluation_table(read_csv(tmp_path / "run" / "eval.csv"))
    assert table.count("<tr>") == 3 and "<th>mean return</th>" in table  # a header and the evaluations at 100, 200
    with pytest.raises(SoftacError, match="has no video yet: pass the agent"):
        softac.show(tmp_path / "run", video=True)
    with pytest.raises(SoftacError, match="is not a run directory"):
        softac.show(tmp_path)
