"""The device's source of transitions (issue 67), the training loop's other source beside the host's
(softac.run.transitions): a chunk is many vector steps of N envs in one jitted `lax.scan`, each step the policy's
actions (uniform ones before learning_starts, unless warmup_actions is policy), the envs stepped and auto-reset (softac.envs.device_envs), the
transitions written into the device's replay buffer and `gradient_steps` updates on batches drawn from it, as
Brax's SAC training step fuses them. The host sees the chunk's end only: the episodes that ended in it (each at
its own step), for the loop's logs, evaluations, checkpoints and callbacks. Evaluation runs its episodes at once on
device envs of its own (`device_episodes`).

Each vector step follows the host's rules: uniform actions while the steps before it are under learning_starts,
updates once the steps after it reach it, a linear learning-rate schedule at the steps after it. A chunk spans
the shortest of the log, eval and checkpoint intervals (so each interval's work falls at the chunk that crosses
it, as with the host's one-step chunks) or what is left of the budget: one compiled program of that many steps
per run setting, shared by every agent of the process, its steps past the budget skipped, so that a run split
anywhere and resumed computes what a straight one does.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from softac.envs.make import Episode
from softac.learner.learner import Learner
from softac.replay.device_collector import DeviceCollector
from softac.replay.offline import offline_rows
from softac.run.run_state import RunState
from softac.run.transitions import Chunk, count_offline_observations

MAX_CHUNK = 1000  # vector steps in one call at most: the host comes back for the progress bar and Ctrl-C


def chunk_length(config: Any) -> int:
    """Vector steps per chunk: the shortest positive interval of host work, in vector steps, at most MAX_CHUNK."""
    intervals = [i for i in (config.log_interval, config.eval_interval, config.checkpoint_interval) if i > 0]
    return max(1, min([MAX_CHUNK] + [i // config.n_envs for i in intervals]))


class ChunkSpec(NamedTuple):
    """What shapes a chunk's program (a static argument: equal specs share it)."""
    program: Any  # learner.build.Program: the update's settings
    policy: Any  # learner.policy.Policy
    envs: Any  # envs.device_envs.DeviceEnvs
    act_dim: int
    gradient_steps: int
    batch_size: int
    learning_starts: int
    uniform_warmup: bool  # warmup_actions uniform: uniform actions before learning_starts (else the policy's)
    random_action_prob: float  # > 0: that share of the rows uniform (each env, each step), as the host's Explorer
    linear_lr: bool
    length: int  # vector steps
    obs_clip: float  # > 0: obs_norm's clip, the observations normalised by running statistics; 0: raw
    reward_scale: str  # off, std or std_max (learner.normalization.RunningReturnScale), with:
    gamma: float
    v_max: float
    n_step: int  # > 1: n-step returns drawn from the replay (device_buffer.n_step_rows)
    offline_rows: int  # > 0: each batch's rows drawn from the offline dataset (offline_data, mix; issue 68)
    noise: tuple  # the exploration noise's settings: ("repeat", mu, largest), FlashSAC's held noise; ("pink", beta,
    # length), coloured sequences; ("gsde", sample_freq), gSDE's exploration matrices; (): white noise


