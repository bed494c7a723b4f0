"""The Python API: save/load, exact resume, envs given as instances, asymmetric bounds."""

import json

import jax
import numpy as np
import pytest

from conftest import assert_same_training
from softac import SAC, evaluate
from softac.errors import SoftacError
from softac.run.checkpoint import load as load_checkpoint
from softac.run.csv_logs import read_csv
from softac_test_envs import DriftEnv


def test_save_load_gives_identical_predictions(tiny, tmp_path):
    agent = SAC(tiny())
    agent.learn(400, progress=False)
    agent.save(tmp_path / "agent")
    loaded = SAC.load(tmp_path / "agent")
    obs = np.random.default_rng(0).normal(size=(16, 2)).astype(np.float32)
    np.testing.assert_array_equal(agent.predict(obs), loaded.predict(obs))
    np.testing.assert_array_equal(agent.predict(obs[0]), loaded.predict(obs[0]))
    np.testing.assert_array_equal(agent.predict(obs, deterministic=False), loaded.predict(obs, deterministic=False))
    assert loaded.num_steps == 400
    meta, arrays = load_checkpoint(tmp_path / "agent")
    assert not meta["has_buffer"] and not any(k.startswith("buffer/") for k in arrays)


@pytest.mark.exact
@pytest.mark.parametrize("obs_once,n_step,obs_norm,crossq", [
    (False, 1, False, False), (True, 1, False, False), (False, 3, False, False), (True, 3, False, False),
    (False, 1, True, False), (True, 3, True, False), (False, 1, False, True), (True, 3, True, True)])
def test_resume_is_exact(tiny, tmp_path, obs_once, n_step, obs_norm, crossq):
    """N+M steps in one go equals N, save, load, M (same seed, CPU), with either replay buffer, n-step too,
    with running observation statistics, and with CrossQ's batch statistics."""
    cfg = tiny(n_envs=2, gradient_steps=2, policy_frequency=2, eval_interval=300, buffer_obs_once=obs_once,
               n_step=n_step, obs_norm=obs_norm, crossq=crossq, batch_renorm_warmup=400)
    straight = SAC(cfg)
    straight.learn(900, run_dir=tmp_path / "straight", progress=False)

    first = SAC(cfg)
    first.learn(500, run_dir=tmp_path / "split", progress=False)
    resumed = SAC.load(tmp_path / "split", which="last")
    assert resumed.num_steps == 500 and len(resumed.collector.buffer) == 500
    resumed.learn(400, run_dir=tmp_path / "split", progress=False)

    assert_same_training(straight, resumed)
    # the first segment stopped off the eval grid (500): no evaluation or log row of its own there
    for name in ("eval.csv", "episodes.csv"):
        assert (tmp_path / "straight" / name).read_text() == (tmp_path / "split" / name).read_text(), name
    timeless = lambda run: [{k: v for k, v in row.items() if k not in ("time_s", "fps")}  # noqa: E731
                            for row in read_csv(tmp_path / run / "progress.csv")]
    assert timeless("straight") == timeless("split")
    if obs_norm:
        assert straight.learner.obs_norm.count == resumed.learner.obs_norm.count == 900
        np.testing.assert_array_equal(straight.learner.obs_norm.mean, resumed.learner.obs_norm.mean)
        np.testing.assert_array_equal(straight.learner.obs_norm.m2, resumed.learner.obs_norm.m2)


def test_env_instance_and_vector_envs(tiny):
    agent = SAC(tiny(n_envs=3), env=DriftEnv(low=-2.0, high=0.5))
    assert agent.config.env_id == "DriftEnv"
    agent.learn(300, progress=False)
    assert agent.num_steps == 300
    acts = agent.predict(np.random.default_rng(1).normal(size=(100, 2)) * 5, deterministic=False)
    assert acts.min() >= -2.0 and acts.max() <= 0.5


