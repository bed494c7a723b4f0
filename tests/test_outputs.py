"""What a person looks at: plots, videos, the HTML report, baselines."""

import itertools
import json
import os
import shutil
import subprocess

import numpy as np
import pytest

from conftest import TESTS, assert_clean_error, run_cli

SETS = ["--set", "hidden_sizes=32,32", "batch_size=32", "learning_starts=200", "buffer_size=5000",
        "log_interval=100", "eval_interval=200", "eval_episodes=2"]


@pytest.fixture
def pendulum_run(trained_run, tmp_path):
    """A copy of the session's trained run, this test's own: what one test adds to it (plots, videos, a report)
    is never there for another, so each test passes alone and in any order."""
    run = tmp_path / trained_run.name
    shutil.copytree(trained_run, run)
    return run


def _png_size(path):
    from PIL import Image

    with Image.open(path) as im:
        return im.size


def test_plot_single_run(pendulum_run):
    assert json.loads((pendulum_run / "baselines.json").read_text())["baselines"]["heuristic"]["episodes"] == 3
    r = run_cli("plot", str(pendulum_run))
    assert r.returncode == 0, r.stderr
    for name in ("learning_curve.png", "metrics.png"):
        path = pendulum_run / "plots" / name
        assert path.exists() and path.stat().st_size > 10_000
        w, h = _png_size(path)
        assert w >= 900 and h >= 500


def test_plot_several_runs_groups_configs(tmp_path):
    runs = []
    for seed in (0, 1):
        for tau in ("0.01", "0.05"):
            run = tmp_path / f"tau{tau}-s{seed}"
            r = run_cli("train", "--env", "softac_test_envs:Drift-v0", "--steps", "400", "--seed", str(seed),
                        "--out", str(run), "--no-progress", *SETS, f"tau={tau}")
            assert r.returncode == 0, r.stderr
            runs.append(str(run))
    out = tmp_path / "cmp"
    r = run_cli("plot", *runs, "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert (out / "comparison.png").stat().st_size > 10_000
    assert len(list(out.glob("*/learning_curve.png"))) == 4
    assert_clean_error(run_cli("plot", *runs), "--out")


def test_confidence_band_maths():
    from softac.outputs.plots import aligned_eval_curves, moving_average
    from softac.outputs.seed_stats import interquartile_mean, mean_and_ci, summarize_seeds, t_critical_95

    values = np.array([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]])
    mean, half, n = mean_and_ci(values)
    np.testing.assert_allclose(mean, [3.0, 4.0])
    np.testing.assert_allclose(half, [4.302653 * 2.0 / np.sqrt(3)] * 2, rtol=1e-6)  # the t table's 7 digits
    # Student t's two-sided 95% quantiles (printed tables): 1 dof 12.706, 2 dof 4.303, 30 dof 2.042,
    # 40 dof 2.021 (a table that jumps to 1.96 past 30 dof gets this wrong), and 1.96 in the limit
    assert [round(t_critical_95(n), 3) for n in (2, 3, 31, 41)] == [12.706, 4.303, 2.042, 2.021]
    assert t_critical_95(100_000) == pytest.approx(1.96, abs=1e-3)
    # IQM: the middle half of the seeds (rliable), the mean below 4 seeds
    assert interquartile_mean([1.0, 2.0, 3.0, 100.0]) == pytest.approx(2.5)
    assert interquartile_mean([0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 1000.0]) == pytest.approx(3.5)
    assert interquartile_mean([1.0, 2.0, 9.0]) == pytest.approx(4.0)
    s = summarize_seeds([2.0, 4.0, 6.0])
    assert (s.mean, s.std, s.iqm, s.n) == (4.0, 2.0, 4.0, 3)
    assert s.ci_half == pytest.approx(4.302653 * 2.0 / np.sqrt(3), rel=1e-6)
    assert summarize_seeds([5.0]).ci_half == 0.0
    np.testing.assert_allclose(moving_average(np.array([1.0, 3.0, 5.0, 7.0]), 2), [1.0, 2.0, 4.0, 6.0])
    assert aligned_eval_curves([])[0].size == 0


