"""The seams issue 65 left for the next capabilities: the training loop takes its transitions from a source, a
chunk at a time (run/transitions.py), so a source that runs many env steps a chunk (issue 67's device envs)
plugs into the one loop; the action choice is the explorer's; an env family is a module and a row of
envs/families.py."""

import gymnasium as gym
import numpy as np
import pytest

from conftest import assert_same_learner, assert_same_run_state


class ChunksOf:
    """A source that runs `n` of the host source's vector steps a chunk and reports them as one, as a source
    stepping envs inside the update's jit would."""

    def __init__(self, host, n: int):
        self.host, self.n = host, n

    def start(self):
        self.host.start()

    def chunk(self, until: int):
        from softac.run.transitions import Chunk

        parts = [self.host.chunk(until) for _ in range(self.n)]
        return Chunk(parts[0].before, parts[-1].after, [e for part in parts for e in part.finished])


def learn_in_chunks(agent, steps: int, n: int, run_dir=None) -> dict:
    """`agent.learn(steps, run_dir)` with the loop's source replaced by one of `n`-step chunks."""
    from softac.run.loop import TrainingLoop

    loop = TrainingLoop(agent.learner, agent.collector, agent.run_state, steps, run_dir=run_dir, progress=False,
                        agent=agent)
    loop.source = ChunksOf(loop.source, n)
    try:
        return loop.run()
    finally:
        agent.collector.close_workers()