@pytest.mark.parametrize("obs_norm", [False, True])
def test_asymmetric_bounds_agent_learns_the_best_action(tiny, obs_norm):
    """Drift-v0 pays most at action 1 inside [-1, 3]: the policy must reach the off-centre optimum."""
    agent = SAC(tiny(learning_starts=300, gradient_steps=2, actor_lr=3e-3, critic_lr=3e-3, alpha_lr=3e-3,
                     obs_norm=obs_norm))
    agent.learn(2500, progress=False)
    stats = evaluate(agent, episodes=4)
    actions = agent.predict(np.array([[0.0, t] for t in range(0, 25, 5)], np.float32))
    assert np.all(np.abs(actions - 1.0) < 0.4), actions
    assert stats["mean_return"] > 15.0


def test_evaluate_reports_per_episode_results(tiny):
    """returns[i] and lengths[i] are those of episode i, started from seed + i, as the policy played it; the
    summary statistics are theirs."""
    import gymnasium as gym

    from softac.run.evaluation import EVAL_SEED_OFFSET

    agent = SAC(tiny())
    calls = []  # (observations, actions) of each policy call the evaluation made
    predict = agent.predict

    def recording_predict(obs, deterministic=True):
        actions = predict(obs, deterministic=deterministic)
        calls.append((np.array(obs, copy=True), np.array(actions, copy=True)))
        return actions

    agent.predict = recording_predict
    stats = evaluate(agent, episodes=3)
    del agent.predict
    assert stats["episodes"] == 3 and len(stats["returns"]) == 3 and len(stats["lengths"]) == 3
    # replay each episode on an env of its own, taking the action the policy chose for each of its observations
    # (found among the rows of the batched call; the evaluation steps its 3 episodes side by side)
    for i in range(3):
        env = gym.make("softac_test_envs:Drift-v0")
        obs, _ = env.reset(seed=agent.config.seed + EVAL_SEED_OFFSET + i)
        total, length, done = 0.0, 0, False
        while not done:
            batch, actions = calls[length]
            rows = np.flatnonzero((batch == obs).all(axis=1))
            assert len(rows) == 1, (i, length)
            obs, reward, terminated, truncated, _ = env.step(actions[rows[0]])
            total, length, done = total + float(reward), length + 1, terminated or truncated
        assert (stats["returns"][i], stats["lengths"][i]) == (total, length), i
    assert len(calls) == max(stats["lengths"])  # one batched call per step while any episode runs
    returns = np.array(stats["returns"])
    assert (stats["mean_return"], stats["std_return"]) == (np.mean(returns), np.std(returns))
    assert (stats["min_return"], stats["max_return"]) == (returns.min(), returns.max())
    assert stats["mean_length"] == np.mean(stats["lengths"])
    again = evaluate(agent, episodes=3)
    assert again["returns"] == stats["returns"]  # deterministic policy, fixed eval seeds


def test_a_loaded_agent_never_writes_over_another_run(tiny, tmp_path):
    """SAC.load(A) then learn(run_dir=B): B holding another run is refused and left as it was; A (loaded from
    its last checkpoint) continues, a new directory is fine, and A's best checkpoint does not rewind A."""
    from softac.errors import SoftacError

    cfg = tiny(eval_interval=200)
    for name in ("a", "b"):
        SAC(cfg).learn(400, run_dir=tmp_path / name, progress=False)
    b_before = {p: p.read_bytes() for p in (tmp_path / "b").rglob("*") if p.is_file()}

    loaded = SAC.load(tmp_path / "a", which="last")
    with pytest.raises(SoftacError, match="already holds a run"):
        loaded.learn(100, run_dir=tmp_path / "b", progress=False)
    assert {p: p.read_bytes() for p in (tmp_path / "b").rglob("*") if p.is_file()} == b_before

    best = SAC.load(tmp_path / "a", which="best")
    with pytest.raises(SoftacError, match="already holds a run"):
        best.learn(100, run_dir=tmp_path / "a", progress=False)

    loaded.learn(100, run_dir=tmp_path / "a", progress=False)
    assert SAC.load(tmp_path / "a", which="last").num_steps == 500
    loaded.learn(100, run_dir=tmp_path / "fork", progress=False)  # a new directory: a fork of run a
    loaded.learn(100, run_dir=tmp_path / "fork", progress=False)  # and, trained into, its own run from then on
    assert SAC.load(tmp_path / "fork", which="last").num_steps == 700
    with pytest.raises(SoftacError, match="already holds a run"):
        loaded.learn(100, run_dir=tmp_path / "a", progress=False)  # a is no longer this agent's latest state


