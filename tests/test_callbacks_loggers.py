"""Callbacks (hooks, clean stops, curriculum) and loggers (one interface; TensorBoard, W&B, MLflow)."""

import functools
import json
from pathlib import Path

import numpy as np
import pytest

from conftest import assert_clean_error, run_cli
from softac import SAC
from softac.run.callbacks import Callback, StopOnPlateau
from softac.errors import SoftacError
from softac.run.csv_logs import read_csv


class Recorder(Callback):
    def __init__(self):
        self.calls = []
        self.steps = []

    def on_training_start(self, info):
        self.calls.append(("start", info.step))

    def on_step(self, info):
        self.steps.append(info.step)

    def on_eval(self, info, stats):
        self.calls.append(("eval", info.step, stats["mean_return"]))

    def on_checkpoint(self, info, name, path):
        assert Path(path).is_dir()
        self.calls.append(("checkpoint", info.step, name))

    def on_training_end(self, info, summary):
        self.calls.append(("end", info.step, summary["stop_reason"]))


def test_hooks_run_at_each_step_eval_and_checkpoint(tiny, tmp_path):
    recorder = Recorder()
    agent = SAC(tiny(n_envs=2, eval_interval=200, checkpoint_interval=400))
    summary = agent.learn(600, run_dir=tmp_path / "run", progress=False, callbacks=[recorder])
    assert recorder.steps == list(range(2, 601, 2))  # after each vector-env step
    calls = recorder.calls
    assert calls[0] == ("start", 0) and calls[-1] == ("end", 600, "steps")
    assert [c[1] for c in calls if c[0] == "eval"] == [200, 400, 600]
    lasts = [c[1] for c in calls if c[:1] == ("checkpoint",) and c[2] == "last"]
    assert lasts == [0, 400, 600]  # the first one, the interval, the end
    assert any(c[0] == "checkpoint" and c[2] == "best" for c in calls)
    assert summary["stop_reason"] == "steps" and not summary["stopped_early"]


class StopAt(Callback):
    def __init__(self, step):
        self.step = step

    def on_step(self, info):
        return info.step < self.step  # False stops


def test_a_callback_stops_training_cleanly_with_a_checkpoint_and_a_reason(tiny, tmp_path):
    run = tmp_path / "run"
    agent = SAC(tiny(eval_interval=500))
    summary = agent.learn(1000, run_dir=run, progress=False, callbacks=[StopAt(300)])
    assert summary["steps"] == 300 and summary["stopped_early"]
    assert summary["stop_reason"] == "callback: StopAt.on_step returned False"
    assert json.loads((run / "summary.json").read_text())["stop_reason"] == summary["stop_reason"]
    assert SAC.load(run, which="last").num_steps == 300  # the checkpoint is where it stopped
    assert [int(r["step"]) for r in read_csv(run / "eval.csv")] == [300]  # the final evaluation ran
    # and the run resumes from there like any other
    resumed = SAC.load(run, which="last")
    assert resumed.learn(100, run_dir=run, progress=False)["steps"] == 400


def test_stop_with_a_reason_from_on_training_start_trains_nothing(tiny):
    class Refuse(Callback):
        def on_training_start(self, info):
            info.stop("nothing to do")

    summary = SAC(tiny()).learn(500, progress=False, callbacks=[Refuse()])
    assert summary["steps"] == 0 and summary["stop_reason"] == "callback: nothing to do"


def test_stop_on_plateau_stops_after_patience_evaluations_without_improvement(tiny):
    plateau = StopOnPlateau(patience=2, min_delta=1e9)  # no evaluation can improve by 1e9
    summary = SAC(tiny(eval_interval=100)).learn(2000, progress=False, callbacks=[plateau])
    # the first evaluation sets the best; the next two do not improve on it
    assert summary["steps"] == 300 and summary["stop_reason"].startswith("callback: eval mean return has not")


