"""benchmarks/results_doc.py: docs/results.md from the kept sweeps of benchmarks/results.sh."""

import json
import shutil

import pytest

from conftest import TESTS, load_benchmark_script

ROOT = TESTS.parent
KEPT = ROOT / "benchmarks" / "sweeps"


def copy_seed_0(source: str, target) -> None:
    """A kept sweep into `target` with its seed=0 trial only: one run, so the arithmetic a test checks stays
    checkable by hand."""
    shutil.copytree(KEPT / source, target)
    for trial in target.glob("seed=*"):
        if trial.name != "seed=0":
            shutil.rmtree(trial)


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

    assert load_benchmark_script("results_doc").main([str(sweeps), "--docs", str(docs)]) == 0

    text = (docs / "results.md").read_text()
    assert "kept Pusher table" in text and "old Hopper table" not in text
    assert "## Walker2d-v5\n\nNot run yet." in text
    hopper = text.split("## Hopper-v5")[1].split("\n## ")[0]
    assert "Example CPU (AVX2), 2 cores and " in hopper or " and Example CPU (AVX2), 2 cores" in hopper
    rows = {line.split("|")[1].strip(): line for line in hopper.splitlines() if line.startswith("| ")}
    # configurations named by framework and preset, not by the keys that differ
    assert {"softac, crossq preset", "softac, env preset + obs_norm=true critic_layer_norm=true",
            "softac, default preset", "SBX SAC, its defaults"} <= set(rows)
    kept_seeds = len([d for d in (KEPT / "Hopper-v5-softac").glob("seed=*") if (d / "summary.json").exists()])
    assert rows["softac, crossq preset"].split("|")[2].strip() == str(kept_seeds)
    assert rows["SBX SAC, its defaults"].split("|")[2].strip() == "2"
    assert (docs / "results" / "Hopper-v5.png").stat().st_size > 10_000


@pytest.mark.skipif(not all((KEPT / f"{env}-softac" / "sweep.json").exists() for env in
                            ("HalfCheetah-v5", "Hopper-v5", "Walker2d-v5", "Ant-v5", "Humanoid-v5")),
                    reason="kept suite sweeps not present")
def test_the_suite_aggregate_is_an_iqm_of_normalised_scores_with_a_bootstrap_interval(tmp_path):
    """One row and one bar per configuration; a configuration on fewer envs is shown beside softac's preset on
    the same envs; normalised between the random policy (0) and the best final eval shown (1)."""
    from softac.outputs.seed_stats import stratified_bootstrap_iqm
    from softac.sweep import load_spec, trial_rows

    results_doc = load_benchmark_script("results_doc")
    sweeps = tmp_path / "sweeps"
    envs = results_doc.SUITE
    for env in envs:
        shutil.copytree(KEPT / f"{env}-softac", sweeps / f"{env}-softac")
    shutil.copytree(KEPT / "Hopper-v5-sbx", sweeps / "Hopper-v5-sbx")  # a peer on one env only
    random = {env: -10.0 * (i + 1) for i, env in enumerate(envs)}  # stand-ins: the real ones take a minute
    lines = results_doc.suite_aggregate(sweeps, tmp_path, {}, random=random)
    table = {line.split("|")[1].strip(): line.split("|") for line in lines if line.startswith("| ")}
    finals = {env: [r["final_eval_mean"] for r in trial_rows(sweeps / f"{env}-softac",
                                                             load_spec(sweeps / f"{env}-softac"))] for env in envs}
    hopper_sbx = [r["final_eval_mean"] for r in trial_rows(sweeps / "Hopper-v5-sbx", load_spec(sweeps / "Hopper-v5-sbx"))]
    best = {env: max(finals[env] + (hopper_sbx if env == "Hopper-v5" else [])) for env in envs}
    expected = stratified_bootstrap_iqm([[(v - random[e]) / (best[e] - random[e]) for v in finals[e]] for e in envs])
    trials = sum(len(values) for values in finals.values())
    assert table["softac, crossq preset"][2:5] == [" 5 ", f" {trials} ", f" {expected[0]:.2f} [{expected[1]:.2f}, "
                                                                         f"{expected[2]:.2f}] "]
    assert table["softac, crossq preset"][5].strip() == "1.00 (1.00-1.00)"
    assert {"SBX SAC, its defaults (Hopper)", "softac, crossq preset (Hopper)"} <= set(table)
    assert table["SBX SAC, its defaults (Hopper)"][2:4] == [" 1 ", " 2 "]
    assert float(table["SBX SAC, its defaults (Hopper)"][5].split()[0]) > 1  # SBX took longer here
    assert (tmp_path / "suite-aggregate.png").stat().st_size > 10_000