def test_stratified_bootstrap_of_the_iqm_resamples_runs_within_each_env():
    from softac.outputs.seed_stats import interquartile_mean, iqm_band, stratified_bootstrap_iqm

    # enumerable: env A's runs {0, 1} resampled give (0,0), (0,1), (1,0), (1,1) with probability 1/4 each,
    # env B's one run is always 10; the IQM of 3 values trims none, so the resampled IQMs are 10/3, 11/3
    # (half the time) and 12/3, and the 2.5th and 97.5th percentiles are the extremes
    point, low, high = stratified_bootstrap_iqm([[0.0, 1.0], [10.0]])
    assert point == pytest.approx(11 / 3)
    assert (low, high) == (pytest.approx(10 / 3), pytest.approx(12 / 3))
    # pooled over envs, a quarter cut from each end; an env of identical runs adds no width
    assert stratified_bootstrap_iqm([[5.0, 5.0], [7.0, 7.0]]) == (6.0, 6.0, 6.0)
    rng = np.random.default_rng(1)
    envs = [rng.normal(m, 1.0, size=n) for m, n in ((0.2, 5), (0.5, 5), (0.9, 3))]  # ragged is fine
    point, low, high = stratified_bootstrap_iqm(envs)
    pooled = np.concatenate(envs)
    assert point == pytest.approx(interquartile_mean(pooled))
    assert pooled.min() <= low < point < high <= pooled.max()
    assert stratified_bootstrap_iqm(envs) == (point, low, high)  # seeded: the same tables every time
    with pytest.raises(ValueError):
        stratified_bootstrap_iqm([[1.0], []])
    # per step of a curve: the seeds present there; one seed is its own band
    values = np.array([[1.0, 2.0, np.nan], [3.0, 4.0, 5.0]])
    iqm, low, high = iqm_band(values)
    np.testing.assert_allclose(iqm, [2.0, 3.0, 5.0])
    assert (low[2], high[2]) == (5.0, 5.0)
    assert 1.0 <= low[0] <= 2.0 <= high[0] <= 3.0 and 2.0 <= low[1] <= 3.0 <= high[1] <= 4.0


def test_baselines_json_and_heuristics():
    r = run_cli("baselines", "--env", "InvertedPendulum-v5", "--episodes", "3", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)["baselines"]
    assert set(out) == {"random", "zero", "heuristic"}
    assert out["heuristic"]["mean_return"] == 1000.0  # the hand-written controller balances the pole
    assert out["random"]["mean_return"] < 100
    r = run_cli("baselines", "--env", "Pusher-v5", "--episodes", "4", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)["baselines"]
    assert out["heuristic"]["mean_return"] > out["zero"]["mean_return"] > out["random"]["mean_return"]
    r = run_cli("baselines", "--env", "softac_test_envs:Drift-v0", "--episodes", "2", "--json")
    assert set(json.loads(r.stdout)["baselines"]) == {"random", "zero"}  # no heuristic for an unknown env
    assert_clean_error(run_cli("baselines", "--env", "CartPole-v1"), "Discrete action space")


def test_video_is_an_mp4_with_the_return_in_its_name(pendulum_run):
    r = run_cli("video", str(pendulum_run), "--max-steps", "60")
    assert r.returncode == 0, r.stderr
    videos = list((pendulum_run / "videos").glob("step*-return*.mp4"))
    assert len(videos) == 1
    import imageio.v2 as imageio

    reader = imageio.get_reader(videos[0])
    frames = list(itertools.islice(reader, 5))
    reader.close()
    assert len(frames) == 5
    assert frames[0].shape == (480, 640, 3) and max(f.mean() for f in frames) > 1.0
    out = pendulum_run / "custom.mp4"
    r = run_cli("video", str(pendulum_run), "--out", str(out), "--episodes", "2", "--max-steps", "20")
    assert r.returncode == 0 and out.stat().st_size > 1000
    assert_clean_error(run_cli("video", str(pendulum_run), "--out", str(pendulum_run / "x.gif")), ".mp4")