def test_metrics_and_a_curriculum_through_the_training_envs(tiny):
    seen = {}

    class Curriculum(Callback):
        def on_step(self, info):
            if info.step == 300:
                seen["metrics"] = info.metrics
                seen["old"] = info.apply_to_envs(lambda env: env.unwrapped.action_space.high.copy())
                info.apply_to_envs(lambda env: setattr(env.unwrapped, "difficulty", 2))

    agent = SAC(tiny(n_envs=2))
    agent.learn(400, progress=False, callbacks=[Curriculum()])
    assert {"critic_loss", "actor_loss", "alpha"} <= set(seen["metrics"])
    assert len(seen["old"]) == 2
    assert [env.unwrapped.difficulty for env in agent.collector.pool.envs] == [2, 2]


def _difficulty(env):
    return getattr(env.unwrapped, "difficulty", 0)


def _set_difficulty(env, level):
    env.unwrapped.difficulty = level


def test_a_curriculum_reaches_envs_in_worker_processes_and_a_lambda_is_refused(tiny):
    seen = {}

    class Curriculum(Callback):
        def on_step(self, info):
            if info.step >= 200 and not seen:  # steps go up by n_envs=3
                seen["before"] = info.apply_to_envs(_difficulty)
                info.apply_to_envs(functools.partial(_set_difficulty, level=3))
                seen["after"] = info.apply_to_envs(_difficulty)
                with pytest.raises(SoftacError, match="not a lambda or a closure"):
                    info.apply_to_envs(lambda env: 1)

    agent = SAC(tiny(n_envs=3, env_workers=2))
    agent.learn(300, progress=False, callbacks=[Curriculum()])
    assert seen == {"before": [0, 0, 0], "after": [3, 3, 3]}


def test_an_object_that_is_not_a_callback_is_refused(tiny):
    with pytest.raises(SoftacError, match="is not a callback"):
        SAC(tiny()).learn(10, progress=False, callbacks=[object()])


class ListLogger:
    def __init__(self):
        self.records = []

    def log(self, kind, values, step):
        self.records.append((kind, step, dict(values)))

    def close(self):
        pass


def test_a_user_logger_gets_the_same_records_as_the_csv_files(tiny, tmp_path):
    run = tmp_path / "run"
    logger = ListLogger()
    SAC(tiny(eval_interval=200)).learn(600, run_dir=run, progress=False, loggers=[logger])
    by_kind = {kind: [(s, v) for k, s, v in logger.records if k == kind] for kind in ("train", "rollout", "eval")}
    progress = read_csv(run / "progress.csv")
    assert [s for s, _ in by_kind["train"]] == [int(r["step"]) for r in progress]
    # the CSV files keep 6 significant digits (logs._fmt's .6g): within 5e-6 relative
    assert by_kind["train"][-1][1]["critic_loss"] == pytest.approx(float(progress[-1]["critic_loss"]), rel=1e-5)
    assert [s for s, _ in by_kind["eval"]] == [int(r["step"]) for r in read_csv(run / "eval.csv")]
    episodes = read_csv(run / "episodes.csv")
    assert [v["return"] for _, v in by_kind["rollout"]] == pytest.approx([float(r["return"]) for r in episodes],
                                                                          rel=1e-5)
    # without a run directory a user's logger still gets every record
    plain = ListLogger()
    SAC(tiny()).learn(300, progress=False, loggers=[plain])
    assert {k for k, _, _ in plain.records} == {"train", "rollout"}


def test_logger_none_writes_csv_only_and_unknown_names_are_refused(tmp_path):
    run = tmp_path / "run"
    r = run_cli("train", "--env", "softac_test_envs:Drift-v0", "--steps", "200", "--out", str(run), "--no-progress",
                "--logger", "none", "--set", "hidden_sizes=16", "learning_starts=100", "eval_interval=0")
    assert r.returncode == 0, r.stderr
    assert (run / "progress.csv").exists() and not (run / "tb").exists()
    bad = run_cli("train", "--steps", "10", "--out", str(tmp_path / "bad"), "--logger", "tensorboard,wandbb")
    assert_clean_error(bad, "unknown logger 'wandbb'")
    assert not (tmp_path / "bad").exists()