def test_wall_time_ratios_compare_trials_that_ran_on_the_same_days():
    """The machine's speed drifts by up to 2x between days: a peer's trials are timed against softac's trials
    of the same days; trials from before the day was recorded form one day of their own."""
    wall_ratio = load_benchmark_script("results_doc").wall_ratio
    ours = [{"day": None, "wall_s": 200.0}, {"day": None, "wall_s": 210.0}, {"day": None, "wall_s": 190.0},
            {"day": "2026-11-25", "wall_s": 500.0}, {"day": "2026-11-25", "wall_s": 480.0}]
    today = [{"day": "2026-11-25", "wall_s": 800.0}, {"day": "2026-11-25", "wall_s": 820.0}]
    assert wall_ratio(today, ours) == (810.0 / 490.0, 810.0, 490.0, True)
    before = [{"day": None, "wall_s": 400.0}]
    assert wall_ratio(before, ours) == (2.0, 400.0, 200.0, True)
    other_day = [{"day": "2026-12-01", "wall_s": 300.0}]
    assert wall_ratio(other_day, ours) == (300.0 / 210.0, 300.0, 210.0, False)  # none beside it: all of ours, said so
    # a trial whose wall time is not comparable (e.g. the test suite ran beside it) is left out of the ratio
    disturbed = today + [{"day": "2026-11-25", "wall_s": 2200.0, "timed": False}]
    assert wall_ratio(disturbed, ours) == (810.0 / 490.0, 810.0, 490.0, True)
    assert wall_ratio([{"day": "2026-11-25", "wall_s": 2200.0, "timed": False}], ours) is None


@pytest.mark.skipif(not (KEPT / "Hopper-v5-softac" / "sweep.json").exists(), reason="kept Hopper sweeps not present")
def test_plotting_several_sweeps_names_each_by_framework_and_preset(tmp_path):
    from conftest import run_cli
    from softac.cli.commands import _trial_configuration
    from softac.sweep import SweepSpec, load_spec

    sweep = load_spec(KEPT / "Hopper-v5-softac").describe()
    assert sweep == "softac, crossq preset"
    assert load_spec(KEPT / "Hopper-v5-sbx").describe() == "SBX SAC, its defaults"
    repeated = SweepSpec(env_id="dmc:cheetah-run", steps=50000, seeds=[0], framework="sbx-crossq-softac",
                         overrides=["eval_interval=5000", "action_repeat=2"])
    assert repeated.describe() == "SBX CrossQ, crossq preset's settings + action_repeat=2"
    assert _trial_configuration(sweep, KEPT / "Hopper-v5-softac" / "seed=1") == "softac, crossq preset"
    assert _trial_configuration(sweep, tmp_path / "tau=0.1,seed=1") == "softac, crossq preset, tau=0.1"
    r = run_cli("plot", str(KEPT / "Hopper-v5-softac"), str(KEPT / "Hopper-v5-sbx"), "--out", str(tmp_path / "figs"))
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "figs" / "comparison.png").stat().st_size > 10_000