def test_video_of_the_actor_of_an_averaging_run_and_a_clean_error_without_one(pendulum_run):
    """`softac video --policy` films the policy it names (SAC.predict gets it), in a file that says which; a run
    without weight averaging has no average to film."""
    from softac.agent import SAC
    from softac.outputs.video import record

    class Recording:  # the agent, with the policies its predict is asked for written down
        def __init__(self, agent):
            self.agent, self.policies = agent, set()

        def __getattr__(self, name):
            return getattr(self.agent, name)

        def predict(self, obs, deterministic=True, policy="deployed"):
            self.policies.add(policy)
            return self.agent.predict(obs, deterministic=deterministic, policy=policy)

    agent = Recording(SAC.load(pendulum_run))
    result = record(agent, pendulum_run / "actor.mp4", max_steps=5, policy="actor", width=64, height=48)
    assert agent.policies == {"actor"} and result["lengths"] == [5]
    r = run_cli("video", str(pendulum_run), "--policy", "actor", "--max-steps", "10")
    assert r.returncode == 0, r.stderr
    assert len(list((pendulum_run / "videos").glob("step*-actor-return*.mp4"))) == 1
    assert_clean_error(run_cli("video", str(pendulum_run), "--policy", "average"), "no weight average")


def _chromium():
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if shutil.which(name):
            return shutil.which(name)
    return None


def test_report_is_self_contained_and_renders_in_chromium(pendulum_run, tmp_path):
    r = run_cli("video", str(pendulum_run), "--max-steps", "30")  # the report inlines the run's latest video
    assert r.returncode == 0, r.stderr
    r = run_cli("report", str(pendulum_run))
    assert r.returncode == 0, r.stderr
    page = (pendulum_run / "report.html").read_text()
    assert "http://" not in page and "https://" not in page  # no network requests
    assert page.count("data:image/png;base64,") >= 2 and "data:video/mp4;base64," in page
    for text in ("Evaluations", "Baselines", "Configuration", "Versions and machine", "heuristic"):
        assert text in page
    chromium = _chromium()
    if chromium is None:
        if os.environ.get("CI"):
            pytest.fail("chromium is missing in CI: `make test` should have installed it")
        pytest.skip("chromium not installed (make test installs it)")
    result = subprocess.run(
        [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         f"--user-data-dir={tmp_path / 'profile'}", "--enable-logging=stderr", "--v=0",
         "--virtual-time-budget=10000", "--dump-dom", (pendulum_run / "report.html").as_uri()],
        capture_output=True, text=True, timeout=120)
    dom = result.stdout
    assert 'data-images-loaded="2"' in dom and 'data-images-total="2"' in dom, dom[:300]
    assert 'data-errors="0"' in dom
    console_errors = [line for line in result.stderr.splitlines() if "CONSOLE" in line and "ERROR" in line]
    assert not console_errors, console_errors
    shot = tmp_path / "report.png"
    subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                    f"--user-data-dir={tmp_path / 'profile2'}", "--window-size=1200,2400",
                    f"--screenshot={shot}", (pendulum_run / "report.html").as_uri()],
                   capture_output=True, timeout=120)
    assert shot.exists() and shot.stat().st_size > 20_000


def test_report_and_plot_errors(tmp_path):
    assert_clean_error(run_cli("report", str(tmp_path / "missing")), "no such run directory")
    assert_clean_error(run_cli("plot", str(tmp_path)), "not a softac run directory")


def test_gl_backend_choice(monkeypatch):
    import softac.base.opengl as gl

    # the choice below sets both variables: restored after the test, also where they were unset (delenv alone
    # records nothing then, and the osmesa chosen here leaked into every later test's MuJoCo processes)
    for name in ("MUJOCO_GL", "PYOPENGL_PLATFORM"):
        monkeypatch.setenv(name, "unset by this test")
        monkeypatch.delenv(name)
    monkeypatch.setattr(gl, "gl_backend_works", lambda backend: False)
    # an earlier test in this worker may have rendered, importing PyOpenGL: that path has its own check below
    modules_before_rendering = {k: v for k, v in gl.sys.modules.items()
                                if k != "mujoco" and k.split(".")[0] != "OpenGL"}
    monkeypatch.setattr(gl.sys, "modules", modules_before_rendering)
    with pytest.raises(gl.SoftacError, match="libosmesa6"):
        gl.choose_gl_backend()
    monkeypatch.setattr(gl, "gl_backend_works", lambda backend: backend == "osmesa")
    assert gl.choose_gl_backend() == "osmesa" and os.environ["MUJOCO_GL"] == "osmesa"
    monkeypatch.setenv("MUJOCO_GL", "egl")
    assert gl.choose_gl_backend() == "egl"  # the user's choice wins
    monkeypatch.delenv("MUJOCO_GL")
    monkeypatch.setitem(gl.sys.modules, "OpenGL", object())
    assert gl.choose_gl_backend() == "preset"  # PyOpenGL already fixed its platform: nothing left to choose