def test_a_missing_backend_package_is_bad_input_naming_the_extra(tiny, tmp_path, monkeypatch):
    from softac.run import loggers

    monkeypatch.setattr(loggers.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(SoftacError, match=r"pip install 'softac\[wandb\]'"):
        SAC(tiny(loggers="wandb")).learn(10, run_dir=tmp_path / "run", progress=False)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("backend", ["wandb", "mlflow"])
def test_wandb_and_mlflow_offline_get_the_metrics_and_a_resume_continues_their_run(backend, tmp_path):
    pytest.importorskip(backend)
    run = tmp_path / "run"
    env = {"WANDB_MODE": "offline", "WANDB_SILENT": "true", "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path}/mlflow.db",
           "MLFLOW_EXPERIMENT_NAME": "softac-test"}
    common = ["--no-progress", "--set", "hidden_sizes=16", "learning_starts=100", "eval_interval=200",
              "eval_episodes=2", "log_interval=100"]
    r = run_cli("train", "--env", "softac_test_envs:Drift-v0", "--steps", "400", "--out", str(run),
                "--logger", f"tensorboard,{backend}", *common, env_extra=env)
    assert r.returncode == 0, r.stderr
    first = json.loads((run / "loggers.json").read_text())[backend]
    r = run_cli("train", "--resume", str(run), "--steps", "200", "--no-progress", env_extra=env)
    assert r.returncode == 0, r.stderr
    assert json.loads((run / "loggers.json").read_text())[backend] == first  # the same run, continued
    assert (run / "tb").is_dir()
    if backend == "wandb":
        assert first["mode"] == "offline"
        offline = list((run / "wandb").glob(f"offline-run-*-{first['id']}"))
        assert offline and list(offline[0].glob("*.wandb"))
    else:
        import mlflow

        client = mlflow.MlflowClient(tracking_uri=env["MLFLOW_TRACKING_URI"])
        history = client.get_metric_history(first["run_id"], "eval/mean_return")
        assert sorted(m.step for m in history) == [200, 400, 600]
        assert [int(m.step) for m in client.get_metric_history(first["run_id"], "train/critic_loss")][-1] == 600
        run_info = client.get_run(first["run_id"])
        assert run_info.data.params["env_id"] == "softac_test_envs:Drift-v0"
        assert run_info.info.status == "FINISHED"


def _readme_block(containing: str) -> str:
    readme = (Path(__file__).resolve().parent.parent / "docs" / "guides" / "callbacks-and-loggers.md").read_text()
    blocks = [b.split("```", 1)[0] for b in readme.split("```python\n")[1:]]
    return next(b for b in blocks if containing in b)


def test_the_guides_curriculum_example_changes_the_training_envs_only(tiny):
    code = _readme_block("class HeavierPole").split("agent.learn(")[0]  # the class, not the 30k-step run
    namespace: dict = {}
    exec(code, namespace)
    agent = SAC(tiny("InvertedPendulum-v5"))
    base = float(agent.make_env().unwrapped.model.body_mass[2])
    agent.learn(500, progress=False, callbacks=[namespace["HeavierPole"](every=200, factor=2.0)])
    assert float(agent.collector.pool.envs[0].unwrapped.model.body_mass[2]) == pytest.approx(base * 4)  # at 200 and 400
    assert float(agent.make_env().unwrapped.model.body_mass[2]) == pytest.approx(base)


def test_a_callback_sees_the_learner_and_the_run_state_of_the_agent_it_trains(tiny):
    class Probe(Callback):
        seen: list = []

        def on_eval(self, info, stats):
            obs = np.linspace(-1.0, 1.0, 2 * info.learner.spaces.obs_dim, dtype=np.float32).reshape(2, -1)
            np.testing.assert_array_equal(info.learner.predict(obs), info.agent.predict(obs, deterministic=True))
            assert info.run_state is info.agent.run_state and info.learner is info.agent.learner
            self.seen.append((info.step, info.last_eval == stats["mean_return"]))

    agent = SAC(tiny(eval_interval=200))
    agent.learn(400, progress=False, callbacks=[Probe()])
    assert Probe.seen == [(200, True), (400, True)]