class _TermsEnv(DriftEnv):
    """Drift with its reward split in info, as MuJoCo envs do (plus entries that are not reward terms)."""

    def step(self, action):
        obs, reward, terminated, truncated, _ = super().step(action)
        return obs, reward, terminated, truncated, {"reward_base": 1.0, "reward_action": reward - 1.0,
                                                    "reward_flag": True, "reward_vector": np.ones(2), "x": 5.0}


def test_evaluate_reports_the_reward_terms_an_env_puts_in_info(tiny):
    agent = SAC(tiny(), env=_TermsEnv())
    stats = evaluate(agent, episodes=3)
    assert set(stats["reward_terms"]) == {"reward_action", "reward_base"}
    assert stats["reward_terms"]["reward_base"] == stats["mean_length"]  # means of sums of 1.0: exact
    # float64 sums over an episode's L steps of terms up to 4 in size (Drift: 1 - (a - 1)^2, a in [-1, 3]) are
    # within L^2 * 4 * 2^-52 of exact, L <= 3 * mean_length here; the return itself may be near 0 (no rtol)
    assert sum(stats["reward_terms"].values()) == pytest.approx(stats["mean_return"], rel=0,
                                                                abs=1e-12 * stats["mean_length"] ** 2)
    assert evaluate(SAC(tiny()), episodes=2)["reward_terms"] == {}  # an env without them


def test_reset_renews_networks_and_optimisers_and_keeps_alpha(tiny):
    agent = SAC(tiny(alpha=0.5))
    agent.learn(400, progress=False)
    before = agent.learner.state
    after = agent.learner.functions.reset(before, agent.config.seed, 3)
    fresh = agent.learner.functions.init(agent.config.seed)
    assert float(after.log_alpha) == float(before.log_alpha) != float(fresh.log_alpha)
    assert int(after.n_updates) == int(before.n_updates) > 0
    np.testing.assert_array_equal(np.asarray(after.key), np.asarray(before.key))
    for online, target in zip(jax.tree_util.tree_leaves(after.critic), jax.tree_util.tree_leaves(after.target_critic),
                              strict=True):
        np.testing.assert_array_equal(online, target)
    for moment in jax.tree_util.tree_leaves(after.actor_opt) + jax.tree_util.tree_leaves(after.critic_opt):
        assert not np.any(np.asarray(moment))  # Adam starts again (counts and moments)
    # the k-th reset draws its own weights: not the initial ones, not another reset's, not the trained ones
    w = lambda s: np.asarray(s.actor[0]["w"])  # noqa: E731
    assert not np.array_equal(w(after), w(fresh)) and not np.array_equal(w(after), w(before))
    assert not np.array_equal(w(after), w(agent.learner.functions.reset(before, agent.config.seed, 4)))
    np.testing.assert_array_equal(w(after), w(agent.learner.functions.reset(before, agent.config.seed, 3)))