class DeviceTransitions:
    """N envs on the device, their replay and the updates, a chunk of vector steps per jitted call."""

    def __init__(self, learner: Learner, collector: DeviceCollector, run_state: RunState) -> None:
        from softac.learner.build import Program, numbers_of

        self.learner, self.collector, self.run_state = learner, collector, run_state
        cfg, settings = learner.config, learner.functions.settings
        mixed = offline_rows(cfg.batch_size, cfg.offline_fraction) if cfg.mixes_offline_data else 0
        self.spec = ChunkSpec(Program(settings), settings.policy, collector.envs, learner.spaces.act_dim,
                              cfg.gradient_steps, cfg.batch_size, cfg.learning_starts,
                              cfg.warmup_actions == "uniform", float(cfg.random_action_prob), cfg.lr_schedule == "linear",
                              chunk_length(cfg), float(cfg.obs_norm_clip) if cfg.obs_norm else 0.0,
                              cfg.reward_scale, float(cfg.gamma), float(cfg.v_max), int(cfg.n_step), mixed,
                              noise_settings(cfg))
        self.numbers = numbers_of(settings)

    def start(self) -> None:
        self.collector.start(self.run_state.num_steps)
        count_offline_observations(self.learner, self.collector.offline, self.run_state)

    def episodes(self, episodes: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """Evaluation's episodes on the device (`device_episodes`): their returns and lengths."""
        return device_episodes(self.learner, self.collector, episodes, seed)

    def chunk(self, until: int) -> Chunk:
        """The chunk's vector steps, or fewer where `until` (the budget's end, in env steps) comes first."""
        import jax.numpy as jnp

        from softac.learner.metrics import zero_totals

        learner, collector, rs, cfg = self.learner, self.collector, self.run_state, self.learner.config
        n, before = cfg.n_envs, rs.num_steps
        count = max(1, min(self.spec.length, -(-(until - before) // n)))
        totals = learner.totals if learner.totals is not None else zero_totals()
        carry = (learner.state, totals, collector.replay, collector.batch, collector.key, obs_stats(learner),
                 return_stats(learner), noise_state(rs.noise))
        schedule = (jnp.float32(max(cfg.total_steps, 1)), jnp.float32(cfg.lr_end_fraction))
        offline = collector.offline_device if self.spec.offline_rows else ()
        carry, (returns, lengths) = compiled_chunk(self.spec, self.numbers, carry, jnp.int32(before),
                                                   jnp.int32(count), schedule, offline)
        learner.state, learner.totals, collector.replay, collector.batch, collector.key, *statistics = carry
        stats, return_scale, noise = statistics
        keep_obs_stats(learner, stats)
        keep_return_stats(learner, return_scale)
        keep_noise_state(rs.noise, noise)
        rs.num_steps = after = before + count * n
        return Chunk(before, after, finished_episodes(np.asarray(lengths)[:count], np.asarray(returns)[:count],
                                                      before, n))


class EvalSpec(NamedTuple):
    """What shapes an evaluation's program: the policy, the env, how many episodes at once and their length."""
    policy: Any
    env: Any  # the env object (DeviceEnvs hashes it by identity)
    episodes: int
    episode_length: int
    action_repeat: int
    obs_clip: float  # as ChunkSpec's


def device_episodes(learner: Learner, collector: DeviceCollector, episodes: int, seed: int,
                    policy: str = "deployed") -> tuple[np.ndarray, np.ndarray]:
    """The returns and lengths of `episodes` deterministic episodes of `policy` (Learner.policy_networks) run at
    once, each on its own device env, in one jitted scan of the episode length (softac.run.evaluation.summarize
    makes the host's statistics of them); each evaluation starts from the same states, drawn from `seed`."""
    import jax

    envs = collector.envs
    spec = EvalSpec(learner.functions.policy, envs.env, episodes, envs.episode_length, envs.action_repeat,
                    float(learner.config.obs_norm_clip) if learner.obs_norm is not None else 0.0)
    returns, lengths = compiled_evaluation(spec, learner.policy_networks(policy), obs_stats(learner),
                                           jax.random.PRNGKey(seed))
    return np.asarray(returns, np.float64), np.asarray(lengths)


def evaluation_program(spec: EvalSpec, networks: tuple, stats: tuple, key: Any) -> tuple[Any, Any]:
    """Returns and lengths of `spec.episodes` episodes, one per env, each counted until it first ends."""
    import jax
    import jax.numpy as jnp

    from softac.envs.device_envs import DeviceEnvs
    from softac.learner.pixels import features_of

    actor, actor_stats, encoder = networks
    envs = DeviceEnvs(spec.env, spec.episodes, spec.episode_length, spec.action_repeat)

    def step(carry, _):
        batch, returns, lengths, running = carry
        obs = normalized(stats, batch.obs, spec.obs_clip)  # frozen: evaluation does not count its observations
        actions = spec.policy.deterministic(actor, actor_stats, features_of(encoder, obs))
        batch, s = envs.step(batch, actions)
        returns = returns + jnp.where(running, s.rewards, 0.0)
        lengths = lengths + running.astype(jnp.int32)
        return (batch, returns, lengths, running & ~(s.terminated | s.truncated)), None

    zeros = jnp.zeros(spec.episodes, jnp.float32)
    carry = (envs.reset(key), zeros, zeros.astype(jnp.int32), jnp.ones(spec.episodes, bool))
    (_, returns, lengths, _), _ = jax.lax.scan(step, carry, None, length=spec.episode_length)
    return returns, lengths


def moments(norm: Any) -> tuple:
    """A RunningObsNorm's (count, mean, m2) as the chunk carries them (float32)."""
    import jax.numpy as jnp

    return jnp.int32(norm.count), jnp.asarray(norm.mean, jnp.float32), jnp.asarray(norm.m2, jnp.float32)


def keep_moments(norm: Any, carried: tuple) -> None:
    """The chunk's (count, mean, m2) back into a RunningObsNorm (float64, as it keeps them)."""
    count, mean, m2 = carried
    norm.count, norm.mean, norm.m2 = int(count), np.asarray(mean, np.float64), np.asarray(m2, np.float64)


def obs_stats(learner: Learner) -> tuple:
    """obs_norm's running statistics (count, mean, m2) as the chunk carries them, or () without."""
    return () if learner.obs_norm is None else moments(learner.obs_norm)


def keep_obs_stats(learner: Learner, stats: tuple) -> None:
    """The chunk's statistics back into the learner's obs_norm (what evaluation, predict and checkpoints use)."""
    if stats:
        keep_moments(learner.obs_norm, stats)


def return_stats(learner: Learner) -> tuple:
    """reward_scale's running return per env and the statistics of all returns seen (returns, count, mean, m2,
    max |G|) as the chunk carries them (float32), or () without."""
    import jax.numpy as jnp

    scale = learner.return_scale
    if scale is None:
        return ()
    return (jnp.asarray(scale.returns, jnp.float32), *moments(scale.stats), jnp.float32(scale.max_abs))


def keep_return_stats(learner: Learner, carried: tuple) -> None:
    """The chunk's return statistics back into the learner's RunningReturnScale (what checkpoints save)."""
    if carried:
        returns, *stats, max_abs = carried
        scale = learner.return_scale
        scale.returns, scale.max_abs = np.asarray(returns, np.float64), float(max_abs)
        keep_moments(scale.stats, tuple(stats))


def noise_settings(config: Any) -> tuple:
    """ChunkSpec.noise: the config's exploration noise as the chunk's program runs it."""
    kind = config.exploration_noise
    if kind == "repeat":
        return kind, float(config.noise_repeat_mu), int(config.noise_repeat_max)
    if kind == "pink":
        return kind, float(config.noise_beta), int(config.noise_sequence_length)
    if kind == "gsde":
        return kind, int(config.sde_sample_freq)
    return ()


def noise_state(noise: Any) -> tuple:
    """The exploration noise's state as the chunk carries it (the noise object's `chunk_state`: repeat's held
    noise, its use count and hold; pink's sequences and positions; gSDE's matrices and the steps since their draw),
    or () for white noise. It lives in the run state's noise object between chunks (checkpointed with it); the
    device draws from its own key, not the host's stream."""
    import jax.numpy as jnp

    return () if noise is None else tuple(jnp.asarray(v) for v in noise.chunk_state())


def keep_noise_state(noise: Any, carried: tuple) -> None:
    """The chunk's noise state back into the run state's noise object (what checkpoints save)."""
    if noise is not None:
        noise.keep_chunk_state(tuple(np.asarray(v) for v in carried))


def next_noise(state: tuple, key: Any, noise: tuple) -> tuple[tuple, Any]:
    """The exploration noise's next values (the policy's with_noise takes them) and its state after, for
    ChunkSpec.noise's kind, as the host's RepeatedNoise, ColoredNoise and SdeNoise `next()` give them."""
    kind = noise[0]
    if kind == "repeat":
        state = next_held(state, key, noise[1:])
        return state, state[0]
    if kind == "pink":
        return next_pink(state, key, noise[1:])
    return next_matrices(state, key, noise[1])


def next_matrices(state: tuple, key: Any, sample_freq: int) -> tuple[tuple, Any]:
    """SdeNoise.next on the device: each env's exploration matrix weights (standard normal), drawn afresh every
    `sample_freq` steps and kept across episode ends, as SB3 keeps them."""
    import jax
    import jax.numpy as jnp

    weights, since_draw = state
    fresh = since_draw >= sample_freq
    weights = jax.lax.cond(fresh, lambda: jax.random.normal(key, weights.shape, jnp.float32), lambda: weights)
    return (weights, jnp.where(fresh, 0, since_draw) + 1), weights


def colored_sequences(key: Any, shape: tuple, pink: tuple) -> Any:
    """Fresh coloured sequences [*shape, length] of unit variance (the host's colored_noise, from a JAX key)."""
    import jax
    import jax.numpy as jnp

    from softac.replay.exploration import colored_spectrum

    beta, length = pink
    real_scale, imag_scale, amplitude, std = colored_spectrum(beta, length)
    real_key, imag_key = jax.random.split(key)
    real = jax.random.normal(real_key, (*shape, len(amplitude)), jnp.float32) * real_scale.astype(np.float32)
    imag = jax.random.normal(imag_key, (*shape, len(amplitude)), jnp.float32) * imag_scale.astype(np.float32)
    return (jnp.fft.irfft(real + 1j * imag, n=length) / std).astype(jnp.float32)


def restarted(state: tuple, which: Any, key: Any, pink: tuple) -> tuple:
    """Pink noise with the envs `which` on fresh sequences from their first value (ColoredNoise.restart); drawn
    only in steps where some env needs one."""
    import jax
    import jax.numpy as jnp

    sequences, position = state
    sequences = jax.lax.cond(which.any(), lambda: jnp.where(which[:, None, None],
                                                            colored_sequences(key, sequences.shape[:2], pink),
                                                            sequences), lambda: sequences)
    return sequences, jnp.where(which, 0, position)


def next_pink(state: tuple, key: Any, pink: tuple) -> tuple[tuple, Any]:
    """ColoredNoise.next on the device: each env's next value of its sequence, a used-up one followed by a fresh."""
    import jax.numpy as jnp

    sequences, position = restarted(state, state[1] >= pink[1], key, pink)
    values = sequences[jnp.arange(sequences.shape[0]), :, position]
    return (sequences, position + 1), values


def next_held(held: tuple, key: Any, repeat: tuple) -> tuple:
    """RepeatedNoise.next on the device: the held noise, drawn afresh (standard normal, every env's) with a new hold
    from the truncated Zeta distribution where the hold is over; one count for all envs, as the authors'."""
    import jax
    import jax.numpy as jnp

    noise, count, hold = held
    mu, largest = repeat
    pmf = jnp.arange(1, largest + 1, dtype=jnp.float32) ** -mu
    cdf = jnp.cumsum(pmf / pmf.sum())
    noise_key, hold_key = jax.random.split(key)
    fresh = (count == 0) | (count >= hold)
    noise = jnp.where(fresh, jax.random.normal(noise_key, noise.shape, jnp.float32), noise)
    hold = jnp.where(fresh, jnp.argmax(jax.random.uniform(hold_key) < cdf).astype(jnp.int32) + 1, hold)
    return noise, jnp.where(fresh, 0, count) + 1, hold


def observed_returns(carried: tuple, rewards: Any, dones: Any, gamma: float) -> tuple:
    """RunningReturnScale.update inside the chunk: each env's G <- gamma (1 - done) G + r, merged into the moments."""
    import jax.numpy as jnp

    from softac.learner.normalization import merged_moments

    returns, count, mean, m2, max_abs = carried
    returns = gamma * (1.0 - dones.astype(jnp.float32)) * returns + rewards
    return (returns, *merged_moments(count, mean, m2, returns[:, None]), jnp.maximum(max_abs, jnp.max(jnp.abs(returns))))


def reward_divisor(carried: tuple, mode: str, v_max: float) -> Any:
    """RunningReturnScale.scale from the carried statistics: what rewards are divided by now (1 before any step)."""
    import jax.numpy as jnp

    from softac.learner.normalization import return_divisor

    _, count, _, m2, max_abs = carried
    var = (m2 / jnp.maximum(count, 1))[0]
    return jnp.where(count > 0, return_divisor(var, max_abs, mode, v_max, jnp), 1.0)


def normalized(stats: tuple, obs: Any, clip: float) -> Any:
    """RunningObsNorm.normalize with these statistics."""
    import jax.numpy as jnp

    if not stats:
        return obs
    count, mean, m2 = stats
    from softac.learner.normalization import EPSILON

    var = jnp.where(count > 0, m2 / jnp.maximum(count, 1), 1.0)
    return jnp.clip((obs - mean) / jnp.sqrt(var + EPSILON), -clip, clip)


def finished_episodes(lengths: np.ndarray, returns: np.ndarray, before: int, n: int) -> list[Episode]:
    """The episodes that ended in a chunk ([steps, N] lengths and returns, 0 where none ended) in step order, each
    with the run's env steps when it ended."""
    steps, envs = np.nonzero(lengths)
    return [Episode(int(e), float(returns[s, e]), int(lengths[s, e]), step=before + (int(s) + 1) * n)
            for s, e in zip(steps, envs)]


def chunk_program(spec: ChunkSpec, numbers: tuple, carry: tuple, start: Any, count: Any, schedule: tuple,
                  offline: Any = ()) -> tuple[tuple, tuple]:
    """`count` (at most spec.length) vector steps from env step `start`: carry (SACState, metric totals, replay,
    envs' batch, key, obs_norm's and reward_scale's statistics, the exploration noise's state) -> the carry after,
    and each step's ended episodes' returns and lengths [length, N].
    `offline`: the dataset on the device (DeviceCollector.offline_device) where spec.offline_rows > 0."""
    import jax
    import jax.numpy as jnp

    from softac.learner.build import update_program
    from softac.learner.losses import Batch
    from softac.learner.normalization import merged_moments
    from softac.learner.pixels import features_of
    from softac.learner.sac import acting_actor
    from softac.replay import device_buffer

    envs, n = spec.envs, spec.envs.n
    total, end_fraction = schedule

    def step(carry, before):
        state, totals, replay, batch, key, stats, returns, noise = carry
        key, act_key, sample_key = jax.random.split(key, 3)
        if stats:  # every observation the policy acts on counts, the warm-up's too (as the host's learner.observe)
            stats = merged_moments(*stats, batch.obs)

        def policy_actions(noise):
            actor, actor_stats, encoder = acting_actor(state)
            features = features_of(encoder, normalized(stats, batch.obs, spec.obs_clip))
            if not noise:
                return spec.policy.sample(actor, actor_stats, features, act_key)[0], noise
            # held, pink or gSDE noise: drawn (from a key of its own) only when the policy acts, as the host's
            noise, values = next_noise(noise, jax.random.fold_in(act_key, 3), spec.noise)
            return spec.policy.with_noise(actor, actor_stats, features, values), noise

        if spec.uniform_warmup:
            actions, noise = jax.lax.cond(
                before < spec.learning_starts,
                lambda noise: (jax.random.uniform(act_key, (n, spec.act_dim), jnp.float32, -1.0, 1.0), noise),
                policy_actions, noise)
        else:
            actions, noise = policy_actions(noise)
        if spec.random_action_prob > 0:  # drawn only when asked: other runs keep their random numbers
            replace_key, uniform_key = jax.random.split(jax.random.fold_in(act_key, 1))
            replace = jax.random.uniform(replace_key, (n,)) < spec.random_action_prob
            uniform = jax.random.uniform(uniform_key, (n, spec.act_dim), jnp.float32, -1.0, 1.0)
            actions = jnp.where(replace[:, None], uniform, actions)
        batch, s = envs.step(batch, actions)
        if spec.noise[:1] == ("pink",):  # an env whose episode ended starts a fresh sequence (episode_ended)
            noise = restarted(noise, s.terminated | s.truncated, jax.random.fold_in(act_key, 4), spec.noise[1:])
        replay = device_buffer.insert(replay, s.obs, s.actions, s.rewards, s.next_obs, s.terminated,
                                      s.terminated | s.truncated)
        if returns:  # reward_scale: every training step's rewards count, the warm-up's too (learner.observe_rewards)
            returns = observed_returns(returns, s.rewards, s.terminated | s.truncated, spec.gamma)
        after = before + n

        def learn(state, totals):
            online_rows = spec.batch_size - spec.offline_rows
            drawn = device_buffer.sample(replay, sample_key, spec.gradient_steps, online_rows, n, spec.n_step,
                                         spec.gamma)
            if spec.offline_rows:  # RLPD's symmetric sampling: each batch's offline rows after its online ones
                drawn = mixed_rows(drawn, offline, jax.random.fold_in(sample_key, 2), spec.offline_rows)
            # raw observations in the buffer, normalised when drawn with the statistics of that moment (as the host's)
            rewards = drawn.rewards / reward_divisor(returns, spec.reward_scale, spec.v_max) if returns else drawn.rewards
            batches = Batch(normalized(stats, drawn.obs, spec.obs_clip), drawn.actions, rewards,
                            normalized(stats, drawn.next_obs, spec.obs_clip), drawn.terminated, drawn.steps)
            scale = (1.0 - (1.0 - end_fraction) * jnp.minimum(after / total, 1.0)).astype(jnp.float32) \
                if spec.linear_lr else None
            return update_program(spec.program, numbers, state, batches, totals, scale)

        if spec.gradient_steps > 0:
            state, totals = jax.lax.cond(after >= spec.learning_starts, learn, lambda s, t: (s, t), state, totals)
        return (state, totals, replay, batch, key, stats, returns, noise), (s.episode_returns, s.episode_lengths)

    def maybe_step(carry, i):
        # the steps past `count` (the budget's end inside this chunk) leave everything as it is
        return jax.lax.cond(i < count, lambda c: step(c, start + i * n), lambda c: (c, _no_episodes(n)), carry)

    return jax.lax.scan(maybe_step, carry, jnp.arange(spec.length, dtype=jnp.int32))


def mixed_rows(drawn: Any, offline: Any, key: Any, rows: int) -> Any:
    """The replay's batches (device_buffer.Sampled, [gradient_steps, rows', ...]) with `rows` more each drawn
    uniformly from the offline dataset, one-step transitions, as the host's mixed_batches lays them out."""
    import jax
    import jax.numpy as jnp

    idx = jax.random.randint(key, (drawn.rewards.shape[0], rows), 0, offline.rewards.shape[0])
    more = (offline.obs[idx], offline.actions[idx], offline.rewards[idx], offline.next_obs[idx],
            offline.terminated[idx], jnp.ones(idx.shape, drawn.steps.dtype))
    return type(drawn)(*(jnp.concatenate([a, b.astype(a.dtype)], axis=1) for a, b in zip(drawn, more)))


def _no_episodes(n: int) -> tuple:
    import jax.numpy as jnp

    return jnp.zeros(n, jnp.float32), jnp.zeros(n, jnp.int32)


def _compile():
    import jax

    # the carry donated (the device's replay and the networks updated in place)
    return jax.jit(chunk_program, static_argnums=0, donate_argnums=(2,))


class _Lazy:
    """A function jitted on first use (this module imports without JAX)."""

    def __init__(self, make):
        self.make, self.fn = make, None

    def __call__(self, *args):
        if self.fn is None:
            self.fn = self.make()
        return self.fn(*args)


compiled_chunk = _Lazy(_compile)
compiled_evaluation = _Lazy(lambda: __import__("jax").jit(evaluation_program, static_argnums=0))
