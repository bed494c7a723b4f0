"""Exploration while training: the action choice of each vector-env step (`Explorer`), and the temporally
correlated noise it can draw through, coloured (pink) noise for the policy's Gaussian and gSDE's exploration
matrices.

SAC explores with a = tanh(mean + std * eps), eps white (independent at each step). Eberhard et al. 2023
("Pink Noise Is All You Need", ICLR) draw eps from a sequence whose power spectrum falls as 1/f^beta along
the episode: beta 1 (pink) sits between white noise (0, SAC's) and a random walk (2, red), and explores
further in sparse-reward and long-horizon tasks (MountainCar, ...) while the policy's loss, its entropy and
the critics stay SAC's. Each env draws one sequence per episode (its length the config's
`noise_sequence_length`, the envs' episode length), a fresh one when its episode ends; each value has unit
variance, as white noise's.

gSDE (Raffin et al. 2022; softac.learner.policy has the maths) draws instead, for each env, the standard-normal weights
of an exploration matrix, kept for `sde_sample_freq` steps; the policy scales them by its current std.
FlashSAC's noise repetition (`RepeatedNoise`) holds white noise for a random number of steps.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from softac.errors import RunFailed


def colored_spectrum(beta: float, length: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """What a coloured sequence of `length` steps is made of (colored_noise, and the device's colored_sequences):
    each rfft frequency's amplitude for the real and the imaginary parts' standard-normal draws, and the std of the
    values irfft makes of them. A real sequence: the zero-frequency term (and, for an even length, the Nyquist term)
    has no imaginary part; its real part carries that variance (sqrt 2)."""
    freqs = np.fft.rfftfreq(length)
    freqs[0] = freqs[1] if length > 1 else 1.0  # the mean's component scaled as the lowest frequency's
    amplitude = freqs ** (-beta / 2.0)
    real, imag = amplitude.copy(), amplitude.copy()
    imag[0] = 0.0
    real[0] *= np.sqrt(2.0)
    if length % 2 == 0:
        imag[-1] = 0.0
        real[-1] *= np.sqrt(2.0)
    # each value's variance (the same at every step): irfft adds each interior term and its conjugate,
    # 2 Re(X_k e^(i w t)) of variance 4 a_k^2, and the end terms once, of variance 2 a^2; all over length^2
    interior = amplitude[1:-1] if length % 2 == 0 else amplitude[1:]
    ends = amplitude[0] ** 2 + (amplitude[-1] ** 2 if length % 2 == 0 else 0.0)
    return real, imag, amplitude, float(np.sqrt((2.0 * ends + 4.0 * np.sum(interior**2)) / length**2))


def colored_noise(rng: np.random.Generator, beta: float, shape: tuple[int, ...], length: int) -> np.ndarray:
    """Gaussian sequences along a last axis of `length` steps whose power spectral density is proportional to
    1/f^beta (Timmer & Koenig 1995: random Fourier amplitudes with the spectrum's scale, inverse FFT),
    scaled so that each value has unit variance. The lowest frequency is 1/length (the sequence's period)."""
    _, _, amplitude, std = colored_spectrum(beta, length)
    real = rng.normal(size=(*shape, len(amplitude))) * amplitude
    imag = rng.normal(size=(*shape, len(amplitude))) * amplitude
    imag[..., 0] = 0.0  # the end terms as colored_spectrum's scales say (in this order: the sequences of old runs)
    real[..., 0] *= np.sqrt(2.0)
    if length % 2 == 0:
        imag[..., -1] = 0.0
        real[..., -1] *= np.sqrt(2.0)
    return np.fft.irfft(real + 1j * imag, n=length) / std


class ColoredNoise:
    """One coloured sequence per env and action dimension, consumed a step at a time; an env whose episode
    ended starts a fresh sequence. Its state (random stream, sequences, positions) goes into checkpoints."""

    def __init__(self, beta: float, n_envs: int, act_dim: int, length: int, seed: int):
        self.beta, self.length = float(beta), int(length)
        self.rng = np.random.default_rng([seed, 0xC0105])
        self.sequences = colored_noise(self.rng, self.beta, (n_envs, act_dim), self.length)
        self.position = np.zeros(n_envs, np.int64)

    def next(self) -> np.ndarray:
        """(n_envs, act_dim) float32: each env's next values; a sequence used up is followed by a fresh one."""
        for i in np.flatnonzero(self.position >= self.length):
            self.restart(int(i))
        values = self.sequences[np.arange(len(self.position)), :, self.position]
        self.position += 1
        return values.astype(np.float32)

    def restart(self, env: int) -> None:
        self.sequences[env] = colored_noise(self.rng, self.beta, self.sequences.shape[1:2], self.length)
        self.position[env] = 0

    def episode_ended(self, env: int) -> None:
        self.restart(env)

    def checkpoint_parts(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        return ({"rng": self.rng.bit_generator.state, "beta": self.beta, "length": self.length},
                {"sequences": self.sequences.copy(), "position": self.position.copy()})

    def restore(self, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        saved = arrays["sequences"].shape if "sequences" in arrays else None
        if saved != self.sequences.shape:
            from softac.errors import SoftacError

            what = f"has shape {saved}" if saved else "is not pink noise (gSDE's exploration matrices)"
            raise SoftacError(f"the checkpoint's exploration noise {what}, this run's pink noise has shape "
                              f"{self.sequences.shape} (n_envs, action dims, noise_sequence_length)")
        self.rng.bit_generator.state = meta["rng"]
        self.sequences = np.array(arrays["sequences"], np.float64)
        self.position = np.array(arrays["position"], np.int64)

    def chunk_state(self) -> tuple[np.ndarray, ...]:
        """What a device chunk carries of it (issue 67): the sequences [N, act, length], each env's position."""
        return self.sequences.astype(np.float32), self.position.astype(np.int32)

    def keep_chunk_state(self, carried: tuple[np.ndarray, ...]) -> None:
        sequences, position = carried
        self.sequences, self.position = np.array(sequences, np.float64), np.array(position, np.int64)


class SdeNoise:
    """gSDE's exploration: for each env the standard-normal weights (features x act) of its exploration
    matrix, drawn afresh every `sample_freq` steps (SB3's sde_sample_freq) and kept across episode ends, as
    SB3 keeps them. Its state (random stream, weights, steps since the draw) goes into checkpoints."""

    def __init__(self, sample_freq: int, n_envs: int, n_features: int, act_dim: int, seed: int):
        self.sample_freq = int(sample_freq)
        self.rng = np.random.default_rng([seed, 0x65DE])
        self.weights = np.zeros((n_envs, n_features, act_dim), np.float32)
        self.since_draw = self.sample_freq  # a draw before the first step

    def next(self) -> np.ndarray:
        """(n_envs, features, act_dim) float32: each env's current weights."""
        if self.since_draw >= self.sample_freq:
            self.weights = self.rng.standard_normal(self.weights.shape, dtype=np.float32)
            self.since_draw = 0
        self.since_draw += 1
        return self.weights

    def episode_ended(self, env: int) -> None:
        pass

    def checkpoint_parts(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        return ({"rng": self.rng.bit_generator.state, "sample_freq": self.sample_freq},
                {"weights": self.weights.copy(), "since_draw": np.asarray(self.since_draw, np.int64)})

    def restore(self, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        if "weights" not in arrays or arrays["weights"].shape != self.weights.shape:
            from softac.errors import SoftacError

            raise SoftacError("the checkpoint's exploration noise is not this run's gSDE exploration matrices "
                              f"(n_envs, features, action dims) {self.weights.shape}")
        self.rng.bit_generator.state = meta["rng"]
        self.weights = np.array(arrays["weights"], np.float32)
        self.since_draw = int(arrays["since_draw"])

    def chunk_state(self) -> tuple[np.ndarray, ...]:
        """What a device chunk carries of it (issue 67): the matrices' weights [N, features, act], the steps since
        their draw."""
        return self.weights.astype(np.float32), np.int32(self.since_draw)

    def keep_chunk_state(self, carried: tuple[np.ndarray, ...]) -> None:
        weights, since_draw = carried
        self.weights, self.since_draw = np.array(weights, np.float32), int(since_draw)


def truncated_zeta_cdf(mu: float, largest: int) -> np.ndarray:
    """The CDF of k on 1..largest with P(k) proportional to k^-mu (a Zeta distribution cut at `largest`)."""
    pmf = np.arange(1, largest + 1, dtype=np.float64) ** -mu
    return np.cumsum(pmf / pmf.sum())


class RepeatedNoise:
    """FlashSAC's noise repetition (Kim et al. 2026, flash_rl/agents/flashSAC/agent.py): the standard-normal
    noise of every env's action is drawn once and held for k steps, k drawn afresh at each draw from a truncated
    Zeta distribution (P(k) ~ k^-mu, k <= largest; mu 2, largest 16: half the draws hold one step, a few hold
    many), so that exploration commits to a direction for a while, as action repeat does, without repeating the
    action itself (the policy's mean and std still follow the state). As the authors' code, one count for all
    envs, and episode ends do not cut a hold. Its state (random stream, the noise, the count) goes into
    checkpoints."""

    def __init__(self, mu: float, largest: int, n_envs: int, act_dim: int, seed: int):
        self.cdf = truncated_zeta_cdf(mu, largest)
        self.rng = np.random.default_rng([seed, 0x2E7A])
        self.noise = np.zeros((n_envs, act_dim), np.float32)
        self.count, self.hold = 0, 1  # steps the current noise was used for, and how many it is held

    def next(self) -> np.ndarray:
        """(n_envs, act_dim) float32: the held noise, drawn afresh when its hold is over (and at the first step)."""
        if self.count == 0 or self.count >= self.hold:
            self.noise = self.rng.standard_normal(self.noise.shape, dtype=np.float32)
            self.hold = int(np.argmax(self.rng.random() < self.cdf)) + 1
            self.count = 0
        self.count += 1
        return self.noise

    def episode_ended(self, env: int) -> None:
        pass

    def checkpoint_parts(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        return ({"rng": self.rng.bit_generator.state, "kind": "repeat"},
                {"held": self.noise.copy(), "count": np.asarray([self.count, self.hold], np.int64)})

    def restore(self, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        if "held" not in arrays or arrays["held"].shape != self.noise.shape:
            from softac.errors import SoftacError

            raise SoftacError("the checkpoint's exploration noise is not this run's repeated noise (n_envs, action "
                              f"dims) {self.noise.shape}")
        self.rng.bit_generator.state = meta["rng"]
        self.noise = np.array(arrays["held"], np.float32)
        self.count, self.hold = (int(v) for v in arrays["count"])

    def chunk_state(self) -> tuple[np.ndarray, ...]:
        """What a device chunk carries of it (issue 67): the held noise [N, act], the steps it was used, its hold."""
        return self.noise.astype(np.float32), np.int32(self.count), np.int32(self.hold)

    def keep_chunk_state(self, carried: tuple[np.ndarray, ...]) -> None:
        held, count, hold = carried
        self.noise, self.count, self.hold = np.array(held, np.float32), int(count), int(hold)


def exploration_noise(config: Any, act_dim: int) -> ColoredNoise | SdeNoise | RepeatedNoise | None:
    """The noise source the config's `exploration_noise` names (None: white noise from the act key)."""
    if config.exploration_noise == "repeat":
        return RepeatedNoise(config.noise_repeat_mu, config.noise_repeat_max, config.n_envs, act_dim, config.seed)
    if config.exploration_noise == "pink":
        return ColoredNoise(config.noise_beta, config.n_envs, act_dim, config.noise_sequence_length, config.seed)
    if config.exploration_noise == "gsde":
        n_features = config.actor_widths[-1]
        return SdeNoise(config.sde_sample_freq, config.n_envs, n_features, act_dim, config.seed)
    return None


# ---- the action choice ---------------------------------------------------------------------------------

def mix_in_random_actions(rng: np.random.Generator, actions: np.ndarray, prob: float) -> np.ndarray:
    """Each row of ACTIONS (one per env, in [-1, 1]) replaced with probability PROB by a uniform one.
    Andrychowicz et al. (2017) explore Fetch with 30% random actions: a policy that never touches the object
    learns nothing from hindsight goals about moving it. Draws the same numbers whichever rows it replaces."""
    replace = rng.random(actions.shape[0]) < prob
    uniform = rng.uniform(-1.0, 1.0, actions.shape)
    return np.where(replace[:, None], uniform, actions).astype(np.float32)


class Explorer:
    """The training loop's actions for one vector-env step: uniform before learning_starts (unless warmup_actions
    is policy); after it the policy's sample, through the run's coloured or gSDE noise where it has one, else through the run's act
    key; with random_action_prob, that share of the rows uniform again. `policy`: the learner (its config,
    act, act_with_noise, scaler); `streams`: the run state, whose random streams (rng, act_key, noise) are
    checkpointed with it and advanced here."""

    def __init__(self, policy: Any, streams: Any) -> None:
        self.policy, self.streams = policy, streams

    def actions(self, obs: np.ndarray, step: int) -> tuple[np.ndarray, np.ndarray]:
        """(actions in [-1, 1], the same in env bounds) for the envs' observations at env step `step`."""
        policy, rs = self.policy, self.streams
        cfg = policy.config
        if step < cfg.learning_starts and cfg.warmup_actions == "uniform":
            actions = rs.rng.uniform(-1.0, 1.0, (cfg.n_envs, policy.spaces.act_dim)).astype(np.float32)
            return actions, policy.scaler.to_env(actions)
        if rs.noise is not None:
            actions, env_actions = policy.act_with_noise(obs, rs.noise.next())
        else:
            actions, env_actions, rs.act_key = policy.act(obs, rs.act_key)
        if not np.all(np.isfinite(actions)):
            raise RunFailed(f"training diverged at step {step}: the policy produced non-finite "
                            "actions; the last good checkpoint is kept")
        if cfg.random_action_prob > 0:  # drawn only when asked: other runs keep their random numbers
            actions = mix_in_random_actions(rs.rng, actions, cfg.random_action_prob)
            env_actions = policy.scaler.to_env(actions)
        return actions, env_actions

    def episode_ended(self, env: int) -> None:
        """An env's episode ended: its noise sequence starts afresh (pink; gSDE keeps its matrices)."""
        if self.streams.noise is not None:
            self.streams.noise.episode_ended(env)