@pytest.mark.parametrize("n_envs", [1, 2])
def test_resets_happen_at_each_multiple_before_total_steps_and_resume_exactly(tiny, tmp_path, n_envs):
    cfg = tiny(reset_interval=300, total_steps=900, n_envs=n_envs, eval_interval=300)

    def counting(agent):
        calls = []
        functions = agent.learner.functions
        agent.learner.functions = functions._replace(reset=lambda state, seed, k: calls.append(k) or
                                                     functions.reset(state, seed, k))
        return calls

    straight = SAC(cfg)
    calls = counting(straight)
    straight.learn(1200, progress=False)  # past total_steps: the budget becomes 1200, as the CLI's --steps makes it
    assert straight.config.total_steps == 1200 and calls == [1, 2, 3]  # and none at 1200, the end

    straight = SAC(cfg)
    straight.learn(900, run_dir=tmp_path / "straight", progress=False)
    first = SAC(cfg)
    first.learn(600, run_dir=tmp_path / "split", progress=False)  # stops exactly at a multiple
    resumed = SAC.load(tmp_path / "split", which="last")
    calls = counting(resumed)
    resumed.learn(300, run_dir=tmp_path / "split", progress=False)
    assert calls == [2]  # the reset at 600 happens after the checkpoint, in the resumed run
    assert_same_training(straight, resumed)
    evals = lambda run: (run / "eval.csv").read_text()  # noqa: E731
    assert evals(tmp_path / "straight") == evals(tmp_path / "split")


@pytest.mark.parametrize("obs_once", [False, True])
def test_assert_same_training_compares_the_whole_training_state(tiny, obs_once):
    """The resume tests' helper: two agents trained alike pass it; changing any one part of one agent's
    training state (a learner leaf, a run state field, a buffer array, the observation statistics, an env's
    state) fails it; only the fields a resumed run has of its own (run_dir, restored_from, train_time_s) may
    differ."""
    import dataclasses
    from pathlib import Path

    import jax.numpy as jnp

    from conftest import RUN_STATE_NOT_COMPARED
    from softac.run.run_state import RunState

    cfg = tiny(n_envs=2, obs_norm=True, eval_interval=100, buffer_obs_once=obs_once)
    a, b = SAC(cfg), SAC(cfg)
    for agent in (a, b):
        agent.learn(300, progress=False)
        agent.run_state.recent_returns = [1.0, 2.0]  # (learn() without a run directory leaves them empty)
    assert_same_training(a, b)

    def differs(what, change, undo):
        change()
        try:
            with pytest.raises(AssertionError):
                assert_same_training(a, b)
        except pytest.fail.Exception:
            raise AssertionError(f"assert_same_training missed a change of {what}") from None
        finally:
            undo()
        assert_same_training(a, b)  # undone

    state = b.learner.state
    leaves, treedef = jax.tree_util.tree_flatten(state)
    for i, leaf in enumerate(leaves):
        changed = [*leaves[:i], jnp.asarray(leaf) + jnp.ones((), leaf.dtype), *leaves[i + 1:]]
        differs(f"learner leaf {i}", lambda c=changed: setattr(b.learner, "state", treedef.unflatten(c)),
                lambda: setattr(b.learner, "state", state))

    for f in dataclasses.fields(RunState):
        value = getattr(b.run_state, f.name)
        if f.name == "rng":
            saved = value.bit_generator.state
            differs("rng", lambda: b.run_state.rng.random(),
                    lambda s=saved: setattr(b.run_state.rng.bit_generator, "state", s))
            continue
        if f.name.endswith("_key"):
            other = jnp.asarray(np.asarray(value) ^ np.uint32(1))
        elif isinstance(value, list):
            other = [*value, 3.0]
        elif isinstance(value, Path) or value is None:
            other = Path("elsewhere")
        else:
            other = value + 1
        if f.name in RUN_STATE_NOT_COMPARED:
            setattr(b.run_state, f.name, other)
            assert_same_training(a, b)  # a resumed run's own: not compared
            setattr(b.run_state, f.name, value)
        else:
            differs(f.name, lambda n=f.name, o=other: setattr(b.run_state, n, o),
                    lambda n=f.name, v=value: setattr(b.run_state, n, v))

    for name, array in b.collector.buffer.state_dict().items():
        if name == "pos_size":
            differs("buffer position", lambda: setattr(b.collector.buffer, "pos", b.collector.buffer.pos + 1),
                    lambda p=b.collector.buffer.pos: setattr(b.collector.buffer, "pos", p))
            continue
        old = array.flat[-1].copy()  # a view of the buffer's array
        new = ~old if array.dtype == bool else old + 1
        differs(f"buffer {name}", lambda a_=array, n=new: a_.flat.__setitem__(-1, n),
                lambda a_=array, o=old: a_.flat.__setitem__(-1, o))

    norm = b.learner.obs_norm
    differs("obs_norm count", lambda: setattr(norm, "count", norm.count + 1),
            lambda c=norm.count: setattr(norm, "count", c))
    for name in ("mean", "m2"):
        differs(f"obs_norm {name}", lambda n=name: setattr(norm, n, getattr(norm, n) + 1.0),
                lambda n=name, v=getattr(norm, name): setattr(norm, n, v))

    pool = b.collector.pool
    for name in ("obs", "episode_return", "episode_length", "resets"):
        array = getattr(pool, name)
        differs(f"envs {name}", lambda a_=array: a_.__setitem__(1, a_[1] + 1),
                lambda a_=array, saved=array[1].copy(): a_.__setitem__(1, saved))  # (x + 1) - 1 rounds
    env = pool.envs[1]
    differs("an env's physics", lambda: setattr(env.unwrapped, "x", env.unwrapped.x + 0.5),
            lambda x=env.unwrapped.x: setattr(env.unwrapped, "x", x))
    saved = env.unwrapped.np_random.bit_generator.state
    differs("an env's random stream", lambda: env.unwrapped.np_random.random(),
            lambda: setattr(env.unwrapped.np_random.bit_generator, "state", saved))
    limit = env
    while not hasattr(limit, "_elapsed_steps"):
        limit = limit.env
    differs("an env's time limit", lambda: setattr(limit, "_elapsed_steps", limit._elapsed_steps + 1),
            lambda s=limit._elapsed_steps: setattr(limit, "_elapsed_steps", s))


