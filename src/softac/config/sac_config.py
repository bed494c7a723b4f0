"""SACConfig: every hyperparameter once, with its one-line doc.

The command line (`--set KEY=VALUE`), the YAML presets (softac.config.presets) and the
configuration reference (docs/reference/config.md) all come from the fields below, so there is one source of truth.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import yaml

from softac.config.checks import CHECKS
from softac.config.names import is_dmc_id, is_playground_id, task_preset_name
from softac.config.presets import DMC_PRESET, FALLBACK_PRESET, GENERIC_PRESETS, load_preset, preset_names
from softac.errors import ConfigError


DEFAULT_ENV = "InvertedPendulum-v5"


def _f(default: Any, doc: str) -> Any:
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda: type(default)(default), metadata={"doc": doc})
    return field(default=default, metadata={"doc": doc})


@dataclass(frozen=True)
class SACConfig:
    # environment and run
    env_id: str = _f(DEFAULT_ENV, "Gymnasium id (or module:EnvId) to train on")
    total_steps: int = _f(20_000, "environment steps (transitions, summed over vector envs) to train for")
    seed: int = _f(0, "seed for networks, exploration, replay sampling and environments")
    n_envs: int = _f(1, "environments stepped together (a vector env)")
    action_repeat: int = _f(1, "each action applied this many times, the rewards summed (the DMC papers use 2); steps count the agent's actions, so frames = steps * action_repeat")
    pixels: bool = _f(False, "observe the env's rendered RGB frames (pixel_size square) instead of its observation: Gymnasium's MuJoCo envs, the DeepMind Control Suite, any env that renders rgb_array; learned through the image encoder")
    pixel_size: int = _f(84, "with pixels: the frames' side in pixels (84 as DrQ; rendered at that size where the renderer takes one, else resized)")
    frame_stack: int = _f(3, "image observations (pixels, or an env's own uint8 HxWxC or CxHxW Box): the last k frames as one observation [k, h, w, c], oldest first (3 as DrQ; the encoder reads them along the channels); 1 = the latest alone")
    collect_on: str = _f("auto", "where the training envs step: host (Gymnasium envs, one vector step at a time), device (N envs vmapped on the device, collection, replay and the updates fused in one jitted scan a chunk; MuJoCo Playground's envs), or auto (device for envs that step in JAX: playground:NAME; host for the rest)")
    env_workers: int = _f(0, "worker processes stepping the n_envs envs (0 = in-process, the default: MuJoCo's fast envs gain nothing); for slow simulators")
    device: str = _f("cpu", "cpu, gpu or auto (gpu when jax finds one)")
    # replay
    buffer_size: int = _f(1_000_000, "replay buffer capacity in transitions")
    offline_data: str = _f("", "transitions to learn from beside the env's own (issue 68): a Minari dataset (its id, downloaded by Minari where the machine reaches its host, or its directory), a softac run directory (its last checkpoint's replay buffer) or a `softac dataset` output; referenced, not copied, and checked by checksum on resume")
    offline_mode: str = _f("mix", "with offline_data: mix (each batch drawn part from the dataset, offline_fraction of it, part from the env's replay: RLPD's symmetric sampling, Ball et al. 2023) or prefill (the dataset copied into the replay buffer before the first step, then sampled as the env's own transitions)")
    offline_fraction: float = _f(0.5, "with offline_data and offline_mode mix: the share of each batch drawn from the dataset (RLPD's 0.5)")
    buffer_obs_once: bool = _f(False, "store each observation once (next_obs rebuilt from the following row; the host's buffer and the device's): Pusher 221 -> 145 B per transition, CheetahRun on the device 169 -> 114")
    batch_size: int = _f(256, "transitions per gradient step")
    obs_norm: bool = _f(False, "normalise observations by a running mean/std (as SB3's VecNormalize); saved in checkpoints")
    obs_norm_clip: float = _f(10.0, "with obs_norm: clip normalised observations to [-clip, clip]")
    learning_starts: int = _f(100, "environment steps of warm-up actions (warmup_actions) before learning")
    warmup_actions: str = _f("uniform", "the actions before learning_starts: uniform (SB3's, CleanRL's) or policy (the initial actor's samples, through the run's exploration noise, as Brax's prefill of its replay)")
    random_action_prob: float = _f(0.0, "after learning_starts (from the first step with warmup_actions policy), the share of training actions drawn uniformly from the action space instead of from the policy (each env, each step); exploration for sparse-reward goal envs, as the HER paper's random_eps (0.3 on Fetch)")
    exploration_noise: str = _f("gaussian", "the noise of training actions after learning_starts: gaussian (white, SAC's), pink (temporally correlated along each episode, Eberhard et al. 2023; its colour noise_beta) or gsde (state-dependent, as SB3's use_sde, Raffin et al. 2022: noise f(s) @ W, the exploration matrix W drawn every sde_sample_freq steps and its log std learned) or repeat (FlashSAC's noise repetition, Kim et al. 2026: the white noise held for k steps, k from a truncated Zeta distribution, noise_repeat_mu and noise_repeat_max)")
    noise_repeat_mu: float = _f(2.0, "with exploration_noise repeat: the exponent of the truncated Zeta distribution each hold's length k is drawn from, P(k) ~ k^-mu (FlashSAC: 2)")
    noise_repeat_max: int = _f(16, "with exploration_noise repeat: the longest hold, in steps (FlashSAC: 16)")
    noise_beta: float = _f(1.0, "with exploration_noise pink: the exponent of its 1/f^beta spectrum (1 pink; 0 white; 2 red, a random walk)")
    noise_sequence_length: int = _f(1000, "with exploration_noise pink: steps per noise sequence (the envs' episode length); each episode starts a fresh one")
    sde_sample_freq: int = _f(64, "with exploration_noise gsde: steps (of each env) between fresh exploration matrices; SB3 draws one per rollout of train_freq steps (RL Zoo's gSDE settings: 32-64), 1 draws one each step")
    sde_log_std_init: float = _f(-3.0, "with exploration_noise gsde: the initial log std of the exploration matrix's weights (SB3's log_std_init; RL Zoo's MountainCarContinuous -3.67)")
    her: str = _f("auto", "hindsight experience replay (Andrychowicz et al. 2017) for goal envs (dict observation with observation, achieved_goal, desired_goal, and compute_reward): auto (on for goal envs), on, off")
    her_strategy: str = _f("future", "with HER, where a relabelled goal comes from: future (achieved later in the episode), final (at its end), episode (anywhere in it)")
    her_k: int = _f(4, "with HER, relabelled goals per real one: her_k/(her_k+1) of each batch gets a hindsight goal")
    # algorithm
    gamma: float = _f(0.99, "discount factor")
    tau: float = _f(0.005, "Polyak coefficient for target critics (1 = hard copy)")
    target_update_interval: int = _f(1, "gradient steps between target-critic updates")
    gradient_steps: int = _f(1, "gradient steps per vector-env step (all fused in one jitted call)")
    policy_frequency: int = _f(1, "critic updates per actor/alpha update round; each round does this many actor updates (CleanRL's delayed update)")
    policy_delay: int = _f(1, "critic updates per actor/alpha update, with no catch-up (TD3's policy_delay): 2 halves the actor's steps and takes ~20% off the update's compute")
    policy_average_tau: float = _f(0.0, "weight averaging (Nikishin et al. 2018): evaluation, predict, sample and export run an exponential moving average of the actor (its running statistics and an image encoder too) updated at this rate after each actor step; exploration acts with the actor itself; 0 = off, the actor itself")
    reset_interval: int = _f(0, "environment steps between resets of actor, critics and their optimisers (the buffer and alpha stay; none at or past total_steps; Nikishin et al. 2022); 0 = never")
    n_step: int = _f(1, "rewards summed before bootstrapping (n-step returns, as RLlib's n_step; the walk stops at episode ends); 1 = plain SAC")
    encoder_channels: int = _f(32, "image observations: filters of each of the encoder's 4 convolutions (DrQ's encoder: 3x3, strides 2,1,1,1, then Linear, LayerNorm, tanh)")
    encoder_features: int = _f(50, "image observations: the encoder's output width, what actor and critics read (DrQ: 50)")
    target_encoder: bool = _f(False, "image observations: the target critics read observations through a target copy of the encoder, Polyak-averaged with them at tau (DrQ, SAC-AE); false: through the online encoder, stopped (DrQ-v2); needs target critics")
    actor_encoder_head: bool = _f(False, "image observations: the actor reads the shared convolutions' output, stopped, through a head of its own (Linear, LayerNorm, tanh, as the encoder's), trained by the actor loss (DrQ's actor); false: the critic-trained encoder's features, stopped")
    augment_pad: int = _f(4, "image observations: DrQ's random shift, each image padded by this many edge pixels and cropped back at a random offset in every update (0 = no augmentation)")
    pixel_range: str = _f("unit", "image observations: what the encoder scales pixels to: unit, [0, 1] (DrQ's obs / 255, SB3's; a black background reads as zero); centered, [-0.5, 0.5] (DrQ-v2's; softac's only scaling before 2026-11-29, which checkpoints from then keep)")
    n_critics: int = _f(2, "critics in the ensemble; the target takes their minimum (target_q; TQC: pools their quantiles)")
    target_q: str = _f("min", "the next-state value the critics learn toward: min (the lowest critic's, clipped double Q, Fujimoto et al. 2018; categorical critics: the distribution with the lowest mean) or each (every critic toward its own next-state critic's value or distribution, as FastSAC) or subset (the lowest of target_q_subset critics drawn at random for each update, REDQ's in-target minimisation, Chen et al. 2021, as RLPD)")
    target_q_subset: int = _f(2, "with target_q subset: how many of the n_critics each update's target draws (REDQ's M; RLPD 2 of 10)")
    actor_q: str = _f("min", "the value the actor climbs: min (the lowest critic's Q, SAC's) or mean (the critics' mean, as FastSAC, REDQ and RLPD); TQC's quantile critics always take the mean of every quantile")
    target_critics: str = _f("auto", "Polyak-averaged target critics for the next-state value: auto (on, off with crossq), on or off; with crossq, on is CrossQ+WN's form (Palenicek et al. 2025): the targets make the joint pass in training mode with their own statistics")
    n_quantiles: int = _f(0, "TQC (Kuznetsov et al. 2020): quantiles each critic predicts (25 in the paper), trained with the quantile Huber loss on the pooled, truncated next-state atoms; 0 = one Q-value per critic (SAC)")
    top_quantiles_to_drop_per_net: int = _f(2, "with n_quantiles: the largest next-state atoms dropped, per critic (TQC's d: n_critics * d of the pool)")
    n_atoms: int = _f(0, "categorical critics: each critic predicts a distribution over n_atoms evenly spaced values from v_min to v_max, learned by cross-entropy to the soft target's distribution (C51, Bellemare et al. 2017: 51; XQC, FastTD3 and FlashSAC: 101); the target is, per row, the distribution of the next-state critic with the lowest mean (clipped double Q on distributions), the actor climbs the smallest mean; 0 = one Q-value per critic (SAC)")
    categorical_target: str = _f("c51", "with n_atoms: the target distribution: c51 (each next-state atom z moved to r + gamma (z - alpha log pi) and projected back onto the support with its probability, as XQC and FastTD3), two_hot (the scalar soft target on its two neighbouring atoms) or hl_gauss (the scalar soft target as a Gaussian of hl_gauss_sigma atom spacings, Farebrother et al. 2024)")
    v_min: float = _f(-5.0, "with n_atoms: the support's lowest value (in the critics' reward units: after reward_scale)")
    v_max: float = _f(5.0, "with n_atoms: the support's highest value")
    hl_gauss_sigma: float = _f(0.75, "with categorical_target hl_gauss: the Gaussian's standard deviation in atom spacings (0.75 as Farebrother et al. 2024)")
    reward_scale: str = _f("off", "the critics' rewards divided by the spread of the running discounted return G (each env's G <- gamma (1 - done) G + r, SimbaV2's normaliser), so that returns fit a fixed support: std (by sigma_G, as XQC), std_max (by max(sigma_G, G_max / v_max), as FlashSAC), or off; the statistics are saved in checkpoints; evaluation returns stay in the env's units")
    critic_layer_norm: bool = _f(False, "LayerNorm before each hidden activation of the critics (RLPD; for high gradient_steps)")
    actor_layer_norm: bool = _f(False, "LayerNorm before each hidden activation of the actor (FastSAC; network=mlp without crossq)")
    layer_norm_affine: bool = _f(False, "with critic_layer_norm or actor_layer_norm: each of those LayerNorms learns a scale and bias per unit (from 1 and 0), as Flax's LayerNorm in Brax's and RLPD's networks; off (the default): none")
    layer_norm_position: str = _f("before", "where critic_layer_norm's and actor_layer_norm's LayerNorms sit: before each hidden activation (RLPD, FastSAC) or after it (Brax's MLP with layer_norm)")
    critic_dropout: float = _f(0.0, "dropout rate on the critics' hidden units in every critic pass (DroQ, Hiraoka et al. 2022: 0.01, with critic_layer_norm, at high gradient_steps)")
    network: str = _f("mlp", "actor and critic networks: mlp; simba (Lee et al. 2024): a linear embedding, one pre-LayerNorm residual block (inner width 4x) per hidden width, a final LayerNorm, use with obs_norm; bn_mlp (XQC, Palenicek et al. 2026; needs crossq): batch normalisation of the input, then per hidden width a dense layer without bias, batch normalisation and the activation (with weight_norm every kernel's units at unit norm, the output layer's too); or flashsac (Kim et al. 2026; needs crossq): batch normalisation of the input, a linear embedding, one inverted residual block x + relu(BN(relu(BN(x W1)) W2)) (inner width 4x) per hidden width, an RMSNorm (with weight_norm kernels' units at unit norm, the normalisations' parameters at norm sqrt(width))")
    actor_hidden_sizes: list = _f([], "the actor's hidden widths when they differ from hidden_sizes (empty: hidden_sizes)")
    critic_hidden_sizes: list = _f([], "the critics' hidden widths when they differ from hidden_sizes (empty: hidden_sizes)")
    crossq: bool = _f(False, "CrossQ (Bhatt et al. 2024): no target critics (tau unused); batch renormalisation in actor and critics, the critics seeing (s, a) and (s', a') as one batch")
    batch_norm_momentum: float = _f(0.99, "with crossq: momentum of the running mean and variance")
    batch_norm_eps: float = _f(1e-3, "with crossq: the epsilon added to the batch variance (1e-3 as CrossQ and XQC; FlashSAC, as PyTorch's BatchNorm, 1e-5)")
    batch_renorm_warmup: int = _f(100_000, "with crossq: gradient steps of plain batch normalisation before batch renormalisation's corrections (Ioffe 2017)")
    weight_norm: bool = _f(False, "with crossq: each hidden unit's weights and bias kept at unit norm after every optimiser step (CrossQ+WN, Palenicek et al. 2025): batch renormalisation makes the next layer blind to their scale, whose growth would shrink the effective learning rate")
    adam_b1: float = _f(0.9, "Adam's first-moment decay, for actor, critics and alpha (CrossQ uses 0.5)")
    adam_b2: float = _f(0.999, "Adam's second-moment decay, for actor, critics and alpha (FastTD3 and FastSAC use 0.95)")
    weight_decay: float = _f(0.0, "AdamW's decoupled weight decay for actor and critics (Loshchilov & Hutter 2019); 0 = Adam")
    weight_decay_layers: str = _f("all", "with weight_decay: all (every parameter, as SimBa) or output (the output layers only, as CrossQ+WN)")
    hidden_sizes: list = _f([256, 256], "hidden layer widths of actor and critics, e.g. 256,256")
    activation: str = _f("relu", "hidden activation: relu, tanh, elu, gelu or silu (FastSAC)")
    init: str = _f("default", "weight init: default (fan-in uniform, as PyTorch), orthogonal, or lecun_uniform (weights U(+-sqrt(3 / fan_in)) and zero biases, as Brax's networks) or xavier_uniform (U(+-sqrt(6 / (fan_in + fan_out))), zero biases, as RLPD's)")
    zero_actor_head: bool = _f(False, "the actor's output layer starts at zero, weights and biases (FastSAC): in every state the mean action 0 and one log std (the middle of its range with log_std_mode tanh) until it learns")
    matmul_dtype: str = _f("float32", "matmul inputs: float32, bfloat16 (f32 accumulation and parameters; fast on AMX/AVX-512 BF16 CPUs and GPUs), or auto (bfloat16 where it is fast, else float32)")
    actor_lr: float = _f(3e-4, "Adam learning rate of the actor")
    critic_lr: float = _f(3e-4, "Adam learning rate of the critics")
    alpha_lr: float = _f(3e-4, "Adam learning rate of log(alpha)")
    lr_schedule: str = _f("constant", "the learning rates over a run: constant, or linear (each falls linearly with the env steps to lr_end_fraction of itself at total_steps, as SB3's and RL Zoo's lin_ schedules)")
    lr_end_fraction: float = _f(0.0, "with lr_schedule=linear: the fraction of each learning rate left at total_steps (0, SB3's lin_: to zero)")
    autotune_alpha: bool = _f(True, "learn the entropy coefficient on log(alpha) (Haarnoja et al. 2018b)")
    alpha: float = _f(1.0, "entropy coefficient: fixed value, or the initial one when autotuned")
    target_entropy: Any = _f("auto", "entropy target when autotuned; auto = -target_entropy_scale * |A|")
    target_entropy_std: float = _f(0.0, "with target_entropy auto and > 0: the target is the entropy of a Gaussian of this std in each action dim, 0.5 |A| log(2 pi e std^2) (FlashSAC's target from a fixed action std, 0.15: about -0.48 |A|), in place of -target_entropy_scale * |A|")
    target_entropy_scale: float = _f(1.0, "with target_entropy auto: the target is -scale * |A| (SAC 1; SimBa and CrossQ+WN 0.5)")
    log_std_min: float = _f(-20.0, "lower bound of the actor's log std (with log_std_mode softplus: the log of the std's floor)")
    log_std_max: float = _f(2.0, "upper bound of the actor's log std (unused with log_std_mode softplus)")
    log_std_mode: str = _f("clamp", "how log std is bounded: clamp (SB3), tanh (CleanRL's squash into [log_std_min, log_std_max]) or softplus (Brax's NormalTanhDistribution: std = softplus(output) + exp(log_std_min), no upper bound; Brax's floor 0.001 is log_std_min -6.907755)")
    # evaluation, logs, checkpoints
    eval_interval: int = _f(5_000, "environment steps between deterministic evaluations (0 disables)")
    eval_episodes: int = _f(10, "episodes per evaluation")
    log_interval: int = _f(1_000, "environment steps between progress.csv rows")
    checkpoint_interval: int = _f(10_000, "environment steps between checkpoints/last writes (0: only at the end)")
    loggers: str = _f("tensorboard", "where metrics go besides the CSV files: tensorboard, wandb, mlflow (comma-separated), or none")

    # ---- construction -------------------------------------------------

    @classmethod
    def field_docs(cls) -> dict[str, str]:
        return {f.name: f.metadata["doc"] for f in fields(cls)}

    @classmethod
    def preset(cls, name: str, env_id: str | None = None, overrides: dict[str, Any] | None = None) -> "SACConfig":
        """The named preset (an env id or `sb3`, `cleanrl`, `default`), with `overrides` (parsed KEY: value) applied
        in the same replace and checked once with it: `fastsac` (4096 envs, for device envs) on a host env with
        `n_envs=2` is valid though the preset alone on that env is not."""
        values = load_preset(name)
        cfg = cls()
        if name == DMC_PRESET and not is_dmc_id(env_id or ""):
            raise ConfigError(f"preset '{DMC_PRESET}' is for DeepMind Control tasks: give one with --env "
                              f"dmc:DOMAIN-TASK (e.g. dmc:cheetah-run), got {env_id or 'no --env'}")
        if env_id is not None:
            values["env_id"] = env_id
        elif "env_id" not in values and name in preset_names() and name not in GENERIC_PRESETS:
            values["env_id"] = name
        return cfg.replace(**{**values, **(overrides or {})})

    @classmethod
    def for_env(cls, env_id: str | None, overrides: dict[str, Any] | None = None) -> "SACConfig":
        """The env's own preset when there is one (`dmc-DOMAIN-TASK` for a DeepMind Control task), else `dmc`
        for a DeepMind Control task, else the fallback preset; `overrides` as in `preset`."""
        env_id = env_id or DEFAULT_ENV
        own = task_preset_name(env_id) if is_dmc_id(env_id) else env_id
        name = own if own in preset_names() else DMC_PRESET if is_dmc_id(env_id) else FALLBACK_PRESET
        return cls.preset(name, env_id=env_id, overrides=overrides)

    @classmethod
    def from_yaml(cls, path: str | Path) -> "SACConfig":
        path = Path(path)
        try:
            data = yaml.safe_load(path.read_text())
        except FileNotFoundError:
            raise ConfigError(f"config file not found: {path}") from None
        except (OSError, yaml.YAMLError) as exc:
            raise ConfigError(f"cannot read config file {path}: {str(exc).splitlines()[0]}") from None
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise ConfigError(f"config file {path} must hold a mapping of key: value")
        data = {k: v for k, v in data.items() if k not in RECORD_ONLY_KEYS}
        base = cls.for_env(data.get("env_id"))
        return base.replace(**data)

    def replace(self, **values: Any) -> "SACConfig":
        known = {f.name: f for f in fields(self)}
        coerced = {}
        for key, value in values.items():
            if key not in known:
                raise ConfigError(_unknown_key_message(key, list(known)))
            coerced[key] = _coerce(key, known[key], value)
        cfg = dataclasses.replace(self, **coerced)
        cfg.validate()
        return cfg

    def with_overrides(self, pairs: list[str]) -> "SACConfig":
        """Apply `KEY=VALUE` strings (values parsed as YAML scalars)."""
        return self.replace(**parse_overrides(pairs))

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def markdown_table(cls) -> str:
        """The table of keys, defaults and docs in docs/reference/config.md (`make docs` writes it there)."""
        default = cls()
        rows = ["| key | default | meaning |", "| --- | --- | --- |"]
        for f in fields(cls):
            value = getattr(default, f.name)
            shown = ",".join(map(str, value)) if isinstance(value, list) else value
            rows.append(f"| `{f.name}` | `{shown}` | {f.metadata['doc']} |")
        return "\n".join(rows)

    @property
    def has_target_critics(self) -> bool:
        """`target_critics: auto` is on for SAC and off for CrossQ (Bhatt et al. 2024 drop them)."""
        return self.target_critics == "on" or (self.target_critics == "auto" and not self.crossq)

    @property
    def collects_on_device(self) -> bool:
        """`collect_on: auto` is the device for envs that step in JAX (MuJoCo Playground's), the host otherwise."""
        return self.collect_on == "device" or (self.collect_on == "auto" and is_playground_id(self.env_id))

    @property
    def mixes_offline_data(self) -> bool:
        """offline_data drawn into each batch (offline_mode mix), not copied into the replay first (prefill)."""
        return bool(self.offline_data) and self.offline_mode == "mix"

    @property
    def critic_outputs(self) -> int:
        """Each critic's outputs: its quantiles (TQC), its atoms' logits (categorical), or its Q-value."""
        return self.n_quantiles or self.n_atoms or 1

    @property
    def actor_widths(self) -> list[int]:
        """The actor's hidden sizes: actor_hidden_sizes, else hidden_sizes."""
        return list(self.actor_hidden_sizes or self.hidden_sizes)

    @property
    def critic_widths(self) -> list[int]:
        """Each critic's hidden sizes: critic_hidden_sizes, else hidden_sizes."""
        return list(self.critic_hidden_sizes or self.hidden_sizes)

    @property
    def pixel_offset(self) -> float:
        """What the encoder subtracts from pixels scaled to [0, 1] (`pixel_range`)."""
        return 0.5 if self.pixel_range == "centered" else 0.0

    # ---- validation ---------------------------------------------------

    def validate(self) -> None:
        """Every key's range and the combinations that cannot work, section by section (ConfigError, naming the
        key, at the first that fails)."""
        for check in CHECKS:
            check(self)


# keys written to config.yaml for the record; ignored when the file is read back
RECORD_ONLY_KEYS = ("versions", "softac_version", "resolved_target_entropy", "resolved_matmul_dtype",
                    "buffer_bytes_per_transition", "cpus", "machine", "segments")


def parse_overrides(pairs: list[str]) -> dict[str, Any]:
    """`KEY=VALUE` strings (--set) as a dict, values parsed as YAML scalars; checked when applied."""
    values = {}
    for pair in pairs:
        if "=" not in pair:
            raise ConfigError(f"--set expects KEY=VALUE, got '{pair}'")
        key, raw = pair.split("=", 1)
        key = override_key(key)
        try:
            values[key] = yaml.safe_load(raw) if raw.strip() else raw
        except yaml.YAMLError:
            values[key] = raw
    return values


def override_key(text: str) -> str:
    """A key as the command line may spell it (`--set eval-interval=...`) to the field name."""
    return text.strip().replace("-", "_")


def _unknown_key_message(key: str, known: list[str]) -> str:
    close = difflib.get_close_matches(key, known, n=1)
    hint = f" (did you mean {close[0]}?)" if close else ""
    return f"unknown config key '{key}'{hint}"


def _coerce(key: str, f: dataclasses.Field, value: Any) -> Any:
    default = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]
    bad = ConfigError(f"{key}={value!r}: expected {_type_name(default)}")
    if key in ("her", "target_critics") and isinstance(value, bool):  # YAML reads on/off/true/false as booleans
        return "on" if value else "off"
    if key == "target_entropy":
        if isinstance(value, str) and value.strip().lower() == "auto" or value is None:
            return "auto"
        value = _as_float(value, bad)
        return value
    if isinstance(default, bool):
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false", "yes", "no", "1", "0", "on", "off"):
            return value.lower() in ("true", "yes", "1", "on")
        if isinstance(value, int) and value in (0, 1):
            return bool(value)
        raise bad
    if isinstance(default, int):
        if isinstance(value, bool):
            raise bad
        if isinstance(value, int):
            return value
        if isinstance(value, float) and value.is_integer() and math.isfinite(value):
            return int(value)
        if isinstance(value, str):
            try:
                as_float = float(value.replace("_", ""))
            except ValueError:
                raise bad from None
            if math.isfinite(as_float) and as_float.is_integer():
                return int(as_float)
        raise bad
    if isinstance(default, float):
        return _as_float(value, bad)
    if isinstance(default, list):
        return _as_int_list(value, bad)
    if isinstance(default, str):
        if isinstance(value, (str, int, float)) and not isinstance(value, bool):
            return str(value).strip()
        raise bad
    raise bad


def _as_float(value: Any, bad: ConfigError) -> float:
    if isinstance(value, bool):
        raise bad
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise bad from None
    if not math.isfinite(out):
        raise bad
    return out


def _as_int_list(value: Any, bad: ConfigError) -> list[int]:
    if isinstance(value, int) and not isinstance(value, bool):
        return [value]
    if isinstance(value, str):
        parts = [p for p in value.replace("x", ",").replace("[", "").replace("]", "").split(",") if p.strip()]
        try:
            return [int(p) for p in parts]
        except ValueError:
            raise bad from None
    if isinstance(value, (list, tuple)) and all(isinstance(v, int) and not isinstance(v, bool) for v in value):
        return list(value)
    raise bad


def _type_name(default: Any) -> str:
    if isinstance(default, bool):
        return "true or false"
    if isinstance(default, int):
        return "an integer"
    if isinstance(default, float):
        return "a finite number"
    if isinstance(default, list):
        return "a list of integers like 256,256"
    return "a string"