def test_make_demo_installs_the_base_package_only(tmp_path):
    """`make demo` must not install PyTorch, Ray or the test tools: only `pip install -e .`."""
    if shutil.which("make") is None:
        pytest.skip("no make")
    root = TESTS.parent
    plan = subprocess.run(["make", "-n", "demo", f"VENV={tmp_path / 'venv'}"], cwd=root, capture_output=True,
                          text=True, timeout=60).stdout
    installs = [line for line in plan.splitlines() if "pip install" in line and "--upgrade pip" not in line]
    assert installs and all(line.rstrip().endswith("pip install -q -e .") for line in installs), installs
    test_plan = subprocess.run(["make", "-n", "test", f"VENV={tmp_path / 'venv'}"], cwd=root, capture_output=True,
                               text=True, timeout=60).stdout
    assert 'pip install -q -e ".[test]"' in test_plan


def test_comparison_labels_name_what_varies_shortly():
    """Legend labels name only the keys that vary, with searched floats cut to 4 significant digits."""
    from softac.outputs.plots import _describe_differences

    base = {"env_id": "Pusher-v5", "seed": 0, "gamma": 0.95, "hidden_sizes": [256, 256], "actor_lr": 0.001}
    other = {**base, "seed": 1, "actor_lr": 0.00036875529945204906, "hidden_sizes": [128, 128]}
    assert _describe_differences([base, other]) == ["actor_lr=0.001, hidden_sizes=256x256",
                                                    "actor_lr=0.0003688, hidden_sizes=128x128"]
    assert _describe_differences([base]) == ["Pusher-v5"]
    # what config.yaml records about the machine (CPU count, versions) does not split seeds into configurations
    assert _describe_differences([{**base, "cpus": 1, "machine": "A"}, {**other, "cpus": 2, "machine": "B"}]) \
        == _describe_differences([base, other])


def test_a_run_made_before_a_config_key_existed_groups_with_new_runs_at_its_default(tmp_path):
    """config.yaml of an older softac lacks keys added since (reset_interval, obs_norm): it ran with their
    defaults, so its seeds belong with new runs of the same settings; a changed value still splits them."""
    import yaml

    from softac.config.sac_config import SACConfig
    from softac.outputs.plots import group_runs

    new = SACConfig().to_dict()
    old = {k: v for k, v in new.items() if k not in ("reset_interval", "obs_norm", "obs_norm_clip")}
    runs = []
    for name, config in (("old", {**old, "seed": 0}), ("new", {**new, "seed": 1}),
                         ("reset", {**new, "seed": 2, "reset_interval": 5000}),
                         ("sbx", {"framework": "sbx", "env_id": new["env_id"], "seed": 0})):
        (tmp_path / name).mkdir()
        (tmp_path / name / "config.yaml").write_text(yaml.safe_dump(config))
        runs.append(tmp_path / name)
    labels, groups = group_runs(runs)
    assert [[r.name for r in g] for g in groups] == [["old", "new"], ["reset"], ["sbx"]]
    assert labels == ["softac, reset_interval=0", "softac, reset_interval=5000", "sbx"]
    # named configurations (the results page names them by preset and framework): grouped by name
    names = {runs[0]: "softac crossq preset", runs[1]: "softac crossq preset", runs[2]: "softac crossq preset",
             runs[3]: "SBX SAC, its defaults"}
    labels, groups = group_runs(runs, names)
    assert labels == ["softac crossq preset", "SBX SAC, its defaults"]
    assert [[r.name for r in g] for g in groups] == [["old", "new", "reset"], ["sbx"]]


def test_the_aggregate_figure_draws_one_bar_per_configuration(tmp_path):
    from softac.outputs.plots import plot_aggregate

    out = plot_aggregate({"softac crossq preset": (0.8, 0.6, 0.9), "SBX CrossQ, same settings": (0.5, 0.2, 0.7)},
                         tmp_path / "aggregate.png", "IQM of normalised scores", "normalised score")
    assert out.stat().st_size > 10_000