@pytest.mark.skipif(not (KEPT / "Hopper-v5-softac" / "sweep.json").exists(), reason="kept Hopper sweeps not present")
def test_the_front_scores_a_configuration_on_all_five_envs_against_the_best_published(tmp_path):
    """Issue 42's goal, per configuration run on all five v4 envs: each env's mean final over the best published
    mean there, their average, the envs at or above published CrossQ and above published FlashSAC (issue 66), and
    the five runs' time over crossq-avg's. The Hopper-v5 trials stand in for every env's; a configuration on four
    envs gets no row."""
    import numpy as np

    sweeps, docs = tmp_path / "sweeps", tmp_path / "docs"
    results_doc = load_benchmark_script("results_doc")
    for env in results_doc.SUITE_V4:
        shutil.copytree(KEPT / "Hopper-v5-softac", sweeps / f"{env}-softac")
        if env != "Humanoid-v4":
            shutil.copytree(KEPT / "Hopper-v5-softac", sweeps / f"{env}-softac-again")
        # the same trials named crossq-avg: the moonshot's time unit, so each row's time ratio is 1
        avg = sweeps / f"{env}-softac-crossq-avg"
        shutil.copytree(KEPT / "Hopper-v5-softac", avg)
        spec = json.loads((avg / "sweep.json").read_text())
        (avg / "sweep.json").write_text(json.dumps({**spec, "preset": "crossq-avg"}))
    docs.mkdir()
    assert results_doc.main([str(sweeps), "--docs", str(docs)]) == 0
    table = (docs / "results.md").read_text().split(f"### {results_doc.AGAINST_BEST}")[1].split("![front]")[0]
    mean = np.mean([float((run / "eval.csv").read_text().splitlines()[-1].split(",")[1])
                    for run in sorted((KEPT / "Hopper-v5-softac").glob("seed=*"))])
    published = results_doc.published_means()
    best = [max(m[env][0] for m in published.values() if env in m) for env in results_doc.SUITE_V4]
    fractions = [mean / b for b in best]
    at_crossq = sum(mean >= published["CrossQ"][env][0] for env in results_doc.SUITE_V4)
    above_flashsac = sum(mean > published["FlashSAC"][env][0] for env in results_doc.SUITE_V4)
    row = next(line for line in table.splitlines() if line.startswith("| softac, crossq preset |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1:6] == [f"{f:.2f}" for f in fractions]
    assert cells[6:9] == [f"{np.mean(fractions):.2f}", f"{at_crossq} of 5", f"{above_flashsac} of 5"]
    assert cells[10] == "1.00"
    assert "| softac, crossq-avg preset |" in table
    assert "again" not in table  # on four envs only: no row


def test_a_per_env_choice_scores_each_env_by_the_configuration_chosen_there():
    """Options chosen per env on tuning seeds are scored as one configuration: each env's score from the
    configuration named for it, the default's elsewhere; no row until every chosen configuration ran on its env."""
    load_benchmark_script("results_doc")  # puts benchmarks/ on the path for its sections' modules
    results_mujoco = load_benchmark_script("results_mujoco")
    envs = results_mujoco.SUITE_V4
    scores = {"base": {env: (1000.0 + i, 300.0) for i, env in enumerate(envs)},
              "special": {"Humanoid-v4": (5000.0, 900.0)}}
    choices = {"picked": ("base", {"Humanoid-v4": "special"}), "missing": ("base", {"Ant-v4": "special"})}
    combined = results_mujoco.per_env_choices(scores, choices)
    assert set(combined) == {"picked"}
    assert combined["picked"] == {**scores["base"], "Humanoid-v4": (5000.0, 900.0)}


@pytest.mark.skipif(not (KEPT / "Hopper-v5-softac" / "sweep.json").exists(), reason="kept Hopper sweeps not present")
def test_the_v4_front_puts_each_configurations_return_against_its_wall_time_beside_the_published(tmp_path):
    """The Hopper-v5 trials stand in for v4 ones: the front's row is their mean ± sd over seeds and the median
    wall time of the trials whose time is comparable; the published table marks the best method in bold."""
    import numpy as np
    import yaml

    sweeps, docs = tmp_path / "sweeps", tmp_path / "docs"
    shutil.copytree(KEPT / "Hopper-v5-softac", sweeps / "Hopper-v4-softac")
    (sweeps / "timing-excluded.yaml").write_text(yaml.safe_dump({"Hopper-v4-softac/seed=0": "shared its core"}))
    docs.mkdir()
    results_doc = load_benchmark_script("results_doc")
    assert results_doc.main([str(sweeps), "--docs", str(docs)]) == 0
    text = (docs / "results.md").read_text()
    front = text.split("## MuJoCo v4 at 100k steps")[1].split("\n## ")[0]
    # each row names its trials' machines (one-core seconds compare only on one), by CPU alone
    machine = results_doc.short_machines(results_doc.machines_of(sorted((sweeps / "Hopper-v4-softac").glob("seed=*"))))
    assert results_doc.short_machines("AMD EPYC (AVX-512 BF16), 2 cores, Python 3.11.7 and Intel(R) Xeon(R) "
                                      "Processor (AMX), 2 cores, Python 3.11.7") == "AMD EPYC (AVX-512 BF16) and Intel Xeon (AMX)"
    finals, walls = [], []
    for seed in range(5):
        run = sweeps / "Hopper-v4-softac" / f"seed={seed}"
        finals.append(float((run / "eval.csv").read_text().splitlines()[-1].split(",")[1]))
        if seed:
            walls.append(round(json.loads((run / "summary.json").read_text())["train_time_s"], 1))
    row = next(line for line in front.splitlines() if line.startswith("| softac, crossq preset |"))
    assert row == (f"| softac, crossq preset | 5 | {np.mean(finals):.0f} ± {np.std(finals, ddof=1):.0f} | "
                   f"{', '.join(f'{v:.0f}' for v in finals)} | {np.median(walls):.0f} | {machine} |")
    assert "| SimBa UTD 8 | **3116 ± 64 (5)** |" in front and "| CrossQ | 2764 ± 823 (10) |" in front
    assert (docs / "results" / "front-v4.png").stat().st_size > 10_000
    # a trial whose config.yaml says it shared its CPUs counts as disturbed, as one listed in timing-excluded.yaml
    config_path = sweeps / "Hopper-v4-softac" / "seed=1" / "config.yaml"
    config = yaml.safe_load(config_path.read_text())
    config.setdefault("segments", [{}])[0]["cpus_shared"] = True
    config_path.write_text(yaml.safe_dump(config))
    assert results_doc.main([str(sweeps), "--docs", str(docs)]) == 0
    front = (docs / "results.md").read_text().split("## MuJoCo v4 at 100k steps")[1].split("\n## ")[0]
    row = next(line for line in front.splitlines() if line.startswith("| softac, crossq preset |"))
    assert row.endswith(f"| {np.median(walls[1:]):.0f} | {machine} |")
    # every trial disturbed: the point stays, at the disturbed trials' median time, said so (hollow in the figure)
    everything = {f"Hopper-v4-softac/seed={seed}": "shared its core" for seed in range(5)}
    (sweeps / "timing-excluded.yaml").write_text(yaml.safe_dump(everything))
    assert load_benchmark_script("results_doc").main([str(sweeps), "--docs", str(docs)]) == 0
    front = (docs / "results.md").read_text().split("## MuJoCo v4 at 100k steps")[1].split("\n## ")[0]
    row = next(line for line in front.splitlines() if line.startswith("| softac, crossq preset |"))
    walls.append(round(json.loads((sweeps / "Hopper-v4-softac" / "seed=0" / "summary.json").read_text())["train_time_s"], 1))
    assert row.endswith(f"| ({np.median(walls):.0f}: disturbed) | {machine} |")
    # the same settings swept again (on another machine, say): both rows, the later named by its directory
    shutil.copytree(KEPT / "Hopper-v5-softac", sweeps / "Hopper-v4-softac-again")
    assert load_benchmark_script("results_doc").main([str(sweeps), "--docs", str(docs)]) == 0
    front = (docs / "results.md").read_text().split("## MuJoCo v4 at 100k steps")[1].split("\n## ")[0]
    assert [line.split(" |")[0] for line in front.splitlines() if line.startswith("| softac, crossq preset")] == [
        "| softac, crossq preset", "| softac, crossq preset (Hopper-v4-softac-again)"]


@pytest.mark.skipif(not (KEPT / "dmc-cheetah-run-softac-crossq-ar2" / "sweep.json").exists(),
                    reason="kept DMC sweeps not present")
def test_the_dmc_section_sets_each_tasks_runs_beside_the_published_means(tmp_path):
    sweeps, docs = tmp_path / "sweeps", tmp_path / "docs"
    copy_seed_0("dmc-cheetah-run-softac-crossq-ar2", sweeps / "dmc-cheetah-run-softac-crossq-ar2")
    docs.mkdir()
    assert load_benchmark_script("results_doc").main([str(sweeps), "--docs", str(docs)]) == 0
    section = (docs / "results.md").read_text().split("## DeepMind Control Suite at 100k frames")[1].split("\n## ")[0]
    [row] = [line for line in section.splitlines() if line.startswith("| cheetah-run |")]
    cells = [cell.strip() for cell in row.strip("|").split("|")]
    summary = json.loads((sweeps / "dmc-cheetah-run-softac-crossq-ar2" / "seed=0" / "summary.json").read_text())
    assert cells[1] == "softac, crossq preset + action_repeat=2" and cells[2] == "1"
    assert cells[4] == f"{summary['last_eval']:.0f}"
    # issue 43's columns at 100k frames: the SimBa paper's SAC 329, SimBa 559 and BRO 463 (10 seeds each), SimbaV2's
    # SimBaV2 UTD 2 642 and TD-MPC2 519
    assert cells[6:] == ["329", "559", "642", "463", "519"]
    # the aggregate: one run of ours is its own IQM; the published SAC's ten cheetah-run seeds trimmed by two at each
    # end (295.3, 296.2, 305.5, 329.3, 338.0, 366.1: mean 321.7), over the same one task
    aggregate = section.split("### One aggregate")[1]
    ours = [line for line in aggregate.splitlines() if line.startswith("| softac, crossq preset + action_repeat=2")]
    assert ours and ours[0].split("|")[4].strip().startswith(f"{summary['last_eval'] / 1000:.2f} [")
    [sac] = [line for line in aggregate.splitlines() if line.startswith("| published SAC (SimBa paper) (cheetah-run)")]
    assert sac.split("|")[3].strip() == "10" and sac.split("|")[4].strip().startswith("0.32 [")
    assert (docs / "results" / "dmc-aggregate.png").stat().st_size > 10_000
    assert "### Continued to 500k frames" not in section  # no sweep ran 500k frames


@pytest.mark.skipif(not (KEPT / "dmc-cheetah-run-softac-dmc-cheetah-run-avg" / "sweep.json").exists(),
                    reason="kept DMC sweeps not present")
def test_the_dmc_aggregate_scores_each_tasks_own_preset_as_its_trials_recorded_it(tmp_path):
    """The presets' row takes, per task, a sweep whose trials' config.yaml records what `softac train --env
    dmc:TASK` trains today: cheetah-run's own preset (dmc-cheetah-run) and the dmc preset on walker-run, both now
    averaging their actor. Not the sweeps of `--preset crossq --set action_repeat=2` (the dmc preset before), nor
    one run as `--preset dmc-cheetah-run` before that preset's file changed (its name is today's, its record is not)."""
    import yaml

    sweeps, docs = tmp_path / "sweeps", tmp_path / "docs"
    for source, final in (("dmc-cheetah-run-softac-crossq-ar2", 100.0), ("dmc-cheetah-run-softac-dmc-cheetah-run", 50.0),
                          ("dmc-cheetah-run-softac-dmc-cheetah-run-avg", 900.0),
                          ("dmc-walker-run-softac-crossq-ar2", 300.0), ("dmc-walker-run-softac-dmc-avg", 500.0)):
        copy_seed_0(source, sweeps / source)
        evals = sweeps / source / "seed=0" / "eval.csv"
        lines = evals.read_text().splitlines()
        last = lines[-1].split(",")
        evals.write_text("\n".join([*lines[:-1], ",".join([last[0], str(final), *last[2:]])]) + "\n")
    old = yaml.safe_load((sweeps / "dmc-cheetah-run-softac-dmc-cheetah-run" / "seed=0" / "config.yaml").read_text())
    assert "policy_average_tau" not in old  # it predates the key: it ran without averaging, its default
    docs.mkdir()
    assert load_benchmark_script("results_doc").main([str(sweeps), "--docs", str(docs)]) == 0
    aggregate = (docs / "results.md").read_text().split("### One aggregate")[1].split("\n## ")[0]
    [own] = [line for line in aggregate.splitlines() if line.startswith("| softac, each task's preset")]
    cells = [cell.strip() for cell in own.strip("|").split("|")]
    # two runs, 900 and 500: their IQM (the plain mean under four runs) is 0.70; the old settings' 100 and 300: 0.20
    assert cells[1:3] == ["2", "2"] and cells[3].startswith("0.70 [")
    [plain] = [line for line in aggregate.splitlines() if line.startswith("| softac, crossq preset + action_repeat=2 (2 tasks) |")]
    assert plain.split("|")[4].strip().startswith("0.20 [")


@pytest.mark.skipif(not (KEPT / "dmc-cheetah-run-softac-crossq-ar2" / "sweep.json").exists(),
                    reason="kept DMC sweeps not present")
def test_a_dmc_run_of_500k_frames_is_set_beside_the_published_500k_means_not_the_100k_ones(tmp_path):
    import yaml

    sweeps, docs = tmp_path / "sweeps", tmp_path / "docs"
    long = sweeps / "dmc-cheetah-run-softac-crossq-ar2-500k"
    copy_seed_0("dmc-cheetah-run-softac-crossq-ar2", long)
    config = yaml.safe_load((long / "seed=0" / "config.yaml").read_text())
    (long / "seed=0" / "config.yaml").write_text(yaml.safe_dump({**config, "total_steps": 250000}))
    docs.mkdir()
    assert load_benchmark_script("results_doc").main([str(sweeps), "--docs", str(docs)]) == 0
    section = (docs / "results.md").read_text().split("## DeepMind Control Suite at 100k frames")[1].split("\n## ")[0]
    table_100k, table_500k = section.split("### Continued to 500k frames")
    assert "| cheetah-run |" not in table_100k
    [row] = [line for line in table_500k.splitlines() if line.startswith("| cheetah-run |")]
    cells = [cell.strip() for cell in row.strip("|").split("|")]
    # issue 43's 500k figures: the SimBa paper's SAC 716, SimBa 815, BRO 740; SimbaV2's SimBaV2 UTD 2 890, TD-MPC2 758
    assert cells[1] == "softac, crossq preset + action_repeat=2" and cells[6:] == ["716", "815", "890", "740", "758"]


def test_the_published_dmc_runs_agree_with_the_published_means():
    """published-dmc-100k-runs.yaml (per seed, for the aggregate) and published-dmc-100k.yaml (mean, sd, seeds) are
    read from the same rows: each task's runs give its mean and sample sd to the rounding of the means file."""
    import numpy as np
    import yaml

    runs = yaml.safe_load((ROOT / "benchmarks" / "published-dmc-100k-runs.yaml").read_text())["runs"]
    means = yaml.safe_load((ROOT / "benchmarks" / "published-dmc-100k.yaml").read_text())["methods"]
    assert set(runs) == set(means)
    for method, tasks in runs.items():
        assert set(tasks) == {task for task in means[method] if task not in ("source", "file")}
        for task, values in tasks.items():
            mean, sd, seeds = means[method][task]
            assert len(values) == seeds
            # the means file rounds to 1 (0.5), this file each value to 0.1 (0.05 on a mean or an sd)
            assert abs(np.mean(values) - mean) <= 0.55
            assert seeds == 1 or abs(np.std(values, ddof=1) - sd) <= 0.55


@pytest.mark.skipif(not (KEPT / "Walker2d-v4-softac-crossq-avg" / "sweep.json").exists(),
                    reason="kept averaging sweeps not present")
def test_the_averaging_section_pairs_each_trials_actor_with_its_average(tmp_path):
    """A trial with actor-eval.json (its last checkpoint's actor, evaluated) is a pair with its final evaluation
    (the average's); pairs count as higher by more than 2%, within 2% or lower. A sweep without it has no row."""
    sweeps, docs, name = tmp_path / "sweeps", tmp_path / "docs", "Walker2d-v4-softac-crossq-avg"
    shutil.copytree(KEPT / name, sweeps / name)
    copy_seed_0("Hopper-v4-softac", sweeps / "Hopper-v4-softac")  # no actor evaluations: not in the section
    finals = {s: json.loads((sweeps / name / f"seed={s}" / "summary.json").read_text())["last_eval"] for s in range(5)}
    actors = {0: finals[0] * 0.5, 1: finals[1] * 0.99, 2: finals[2] * 1.5}  # average higher, within 2%, lower
    for seed, value in actors.items():
        (sweeps / name / f"seed={seed}" / "actor-eval.json").write_text(json.dumps({"mean_return": value}))
    docs.mkdir()
    assert load_benchmark_script("results_doc").main([str(sweeps), "--docs", str(docs)]) == 0
    section = (docs / "results.md").read_text().split("## Weight averaging: the two policies of one training")[1]
    rows = [line for line in section.split("\n## ")[0].splitlines() if line.startswith("| Walker2d-v4")]
    assert len(rows) == 1 and "Hopper-v4-softac" not in section.split("\n## ")[0]
    cells = [cell.strip() for cell in rows[0].strip("|").split("|")]
    assert cells[1:3] == [name, "3"]
    assert cells[3] == ", ".join(f"{actors[s]:.0f}" for s in range(3)) + f" ({sum(actors.values()) / 3:.0f})"
    assert cells[4] == ", ".join(f"{finals[s]:.0f}" for s in range(3)) + f" ({sum(finals[s] for s in range(3)) / 3:.0f})"
    assert cells[5] == "1 / 1 / 1"


def test_keep_trials_copies_finished_trials_results_only(tmp_path):
    """benchmarks/keep_trials.sh: a worktree's finished trials, without weights, into the checkout it lives in
    (here a copy of it in tmp_path); an unfinished trial is left out; a directory that is no sweep is refused with
    exit code 2."""
    import subprocess

    checkout, worktree, rel = tmp_path / "checkout", tmp_path / "worktree", "benchmarks/sweeps/X"
    (checkout / "benchmarks").mkdir(parents=True)
    script = shutil.copy(ROOT / "benchmarks" / "keep_trials.sh", checkout / "benchmarks")
    sweep = worktree / rel
    (sweep / "seed=0" / "checkpoints").mkdir(parents=True)
    (sweep / "seed=1").mkdir()
    (sweep / "sweep.json").write_text("{}")
    (sweep / "summary.md").write_text("# summary")
    for name in ("summary.json", "eval.csv", "config.yaml", "actor-eval.json"):
        (sweep / "seed=0" / name).write_text(name)
    (sweep / "seed=0" / "checkpoints" / "latest.npz").write_text("weights")
    (sweep / "seed=1" / "eval.csv").write_text("still running")  # no summary.json yet
    done = subprocess.run(["bash", script, str(worktree), rel], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == f"{rel}: seed=0"
    kept = checkout / rel
    assert sorted(p.name for p in (kept / "seed=0").iterdir()) == ["actor-eval.json", "config.yaml", "eval.csv",
                                                                   "summary.json"]
    assert (kept / "summary.md").read_text() == "# summary"
    assert not (kept / "seed=1").exists()
    refused = subprocess.run(["bash", script, str(worktree), "nowhere"], capture_output=True, text=True)
    assert refused.returncode == 2 and "no sweep.json" in refused.stderr


@pytest.mark.skipif(not (KEPT / "Pendulum-v1-softac" / "sweep.json").exists(), reason="kept Pendulum sweep not present")
def test_the_pixels_section_sets_softacs_pixel_runs_beside_sb3s_cnn_policy_runs(tmp_path):
    """SWEEPS/pixels/ holds softac's pixel sweeps and SB3's CnnPolicy runs (benchmarks/sb3_pixels.py): each gets a
    row with every seed's final return, its first evaluation at the env's mark (step and seconds then), its steps
    and wall seconds; they stay out of the env sections (those are of state observations)."""
    import yaml

    sweeps, docs = tmp_path / "sweeps", tmp_path / "docs"
    softac = sweeps / "pixels" / "Pendulum-v1-softac-48px"
    copy_seed_0("Pendulum-v1-softac", softac)
    spec = json.loads((softac / "sweep.json").read_text())
    spec["overrides"] = ["pixels=true", "pixel_size=48", "batch_size=32"]
    (softac / "sweep.json").write_text(json.dumps(spec))
    from softac.config.sac_config import SACConfig

    config = dict(vars(SACConfig.for_env("Pendulum-v1").with_overrides(spec["overrides"])))
    config.update(hidden_sizes=list(config["hidden_sizes"]), seed=0)
    (softac / "seed=0" / "config.yaml").write_text(yaml.safe_dump(config))
    # the same sweep run before pixel_range and target_encoder's preset: its row names what it ran with
    older = sweeps / "pixels" / "Pendulum-v1-softac-48px-older"
    shutil.copytree(softac, older)
    (older / "seed=0" / "config.yaml").write_text(yaml.safe_dump(
        {k: v for k, v in config.items() if k != "pixel_range"} | {"target_encoder": True}))
    sb3 = sweeps / "pixels" / "Pendulum-v1-sb3-cnn-48px" / "seed=1"
    sb3.mkdir(parents=True)
    (sb3 / "eval.csv").write_text("step,return_mean,return_std,wall_s\n1000,-900,1,50\n2000,-190,1,120\n3000,-170,1,200\n")
    (sb3 / "summary.json").write_text(json.dumps({
        "framework": "sb3-cnn", "env": "Pendulum-v1", "seed": 1, "steps": 3000, "pixel_size": 48, "frames": 3,
        "action_repeat": 1, "batch_size": 256, "wall_s": 210.4, "final_return": -170.0, "machine": "CPU X, 2 cores"}))
    (sweeps / "pixels" / "notes").mkdir()  # neither: no row
    docs.mkdir()
    assert load_benchmark_script("results_doc").main([str(sweeps), "--docs", str(docs)]) == 0
    text = (docs / "results.md").read_text()
    section = text.split("## From pixels")[1].split("\n## ")[0]
    rows = {line.split("|")[2].strip(): [c.strip() for c in line.strip("|").split("|")]
            for line in section.splitlines() if line.startswith("| Pendulum-v1")}
    summary = json.loads((softac / "seed=0" / "summary.json").read_text())
    today = "softac, env preset + pixels=true pixel_size=48 batch_size=32"
    assert set(rows) >= {today, f"{today}, as run then: pixel_range=centered target_encoder=true"}, rows
    ours = rows[today]
    assert ours[2] == "48x48, 3 stacked, action repeat 1, batch 32" and ours[3] == "1"
    assert ours[4] == f"{summary['last_eval']:.0f} ({summary['last_eval']:.0f})"
    assert ours[5].startswith("2k (") and ours[6] == "20k" and ours[7] == f"{summary['train_time_s']:.0f}"
    theirs = rows["SB3 SAC CnnPolicy (SB3's defaults, benchmarks/sb3_pixels.py)"]
    assert theirs[2:] == ["48x48, 3 stacked, action repeat 1, batch 256", "1", "-170 (-170)", "2k (120 s)", "3k", "210",
                          "CPU X"]
    assert "Pendulum-v1-softac-48px" not in text.split("## From pixels")[0]


def test_the_fronts_configurations_each_get_a_colour_and_a_marker_of_their_own():
    from softac.errors import SoftacError
    from softac.outputs.plots import FRONT_COLOURS, front_styles

    names = [f"configuration {i}" for i in range(len(FRONT_COLOURS))]
    styles = front_styles(names)
    assert len({colour for colour, _ in styles.values()}) == len(names)
    assert len({str(marker) for _, marker in styles.values()}) == len(names)
    with pytest.raises(SoftacError, match="at most 20 configurations"):
        front_styles([*names, "one more"])


@pytest.mark.skipif(not (KEPT / "Hopper-v5-softac" / "sweep.json").exists(), reason="kept Hopper sweeps not present")
def test_the_front_figure_draws_short_labels_the_named_and_best_published_on_every_panel_and_gpu_points(
        tmp_path, monkeypatch):
    """Issue 66's front: configurations by short labels with a key under the figure, every panel the same named
    published methods and its env's best, a GPU trial's point told apart from a CPU's."""
    import yaml

    sweeps, docs = tmp_path / "sweeps", tmp_path / "docs"
    shutil.copytree(KEPT / "Hopper-v5-softac", sweeps / "Hopper-v4-softac")
    shutil.copytree(KEPT / "Hopper-v5-softac", sweeps / "Ant-v4-softac-crossq-avg")
    spec = json.loads((sweeps / "Ant-v4-softac-crossq-avg" / "sweep.json").read_text())
    (sweeps / "Ant-v4-softac-crossq-avg" / "sweep.json").write_text(json.dumps({**spec, "preset": "crossq-avg"}))
    for trial in (sweeps / "Ant-v4-softac-crossq-avg").glob("seed=*"):
        config = yaml.safe_load((trial / "config.yaml").read_text())
        (trial / "config.yaml").write_text(yaml.safe_dump({**config, "device": "gpu"}))
    docs.mkdir()
    results_doc = load_benchmark_script("results_doc")
    drawn = {}
    results_mujoco = __import__("results_mujoco")
    original = results_mujoco.plot_front
    monkeypatch.setattr(results_mujoco, "plot_front",
                        lambda points, published, out, title: drawn.update(points=points, published=published)
                        or original(points, published, out, title))
    assert results_doc.main([str(sweeps), "--docs", str(docs)]) == 0
    assert set(drawn["points"]) == {"Hopper-v4", "Ant-v4"}
    assert list(drawn["points"]["Hopper-v4"]) == ["crossq"] and list(drawn["points"]["Ant-v4"]) == ["crossq-avg"]
    assert drawn["points"]["Ant-v4"]["crossq-avg"].gpu and drawn["points"]["Ant-v4"]["crossq-avg"].machine.endswith(
        " + GPU")
    assert not drawn["points"]["Hopper-v4"]["crossq"].gpu
    published = results_doc.published_means()
    for env, lines in drawn["published"].items():
        best = max((m for m in published if env in published[m]), key=lambda m: published[m][env][0])
        assert set(lines) == {"SAC", "CrossQ", "FlashSAC", "XQC", "MR.Q", best}
        assert lines[best] == published[best][env][0]
    key = (docs / "results.md").read_text().split("The figure's key")[1].split("\n## ")[0]
    rows = [line for line in key.splitlines() if line.startswith("| crossq")]
    assert rows[0].startswith("| crossq | softac, crossq preset | ") and "GPU" not in rows[0]
    assert rows[1].startswith("| crossq-avg | softac, crossq-avg preset | ") and rows[1].endswith(" + GPU |")
    n = len(list((KEPT / "Hopper-v5-softac").glob("seed=*")))  # each configuration's seeds per env, in suite order
    assert "| label | configuration | seeds (Hopper, Ant) | machine |" in key
    assert f" preset | {n}, - | " in rows[0] and f" preset | -, {n} | " in rows[1]
    assert (docs / "results" / "front-v4.png").stat().st_size > 10_000


def test_the_playground_section_sets_softacs_device_loop_beside_braxs_sac(tmp_path):
    """benchmarks/results_playground.py: per sweep the settings and the envs (softac's n_envs, Brax's num_envs), the
    median over seeds of each trial's steady env steps per second (its progress rows in the run's second half, past
    the compiles), the final evaluations' mean and sd over seeds and the median wall time; sweeps of one setting
    pooled in a row of their own."""
    import yaml

    def trial(sweep: str, seed: int, config: dict, fps: list[float], final: float, wall: float) -> None:
        run = tmp_path / "sweeps" / sweep / f"seed={seed}"
        run.mkdir(parents=True)
        (run / "config.yaml").write_text(yaml.safe_dump({"env_id": "playground:CartpoleSwingup", "total_steps": 400,
                                                          "machine": "Intel(R) Xeon(R) Processor (AMX), 2 cores",
                                                          **config}))
        (run / "summary.json").write_text(json.dumps({"last_eval": final, "wall_s": wall}))
        rows = "\n".join(f"{100 * (i + 1)},{i},{v}" for i, v in enumerate(fps))
        (run / "progress.csv").write_text("step,time_s,fps\n" + rows + "\n")

    trial("playground-Cartpole-softac", 0, {"n_envs": 128}, [5.0, 10.0, 100.0, 110.0], 400.0, 60.0)  # steady 105
    trial("playground-Cartpole-softac", 1, {"n_envs": 128}, [5.0, 10.0, 120.0, 120.0], 500.0, 80.0)  # steady 120
    brax_like = {"n_envs": 128, "init": "lecun_uniform", "warmup_actions": "policy"}
    trial("playground-Cartpole-softac-new", 0, brax_like, [1.0, 1.0, 90.0, 90.0], 300.0, 50.0)
    trial("playground-Cartpole-softac-new-s1", 1, brax_like, [1.0, 1.0, 100.0, 100.0], 700.0, 70.0)
    trial("playground-Cartpole-brax-sac", 0, {"framework": "brax-sac", "brax": {"num_envs": 128}}, [1.0, 2.0, 3.0, 50.0],
          600.0, 90.0)  # steady 26.5
    trial("Hopper-v4-softac", 0, {"n_envs": 1}, [1.0], 1.0, 1.0)  # not a Playground sweep
    section = load_benchmark_script("results_doc").playground_section(tmp_path / "sweeps")
    rows = [line for line in section if line.startswith("| playground-")]
    head = "| playground:CartpoleSwingup | 128 | 400 |"
    assert rows == [
        f"| playground-Cartpole-brax-sac | brax-sac | Brax's own {head} 1 | 26 | 600.0 ± 0.0 | 90 | Intel Xeon (AMX) |",
        f"| playground-Cartpole-softac | softac | before 7c51039 {head} 2 | 112 | 450.0 ± 70.7 | 70 | Intel Xeon (AMX) |",
        f"| playground-Cartpole-softac-new | softac | Brax's networks and warm-up {head} 1 | 90 | 300.0 ± 0.0 | 50 "
        "| Intel Xeon (AMX) |",
        f"| playground-Cartpole-softac-new-s1 | softac | Brax's networks and warm-up {head} 1 | 100 | 700.0 ± 0.0 | 70 "
        "| Intel Xeon (AMX) |",
        # the two sweeps of one setting, pooled: seeds 0 and 1
        f"| playground-Cartpole-softac-new + playground-Cartpole-softac-new-s1 | softac | Brax's networks and warm-up "
        f"{head} 2 | 95 | 500.0 ± 282.8 | 60 | Intel Xeon (AMX) |"]


def test_the_offline_section_sets_each_dataset_beside_the_preset_from_scratch(tmp_path):
    """benchmarks/results_offline.py: per env, each offline-* sweep's returns at 10k, 25k, 50k and 100k online steps
    (mean ± sd over seeds), the median first step at or above crossq-avg-from-scratch's mean at 100k (with the seeds
    that got there) and the median wall time of its comparable trials; a trial another pinned process shared its
    CPU with counts for the returns, not the time."""
    import yaml

    def trial(sweep: str, seed: int, data: str | None, curve: list[float], wall: float, shared: bool = False) -> None:
        d = tmp_path / "sweeps" / sweep
        overrides = [f"offline_data=/data/{data}"] if data else []
        d.mkdir(parents=True, exist_ok=True)
        (d / "sweep.json").write_text(json.dumps({"env_id": "Hopper-v5", "steps": 100000, "seeds": [0, 1],
                                                  "preset": "crossq-avg", "overrides": overrides,
                                                  "framework": "softac"}))
        run = d / f"seed={seed}"
        run.mkdir()
        segment = {"machine": "Intel(R) Xeon(R) Processor (AMX), 2 cores", "cpus_shared": shared}
        (run / "config.yaml").write_text(yaml.safe_dump({
            "env_id": "Hopper-v5", "seed": seed, "total_steps": 100000, "segments": [segment],
            "offline_data": f"/data/{data}" if data else None, "offline_mode": "mix", "offline_fraction": 0.5}))
        steps = range(5000, 100001, 5000)
        (run / "eval.csv").write_text("step,mean_return\n" + "".join(f"{s},{v}\n" for s, v in zip(steps, curve)))
        (run / "summary.json").write_text(json.dumps({"steps": 100000, "train_time_s": wall, "wall_s": wall,
                                                      "last_eval": curve[-1]}))

    ramp = [100.0 * (i + 1) for i in range(20)]  # 100 at 5k ... 2,000 at 100k
    trial("offline-Hopper-v5-crossq-avg-scratch", 0, None, ramp, 300.0)
    trial("offline-Hopper-v5-crossq-avg-scratch", 1, None, [v + 200 for v in ramp], 340.0)  # 100k mean: 2,100
    trial("offline-Hopper-v5-crossq-avg-medium", 0, "Hopper-v5-medium-v0", [v * 3 for v in ramp], 320.0)  # 2,100 at 35k
    trial("offline-Hopper-v5-crossq-avg-medium", 1, "Hopper-v5-medium-v0", [900.0] * 20, 900.0, shared=True)
    section = load_benchmark_script("results_doc").offline_section(tmp_path / "sweeps")
    assert section[0] == "## Starting from data" and "### Hopper-v5" in section
    header = next(line for line in section if line.startswith("| sweep "))
    assert "| reaches scratch (2,100) |" in header
    rows = [line for line in section if line.startswith("| offline-")]
    assert rows == [
        "| offline-Hopper-v5-crossq-avg-medium | crossq-avg | Hopper-v5-medium-v0 (mix, 0.5) | 0, 1 | 750 ± 212 "
        "| 1,200 ± 424 | 1,950 ± 1,485 | 3,450 ± 3,606 | 35k (1/2) | 320 | Intel Xeon (AMX) |",
        "| offline-Hopper-v5-crossq-avg-scratch | crossq-avg | none | 0, 1 | 300 ± 141 | 600 ± 141 | 1,100 ± 141 "
        "| 2,100 ± 141 | 95k (1/2) | 320 | Intel Xeon (AMX) |"]