def test_a_source_that_runs_many_env_steps_a_chunk_plugs_into_the_one_loop(tiny, tmp_path):
    """The loop with a source of 5-step chunks trains exactly as with the host's one-step chunks (the same
    learner state, run state and episodes), and writes the same log rows and evaluations (its intervals are
    multiples of 5): the loop does the host's work between chunks, whatever a chunk holds."""
    from softac import SAC
    from softac.run.csv_logs import read_csv

    config = tiny(eval_interval=250, log_interval=50)
    plain, chunked = SAC(config), SAC(config)
    plain.learn(500, run_dir=tmp_path / "plain", progress=False)
    summary = learn_in_chunks(chunked, 500, 5, run_dir=tmp_path / "chunked")
    assert summary["stop_reason"] == "steps" and chunked.num_steps == 500
    assert_same_learner(plain, chunked)
    assert_same_run_state(plain, chunked)
    for name in ("progress.csv", "eval.csv"):  # every row and value but the clock's
        a, b = (read_csv(tmp_path / run / name) for run in ("plain", "chunked"))
        clockless = [[{k: v for k, v in row.items() if k not in ("time_s", "fps")} for row in rows] for rows in (a, b)]
        assert clockless[0] == clockless[1] and len(a) > 1, name
    # the same episodes, each logged at the end of the chunk it ended in
    a, b = (read_csv(tmp_path / run / "episodes.csv") for run in ("plain", "chunked"))
    assert [(r["return"], r["length"]) for r in a] == [(r["return"], r["length"]) for r in b] and len(a) > 3
    assert [int(r["step"]) for r in b] == [-(-int(r["step"]) // 5) * 5 for r in a]


def test_periodic_resets_follow_chunks_that_cross_their_interval(tiny):
    """reset_interval with chunks that do not divide it: one reset before the first chunk past each multiple,
    none skipped (7-step chunks cross 100 in the chunk 98 -> 105), and the host's one-step chunks reset at the
    first step past each multiple as before."""
    from softac import SAC

    for n, expected in ((7, [(105, 1), (203, 2)]), (1, [(100, 1), (200, 2)])):
        agent = SAC(tiny(reset_interval=100, total_steps=1000))
        resets = []
        reset = agent.learner.reset_networks
        agent.learner.reset_networks = lambda seed, k: (resets.append((agent.num_steps, k)), reset(seed, k))
        learn_in_chunks(agent, 245, n)
        assert resets == expected, (n, resets)


class _Policy:
    """What the explorer asks of a learner: its config, spaces, scaler and the two ways to act."""

    def __init__(self, config, actions):
        from softac.learner.policy import ActionScaler

        self.config, self.actions, self.calls = config, actions, 0
        self.spaces = type("Spaces", (), {"act_dim": actions.shape[1]})()
        self.scaler = ActionScaler(np.full(actions.shape[1], -2.0), np.full(actions.shape[1], 2.0))

    def act(self, obs, key):
        self.calls += 1
        return self.actions, self.scaler.to_env(self.actions), key + 1


def test_the_explorer_chooses_warm_up_policy_and_random_actions_and_refuses_non_finite_ones(tiny):
    from softac.errors import RunFailed
    from softac.replay.exploration import Explorer
    from softac.run.run_state import RunState

    config = tiny(learning_starts=10, n_envs=2)
    actions = np.array([[0.5], [-0.25]], np.float32)
    policy, streams = _Policy(config, actions), RunState.new(0)
    explorer = Explorer(policy, streams)
    warm, warm_env = explorer.actions(np.zeros((2, 3)), step=8)  # before learning_starts: uniform, no policy call
    assert policy.calls == 0 and warm.shape == (2, 1) and np.all(np.abs(warm) <= 1)
    np.testing.assert_allclose(warm_env, 2.0 * warm, rtol=1e-6)
    key = streams.act_key
    chosen, chosen_env = explorer.actions(np.zeros((2, 3)), step=10)
    assert policy.calls == 1 and np.array_equal(chosen, actions) and np.all(streams.act_key == key + 1)
    np.testing.assert_allclose(chosen_env, 2.0 * actions)

    policy.config = config.replace(random_action_prob=1.0)  # every row uniform again, in bounds
    mixed, mixed_env = explorer.actions(np.zeros((2, 3)), step=12)
    assert not np.array_equal(mixed, actions) and np.all(np.abs(mixed) <= 1)
    np.testing.assert_allclose(mixed_env, 2.0 * mixed, rtol=1e-6)

    policy.config = config  # random_action_prob 0: the run's NumPy stream is left alone after warm-up
    rng_state = streams.rng.bit_generator.state
    explorer.actions(np.zeros((2, 3)), step=13)
    assert streams.rng.bit_generator.state == rng_state

    policy.actions = np.array([[np.nan], [0.0]], np.float32)
    with pytest.raises(RunFailed, match="training diverged at step 14: the policy produced non-finite actions"):
        explorer.actions(np.zeros((2, 3)), step=14)

    policy.actions, policy.config = actions, config.replace(warmup_actions="policy")  # Brax's prefill
    rng_state = streams.rng.bit_generator.state
    warm_policy, _ = explorer.actions(np.zeros((2, 3)), step=0)
    assert policy.calls == 5 and np.array_equal(warm_policy, actions) and streams.rng.bit_generator.state == rng_state


def test_the_explorer_acts_through_the_runs_noise_and_restarts_an_ended_episodes_sequence(tiny):
    """With pink noise the policy acts on the noise sequence's next values (not the act key), and an env whose
    episode ended starts a fresh sequence."""
    from softac.replay.exploration import ColoredNoise, Explorer
    from softac.run.run_state import RunState

    config = tiny(learning_starts=0, n_envs=2)
    policy = _Policy(config, np.zeros((2, 1), np.float32))
    seen = []
    policy.act_with_noise = lambda obs, noise: (seen.append(noise.copy()), (np.tanh(noise), 2 * np.tanh(noise)))[1]
    noise = ColoredNoise(1.0, 2, 1, 16, seed=0)
    streams = RunState.new(0, noise)
    key = np.asarray(streams.act_key).copy()
    explorer = Explorer(policy, streams)
    first = noise.sequences[:, :, :2].copy()
    for step in range(2):
        actions, _ = explorer.actions(np.zeros((2, 3)), step)
        np.testing.assert_array_equal(seen[step], first[:, :, step].astype(np.float32))  # the sequence's values
        np.testing.assert_array_equal(actions, np.tanh(seen[step]))
    assert policy.calls == 0 and np.array_equal(np.asarray(streams.act_key), key)  # the key is not drawn from
    explorer.episode_ended(1)
    assert noise.position.tolist() == [2, 0] and not np.array_equal(noise.sequences[1, :, :2], first[1])


def test_env_ids_find_their_family():
    from softac.envs import families

    ids = ("dmc:cheetah-run", "dm_control/walker-walk-v0", "FetchPush-v4", "Hopper-v5", "mymodule:Thing-v0",
           "FetchEnvs:MyArm-v0")  # a user's module named like Gymnasium-Robotics' ids is still imported first
    assert [families.family_of(i).name for i in ids] == ["dmc", "dmc", "robotics", "gymnasium", "gymnasium",
                                                         "gymnasium"]
    assert families.family_of_entry_point("gymnasium_robotics.envs.fetch.push:MujocoFetchPushEnv").name == "robotics"
    assert families.family_of_entry_point("gymnasium.envs.mujoco.hopper_v5:HopperEnv") is None  # no row claims it
    assert families.renders_at_size("gymnasium.envs.mujoco.hopper_v5:HopperEnv")
    assert families.renders_at_size("softac.envs.dmc:make_suite_env")
    assert not families.renders_at_size("gymnasium.envs.classic_control.pendulum:PendulumEnv")


def test_a_family_is_a_module_and_one_row(monkeypatch):
    """A family added as one row (here a toy one whose `toy:NAME` ids register on first use, and whose envs
    cannot be made while its `problem` says why) is resolved, made and refused through the row alone."""
    from softac.envs import families
    from softac.envs.make import make_env, resolve_env_id
    from softac.errors import EnvError

    def resolve(env_id: str) -> str:
        name = f"Toy{env_id.removeprefix('toy:').capitalize()}-v0"
        if name not in gym.registry:
            gym.register(name, entry_point="toy_family_test:make")
        return name

    problem = {"why": None}
    toy = families.EnvFamily("toy", owns=lambda env_id: env_id.startswith("toy:"), resolve=resolve,
                             problem=lambda: problem["why"], entry_points=("toy_family_test",))
    monkeypatch.setattr(families, "FAMILIES", (toy, *families.FAMILIES))
    monkeypatch.setitem(__import__("sys").modules, "toy_family_test",
                        type("M", (), {"make": staticmethod(lambda **kw: gym.make("Pendulum-v1").unwrapped)}))
    try:
        assert resolve_env_id("toy:swing") == "ToySwing-v0"
        assert make_env("toy:swing").action_space.shape == (1,)
        gym.registry["ToyBroken-v0"] = gym.envs.registration.EnvSpec("ToyBroken-v0",
                                                                      entry_point="toy_family_test:nothing")
        problem["why"] = "toy envs need toy-sim 2: pip install toy-sim"
        with pytest.raises(EnvError, match="cannot make env 'ToyBroken-v0': toy envs need toy-sim 2"):
            make_env("toy:broken")
    finally:
        for name in ("ToySwing-v0", "ToyBroken-v0"):
            gym.registry.pop(name, None)