def test_loading_into_an_env_with_other_action_bounds_is_refused_unless_asked(tiny, tmp_path):
    """Sizes alone used to be checked: a policy trained on [-1, 3] silently acted on [-2, 0.5]."""
    from softac.run.checkpoint import CheckpointError

    agent = SAC(tiny())
    agent.learn(300, progress=False)
    agent.save(tmp_path / "agent")
    with pytest.raises(CheckpointError, match=r"action bounds low \[-1.\], high \[3.\], but the env has low \[-2.\]"):
        SAC.load(tmp_path / "agent", env=DriftEnv(low=-2.0, high=0.5))
    SAC.load(tmp_path / "agent", env=DriftEnv())  # the same bounds: fine

    moved = SAC.load(tmp_path / "agent", env=DriftEnv(low=-2.0, high=0.5), allow_new_bounds=True)
    obs = np.random.default_rng(0).normal(scale=5.0, size=(64, 2)).astype(np.float32)
    actions = moved.predict(obs)
    assert actions.min() >= -2.0 and actions.max() <= 0.5
    # the same policy, scaled to the new bounds: a few float32 roundings of values below 4 in magnitude apart
    np.testing.assert_allclose(moved.learner.scaler.to_normalised(actions), agent.learner.scaler.to_normalised(agent.predict(obs)),
                               rtol=0, atol=1e-6)


