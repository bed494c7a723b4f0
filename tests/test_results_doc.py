"""benchmarks/results_doc.py: docs/results.md from the kept sweeps of benchmarks/results.sh."""

import importlib.util
import json
import shutil

import pytest

from conftest import TESTS

ROOT = TESTS.parent
KEPT = ROOT / "benchmarks" / "sweeps"


def load_results_doc():
    spec = importlib.util.spec_from_file_location("results_doc", ROOT / "benchmarks" / "results_doc.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.skipif(not (KEPT / "Hopper-v5-softac" / "sweep.json").exists(), reason="kept Hopper sweeps not present")
def test_results_doc_tables_presets_options_other_presets_and_peers_and_keeps_other_sections(tmp_path):
    sweeps, docs = tmp_path / "sweeps", tmp_path / "docs"
    for name in ("Hopper-v5-softac", "Hopper-v5-sbx"):
        shutil.copytree(KEPT / name, sweeps / name)
    # an option variant: the same trials under a sweep whose spec names the options
    variant = sweeps / "Hopper-v5-softac-norm"
    shutil.copytree(KEPT / "Hopper-v5-softac", variant)
    spec = json.loads((variant / "sweep.json").read_text())
    spec["preset"], spec["overrides"] = None, ["obs_norm=true", "critic_layer_norm=true"]
    (variant / "sweep.json").write_text(json.dumps(spec))
    # a preset variant (results.sh fallback: another preset on the env), named by its preset
    other = sweeps / "Hopper-v5-softac-default"
    shutil.copytree(KEPT / "Hopper-v5-softac", other)
    spec = json.loads((other / "sweep.json").read_text())
    spec["preset"] = "default"
    (other / "sweep.json").write_text(json.dumps(spec))
    # the machine each trial recorded names its section (two machines: both named)
    import yaml
    for trial in (sweeps / "Hopper-v5-sbx").glob("seed=*"):
        config = yaml.safe_load((trial / "config.yaml").read_text())
        (trial / "config.yaml").write_text(yaml.safe_dump({**config, "machine": "Example CPU (AVX2), 2 cores"}))
    docs.mkdir()
    (docs / "results.md").write_text("# old\n\n## Pusher-v5\n\nkept Pusher table\n\n## Hopper-v5\n\nold Hopper table\n")

    assert load_results_doc().main([str(sweeps), "--docs", str(docs)]) == 0

    text = (docs / "results.md").read_text()
    assert "kept Pusher table" in text and "old Hopper table" not in text
    assert "## Walker2d-v5\n\nNot run yet." in text
    hopper = text.split("## Hopper-v5")[1].split("\n## ")[0]
    assert "Example CPU (AVX2), 2 cores and " in hopper or " and Example CPU (AVX2), 2 cores" in hopper
    rows = {line.split("|")[1].strip(): line for line in hopper.splitlines() if line.startswith("| ")}
    assert {"softac", "softac obs_norm=true critic_layer_norm=true", "softac preset=default", "sbx"} <= set(rows)
    assert rows["softac"].split("|")[2].strip() == "3" and rows["sbx"].split("|")[2].strip() == "2"
    assert (docs / "results" / "Hopper-v5.png").stat().st_size > 10_000
