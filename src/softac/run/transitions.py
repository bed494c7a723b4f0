"""Where a run's transitions come from and how they reach the learner, a chunk of env steps at a time: the
training loop's one seam for its sources (issue 65). The loop calls `chunk()` until its budget is spent and
does the host's work between chunks (log rows, evaluations, checkpoints, callbacks, progress); a source does
the env steps, the replay writes and the gradient steps of each chunk.

The host's source (here): envs stepped on the host one vector step at a time (the collector's pool and its
NumPy buffer), so a chunk is one vector-env step and its `gradient_steps` updates. The device's
(softac.run.device_transitions, issue 67; the loop picks it for a DeviceCollector): envs stepped inside the
update's jit, many vector steps a chunk, reported the same way. The host's work then falls at chunk ends: a log
row, evaluation or checkpoint at the end of the chunk that crosses its interval, periodic resets before the
chunk after it, a callback's on_step once a chunk, and each episode logged at the step it ended.
"""

from __future__ import annotations

from typing import NamedTuple

from softac.envs.make import Episode
from softac.learner.learner import Learner
from softac.replay.collector import Collector
from softac.replay.exploration import Explorer
from softac.replay.offline import OfflineData
from softac.run.run_state import RunState


def count_offline_observations(learner: Learner, offline: OfflineData | None, run_state: RunState) -> None:
    """A fresh run's obs_norm counts its offline dataset's observations before its first step, so that the
    dataset's rows and the env's are normalised alike from the first update (issue 68)."""
    norm = learner.obs_norm
    if offline is not None and norm is not None and norm.count == 0 and run_state.num_steps == 0:
        learner.observe(offline.obs)


class Chunk(NamedTuple):
    before: int  # the run's env steps before the chunk
    after: int  # and after it
    finished: list[Episode]  # the training episodes that ended in it


class HostTransitions:
    """Envs on the host: each chunk one vector-env step (the explorer's actions, the envs stepped, the
    transitions stored), then its gradient steps in one jitted update once learning has started."""

    def __init__(self, learner: Learner, collector: Collector, run_state: RunState) -> None:
        self.learner, self.collector, self.run_state = learner, collector, run_state
        self.explorer = Explorer(learner, run_state)

    def start(self) -> None:
        """Envs ready to step from the run's current step (fresh, or as a checkpoint left them). A fresh run with
        offline_data counts the dataset's observations in obs_norm's statistics first, so that its rows and the
        env's are normalised alike from the first update (issue 68)."""
        self.collector.start(self.run_state.num_steps)
        count_offline_observations(self.learner, self.collector.offline, self.run_state)

    def chunk(self, until: int) -> Chunk:
        """One vector step (`until`, the budget's end, is the device source's bound; one step never passes it)."""
        learner, rs = self.learner, self.run_state
        before, obs = rs.num_steps, self.collector.obs
        learner.observe(obs)  # every observation the policy acts on, warm-up included (obs_norm)
        actions, env_actions = self.explorer.actions(obs, before)
        result = self.collector.step(obs, actions, env_actions, before)
        learner.observe_rewards(result.rewards, result.terminated | result.truncated)  # reward_scale
        rs.num_steps = after = before + learner.config.n_envs
        for episode in result.finished:
            self.explorer.episode_ended(episode.env)
        self.learn(after)
        return Chunk(before, after, result.finished)

    def learn(self, after: int) -> None:
        """`gradient_steps` updates in one jitted call, once learning has started."""
        cfg = self.learner.config
        if after >= cfg.learning_starts and cfg.gradient_steps > 0 and self.collector.can_sample():
            batch = self.collector.sample(self.run_state.rng, cfg.batch_size, cfg.gradient_steps)
            self.learner.update(batch, after)