def test_learning_past_total_steps_raises_the_runs_budget_as_one_longer_run(tiny, tmp_path):
    """learn(n) past config.total_steps kept the old total in the run's checkpoint, config.yaml and
    summary.json, so a later resume to the budget trained nothing; the CLI's --steps raised it."""
    straight = SAC(tiny(total_steps=500, eval_interval=100))
    straight.learn(500, run_dir=tmp_path / "straight", progress=False)
    split = SAC(tiny(total_steps=300, eval_interval=100))
    split.learn(300, run_dir=tmp_path / "split", progress=False)
    assert split.config.total_steps == 300
    resumed = SAC.load(tmp_path / "split", which="last")
    resumed.learn(200, run_dir=tmp_path / "split", progress=False)
    assert resumed.config.total_steps == 500
    summary = json.loads((tmp_path / "split" / "summary.json").read_text())
    assert summary["steps"] == summary["total_steps"] == 500
    assert "total_steps: 500" in (tmp_path / "split" / "config.yaml").read_text()
    assert SAC.load(tmp_path / "split", which="last").config.total_steps == 500
    assert_same_training(straight, resumed)
    steps = lambda run: [int(row["step"]) for row in read_csv(run / "eval.csv")]  # noqa: E731
    assert steps(tmp_path / "split") == steps(tmp_path / "straight") == [100, 200, 300, 400, 500]
    given = split.config
    split.learn(100, progress=False)
    assert split.config.total_steps == 400  # without a run directory, too
    assert given.total_steps == 300 and split.learner.config is split.collector.config is split.config
    with pytest.raises(SoftacError):  # another run's directory: refused before training, the budget as it was
        split.learn(1000, run_dir=tmp_path / "straight", progress=False)
    assert split.config.total_steps == 400


def test_the_config_is_never_changed_in_place():
    """SACConfig is frozen (issue 65): a run that raises its budget gets a new config; the one a user holds,
    shares between agents or reuses in a sweep stays what it was."""
    import dataclasses

    from softac import SACConfig

    config = SACConfig()
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.total_steps = 5
    assert config.replace(total_steps=5).total_steps == 5 and config.total_steps == SACConfig().total_steps


def test_learning_in_two_calls_keeps_the_recent_returns_between_them(tiny):
    """Without a run directory the recent returns (progress's return_mean, summary, save()) were dropped
    between learn() calls: a second call started its mean afresh and save() stored none."""
    once, twice = SAC(tiny()), SAC(tiny())
    whole = once.learn(600, progress=False)
    twice.learn(300, progress=False)
    assert twice.run_state.recent_returns  # kept after the first call
    split = twice.learn(300, progress=False)
    assert split["recent_return_mean"] == whole["recent_return_mean"]
    assert twice.run_state.recent_returns == once.run_state.recent_returns and len(once.run_state.recent_returns) == 20


def test_the_parts_train_without_the_agent_as_the_agent_trains_them(tiny, tmp_path):
    """Data flows one way: a learner, a collector and a run state, made and trained by hand with the loop,
    end where SAC.learn ends, bit for bit, and their checkpoint loads as an agent."""
    from softac.run import checkpoint
    from softac.run import checkpoint_contents as snapshot
    from softac.replay.collector import Collector
    from softac.envs.make import check_spaces, make_env
    from softac.learner.learner import Learner
    from softac.run.loop import train
    from softac.run.run_state import RunState

    cfg = tiny(obs_norm=True, n_envs=2)
    agent = SAC(cfg)
    agent.learn(600, progress=False)

    env = make_env(cfg.env_id)
    spaces = check_spaces(env)
    env.close()
    learner, collector, run_state = Learner(cfg, spaces), Collector(cfg, cfg.env_id, spaces), RunState.new(cfg.seed)
    summary = train(learner, collector, run_state, 600, progress=False)
    assert summary["steps"] == run_state.num_steps == 600

    class Parts:  # what assert_same_training reads of an agent
        pass

    parts = Parts()
    parts.learner, parts.collector, parts.run_state = learner, collector, run_state
    assert_same_training(agent, parts)

    checkpoint.save(tmp_path / "parts", *snapshot.checkpoint_parts(learner, run_state, collector, include_buffer=True))
    loaded = SAC.load(tmp_path / "parts")
    obs = np.linspace(-1.0, 1.0, 8, dtype=np.float32).reshape(4, 2)
    np.testing.assert_array_equal(loaded.predict(obs), agent.predict(obs))
    assert loaded.num_steps == 600 and len(loaded.collector.buffer) == 600


def test_load_replaces_only_the_settings_that_do_not_change_what_is_computed(tiny, tmp_path):
    from softac.errors import SoftacError

    agent = SAC(tiny(loggers="tensorboard"))
    agent.learn(300, run_dir=tmp_path / "run", progress=False)
    loaded = SAC.load(tmp_path / "run", which="last", loggers="none", env_workers=1, device="cpu")
    assert (loaded.config.loggers, loaded.config.env_workers) == ("none", 1)
    assert loaded.config.replace(loggers="tensorboard", env_workers=0) == agent.config
    assert loaded.learner.config == loaded.collector.config == loaded.config  # one config for every part
    with pytest.raises(SoftacError, match="loggers"):
        SAC.load(tmp_path / "run", loggers="tensorboard,wandbb")


def test_random_action_prob_replaces_that_share_of_actions_by_uniform_ones():
    """mix_in_random_actions: about PROB of the rows become uniform in [-1, 1], the others stay as they were
    (bounds: 5 binomial standard deviations), and the generator advances the same whichever rows it picks."""
    from softac.replay.exploration import mix_in_random_actions

    n, prob = 20000, 0.3
    policy = np.full((n, 3), 0.25, np.float32)
    mixed = mix_in_random_actions(np.random.default_rng(0), policy, prob)
    replaced = np.any(mixed != 0.25, axis=1)
    assert abs(replaced.sum() - n * prob) < 5 * np.sqrt(n * prob * (1 - prob))
    uniform = mixed[replaced]
    assert uniform.min() >= -1.0 and uniform.max() <= 1.0
    assert abs(uniform.mean()) < 5 * np.sqrt(1 / 3 / uniform.size) and abs(uniform.var() - 1 / 3) < 0.02
    a, b = np.random.default_rng(1), np.random.default_rng(1)
    mix_in_random_actions(a, policy, 0.0), mix_in_random_actions(b, policy, 1.0)
    assert a.random() == b.random()
    np.testing.assert_array_equal(mix_in_random_actions(np.random.default_rng(2), policy, 0.0), policy)


def test_random_action_prob_1_makes_every_training_action_uniform(tiny):
    """With random_action_prob 1 every training action after learning_starts is uniform: the buffer's actions
    spread over [-1, 1] as uniform ones do (the policy's own, at 0, have about half that variance here)."""
    agent = SAC(tiny(random_action_prob=1.0, learning_starts=100))
    agent.learn(1500, progress=False)
    actions = agent.collector.buffer.actions[600:1500]
    assert abs(actions.mean()) < 0.15 and abs(actions.var() - 1 / 3) < 0.08
    with pytest.raises(SoftacError, match="random_action_prob"):
        tiny(random_action_prob=1.5).validate()


def test_near_the_memory_map_limit_building_an_agent_drops_jaxs_programs_and_a_live_agent_trains_on(
        tmp_path, tiny, monkeypatch):
    """XLA maps each compiled program's code into regions of its own; past vm.max_map_count a process can compile
    nothing more and dies (softac.base.device.release_compiled_programs_near_map_limit). Building an agent with
    half the limit used drops JAX's compiled programs first; an agent built before recompiles and trains on."""
    import jax.numpy as jnp

    from softac.base import device

    agent = SAC(tiny(learning_starts=50))
    agent.learn(100, run_dir=tmp_path / "run", progress=False)
    probe = jax.jit(lambda x: x * 2.5 + 1.0)
    probe(jnp.ones(3))
    assert device.memory_map_count() > 0 and device.max_map_count() > 0
    assert not device.release_compiled_programs_near_map_limit(fraction=1e9)  # far from it: kept
    assert probe._cache_size() == 1
    monkeypatch.setattr(device, "max_map_count", lambda: 2)  # every process holds more than one mapping
    SAC(tiny(learning_starts=50))
    assert probe._cache_size() == 0
    agent.learn(100, run_dir=tmp_path / "run", progress=False)
    assert agent.num_steps == 200 and int(read_csv(tmp_path / "run" / "progress.csv")[-1]["step"]) == 200
