"""SACConfig: every hyperparameter once, with its one-line doc.

The command line (`--set KEY=VALUE`), the YAML presets in `presets/` and the
configuration reference (docs/reference/config.md) all come from the fields below, so there is one source of truth.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from dataclasses import dataclass, field, fields
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from softac.config.names import is_dmc_id, parse_backends, task_preset_name
from softac.errors import SoftacError


class ConfigError(SoftacError, ValueError):
    """A bad config key or value; the message names the key."""


DEFAULT_ENV = "InvertedPendulum-v5"
FALLBACK_PRESET = "default"
DMC_PRESET = "dmc"  # every DeepMind Control task without a preset of its own (issue 43); names no env itself


def _f(default: Any, doc: str) -> Any:
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda: type(default)(default), metadata={"doc": doc})
    return field(default=default, metadata={"doc": doc})


@dataclass
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
    env_workers: int = _f(0, "worker processes stepping the n_envs envs (0 = in-process, the default: MuJoCo's fast envs gain nothing); for slow simulators")
    device: str = _f("cpu", "cpu, gpu or auto (gpu when jax finds one)")
    # replay
    buffer_size: int = _f(1_000_000, "replay buffer capacity in transitions")
    buffer_obs_once: bool = _f(False, "store each observation once (next_obs rebuilt from the following row): Pusher 221 -> 145 B per transition")
    batch_size: int = _f(256, "transitions per gradient step")
    obs_norm: bool = _f(False, "normalise observations by a running mean/std (as SB3's VecNormalize); saved in checkpoints")
    obs_norm_clip: float = _f(10.0, "with obs_norm: clip normalised observations to [-clip, clip]")
    learning_starts: int = _f(100, "environment steps of uniform random actions before learning")
    random_action_prob: float = _f(0.0, "after learning_starts, the share of training actions drawn uniformly from the action space instead of from the policy (each env, each step); exploration for sparse-reward goal envs, as the HER paper's random_eps (0.3 on Fetch)")
    exploration_noise: str = _f("gaussian", "the noise of training actions after learning_starts: gaussian (white, SAC's), pink (temporally correlated along each episode, Eberhard et al. 2023; its colour noise_beta) or gsde (state-dependent, as SB3's use_sde, Raffin et al. 2022: noise f(s) @ W, the exploration matrix W drawn every sde_sample_freq steps and its log std learned)")
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
    n_critics: int = _f(2, "critics in the ensemble; the target takes their minimum (TQC: pools their quantiles)")
    target_critics: str = _f("auto", "Polyak-averaged target critics for the next-state value: auto (on, off with crossq), on or off; with crossq, on is CrossQ+WN's form (Palenicek et al. 2025): the targets make the joint pass in training mode with their own statistics")
    n_quantiles: int = _f(0, "TQC (Kuznetsov et al. 2020): quantiles each critic predicts (25 in the paper), trained with the quantile Huber loss on the pooled, truncated next-state atoms; 0 = one Q-value per critic (SAC)")
    top_quantiles_to_drop_per_net: int = _f(2, "with n_quantiles: the largest next-state atoms dropped, per critic (TQC's d: n_critics * d of the pool)")
    critic_layer_norm: bool = _f(False, "LayerNorm before each hidden activation of the critics (RLPD; for high gradient_steps)")
    critic_dropout: float = _f(0.0, "dropout rate on the critics' hidden units in every critic pass (DroQ, Hiraoka et al. 2022: 0.01, with critic_layer_norm, at high gradient_steps)")
    network: str = _f("mlp", "actor and critic networks: mlp, or simba (Lee et al. 2024): a linear embedding, one pre-LayerNorm residual block (inner width 4x) per hidden width, a final LayerNorm; use with obs_norm")
    actor_hidden_sizes: list = _f([], "the actor's hidden widths when they differ from hidden_sizes (empty: hidden_sizes)")
    critic_hidden_sizes: list = _f([], "the critics' hidden widths when they differ from hidden_sizes (empty: hidden_sizes)")
    crossq: bool = _f(False, "CrossQ (Bhatt et al. 2024): no target critics (tau unused); batch renormalisation in actor and critics, the critics seeing (s, a) and (s', a') as one batch")
    batch_norm_momentum: float = _f(0.99, "with crossq: momentum of the running mean and variance")
    batch_renorm_warmup: int = _f(100_000, "with crossq: gradient steps of plain batch normalisation before batch renormalisation's corrections (Ioffe 2017)")
    weight_norm: bool = _f(False, "with crossq: each hidden unit's weights and bias kept at unit norm after every optimiser step (CrossQ+WN, Palenicek et al. 2025): batch renormalisation makes the next layer blind to their scale, whose growth would shrink the effective learning rate")
    adam_b1: float = _f(0.9, "Adam's first-moment decay, for actor, critics and alpha (CrossQ uses 0.5)")
    weight_decay: float = _f(0.0, "AdamW's decoupled weight decay for actor and critics (Loshchilov & Hutter 2019); 0 = Adam")
    weight_decay_layers: str = _f("all", "with weight_decay: all (every parameter, as SimBa) or output (the output layers only, as CrossQ+WN)")
    hidden_sizes: list = _f([256, 256], "hidden layer widths of actor and critics, e.g. 256,256")
    activation: str = _f("relu", "hidden activation: relu, tanh, elu or gelu")
    init: str = _f("default", "weight init: default (fan-in uniform, as PyTorch) or orthogonal")
    matmul_dtype: str = _f("float32", "matmul inputs: float32, bfloat16 (f32 accumulation and parameters; fast on AMX/AVX-512 BF16 CPUs and GPUs), or auto (bfloat16 where it is fast, else float32)")
    actor_lr: float = _f(3e-4, "Adam learning rate of the actor")
    critic_lr: float = _f(3e-4, "Adam learning rate of the critics")
    alpha_lr: float = _f(3e-4, "Adam learning rate of log(alpha)")
    lr_schedule: str = _f("constant", "the learning rates over a run: constant, or linear (each falls linearly with the env steps to lr_end_fraction of itself at total_steps, as SB3's and RL Zoo's lin_ schedules)")
    lr_end_fraction: float = _f(0.0, "with lr_schedule=linear: the fraction of each learning rate left at total_steps (0, SB3's lin_: to zero)")
    autotune_alpha: bool = _f(True, "learn the entropy coefficient on log(alpha) (Haarnoja et al. 2018b)")
    alpha: float = _f(1.0, "entropy coefficient: fixed value, or the initial one when autotuned")
    target_entropy: Any = _f("auto", "entropy target when autotuned; auto = -target_entropy_scale * |A|")
    target_entropy_scale: float = _f(1.0, "with target_entropy auto: the target is -scale * |A| (SAC 1; SimBa and CrossQ+WN 0.5)")
    log_std_min: float = _f(-20.0, "lower bound of the actor's log std")
    log_std_max: float = _f(2.0, "upper bound of the actor's log std")
    log_std_mode: str = _f("clamp", "how log std is bounded: clamp (SB3) or tanh (CleanRL's squash)")
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
    def preset(cls, name: str, env_id: str | None = None) -> "SACConfig":
        """The named preset (an env id or `sb3`, `cleanrl`, `default`)."""
        values = load_preset(name)
        cfg = cls()
        if name == DMC_PRESET and not is_dmc_id(env_id or ""):
            raise ConfigError(f"preset '{DMC_PRESET}' is for DeepMind Control tasks: give one with --env "
                              f"dmc:DOMAIN-TASK (e.g. dmc:cheetah-run), got {env_id or 'no --env'}")
        if env_id is not None:
            values["env_id"] = env_id
        elif "env_id" not in values and name in preset_names() and name not in GENERIC_PRESETS:
            values["env_id"] = name
        return cfg.replace(**values)

    @classmethod
    def for_env(cls, env_id: str | None) -> "SACConfig":
        """The env's own preset when there is one (`dmc-DOMAIN-TASK` for a DeepMind Control task), else `dmc`
        for a DeepMind Control task, else the fallback preset."""
        env_id = env_id or DEFAULT_ENV
        own = task_preset_name(env_id) if is_dmc_id(env_id) else env_id
        name = own if own in preset_names() else DMC_PRESET if is_dmc_id(env_id) else FALLBACK_PRESET
        return cls.preset(name, env_id=env_id)

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
    def pixel_offset(self) -> float:
        """What the encoder subtracts from pixels scaled to [0, 1] (`pixel_range`)."""
        return 0.5 if self.pixel_range == "centered" else 0.0

    # ---- validation ---------------------------------------------------

    def validate(self) -> None:
        """Every key's range and the combinations that cannot work, section by section (ConfigError, naming the
        key, at the first that fails)."""
        for check in CHECKS:
            check(self)


def _requirer(config: "SACConfig"):
    """need(ok, key, what): a ConfigError naming key, its value and what it must be, unless ok."""
    def need(ok: bool, key: str, what: str) -> None:
        if not ok:
            raise ConfigError(f"{key}={getattr(config, key)!r}: {what}")
    return need


def _check_env_and_images(config: "SACConfig") -> None:
    """The env, its images and how its steps are run."""
    need = _requirer(config)
    need(bool(config.env_id.strip()), "env_id", "must name an environment")
    need(config.total_steps >= 0, "total_steps", "must be >= 0")
    need(config.n_envs >= 1, "n_envs", "must be >= 1")
    need(config.n_envs <= 1024, "n_envs", "must be <= 1024")
    need(1 <= config.action_repeat <= 1000, "action_repeat", "must be between 1 and 1000")
    need(15 <= config.pixel_size <= 1024, "pixel_size", "must be between 15 (the encoder's smallest input) and 1024")
    need(1 <= config.frame_stack <= 16, "frame_stack", "must be between 1 (none) and 16")
    need(not (config.pixels and config.obs_norm), "obs_norm",
         "normalises vector observations; with pixels the encoder scales the images (pixel_range)")
    need(1 <= config.encoder_channels <= 1024, "encoder_channels", "must be between 1 and 1024")
    need(1 <= config.encoder_features <= 65_536, "encoder_features", "must be between 1 and 65536")
    need(0 <= config.augment_pad <= 64, "augment_pad", "must be between 0 (no augmentation) and 64")
    need(config.pixel_range in ("unit", "centered"), "pixel_range", "must be unit ([0, 1]) or centered ([-0.5, 0.5])")
    need(0 <= config.env_workers <= config.n_envs, "env_workers",
         f"must be between 0 (the envs stepped in-process) and n_envs={config.n_envs}")
    need(config.device in ("cpu", "gpu", "cuda", "auto"), "device", "must be cpu, gpu or auto")


def _check_collection(config: "SACConfig") -> None:
    """The replay buffer, the warm-up, exploration and HER."""
    need = _requirer(config)
    need(config.buffer_size >= 1, "buffer_size", "must be >= 1")
    need(config.batch_size >= 1, "batch_size", "must be >= 1")
    need(config.learning_starts >= 0, "learning_starts", "must be >= 0")
    need(0.0 <= config.random_action_prob <= 1.0, "random_action_prob", "must be in [0, 1]")
    need(config.exploration_noise in ("gaussian", "pink", "gsde"), "exploration_noise", "must be gaussian, pink or gsde")
    need(1 <= config.sde_sample_freq <= 1_000_000, "sde_sample_freq", "must be between 1 and 1,000,000")
    need(-20.0 <= config.sde_log_std_init <= 2.0, "sde_log_std_init", "must be in [-20, 2]")
    need(0.0 <= config.noise_beta <= 4.0, "noise_beta", "must be in [0, 4]")
    need(2 <= config.noise_sequence_length <= 1_000_000, "noise_sequence_length", "must be between 2 and 1,000,000")
    need(config.obs_norm_clip > 0.0, "obs_norm_clip", "must be > 0")
    need(config.her in ("auto", "on", "off"), "her", "must be auto, on or off")
    need(config.her_strategy in ("future", "final", "episode"), "her_strategy", "must be future, final or episode")
    need(1 <= config.her_k <= 1000, "her_k", "must be between 1 and 1000")


def _check_targets_and_critics(config: "SACConfig") -> None:
    """The critics' target, updates and variants (n-step, ensembles, quantiles, dropout)."""
    need = _requirer(config)
    need(0.0 <= config.gamma <= 1.0, "gamma", "must be in [0, 1]")
    need(0.0 < config.tau <= 1.0, "tau", "must be in (0, 1]")
    need(0.0 <= config.policy_average_tau <= 1.0, "policy_average_tau", "must be in [0, 1] (0 = off)")
    need(config.target_update_interval >= 1, "target_update_interval", "must be >= 1")
    need(config.gradient_steps >= 0, "gradient_steps", "must be >= 0")
    need(config.gradient_steps <= 10_000, "gradient_steps", "must be <= 10000")
    need(config.policy_frequency >= 1, "policy_frequency", "must be >= 1")
    need(config.policy_delay >= 1, "policy_delay", "must be >= 1")
    need(config.reset_interval >= 0, "reset_interval", "must be >= 0 (0: never)")
    need(1 <= config.n_step <= 100, "n_step", "must be between 1 and 100")
    need(1 <= config.n_critics <= 100, "n_critics", "must be between 1 and 100")
    need(not (config.crossq and config.critic_layer_norm), "critic_layer_norm",
         "cannot be combined with crossq, which normalises with batch renormalisation")
    need(config.target_critics in ("auto", "on", "off"), "target_critics", "must be auto, on or off")
    need(not (config.target_encoder and not config.has_target_critics), "target_encoder",
         "copies the encoder for the target critics, and these critics have none (target_critics=on gives them)")
    need(0 <= config.n_quantiles <= 1000, "n_quantiles", "must be between 0 (SAC's critics) and 1000")
    need(config.top_quantiles_to_drop_per_net >= 0 and (
        config.n_quantiles == 0 or config.top_quantiles_to_drop_per_net < config.n_quantiles),
        "top_quantiles_to_drop_per_net", f"must be >= 0 and below n_quantiles={config.n_quantiles}")
    need(0.0 <= config.critic_dropout < 1.0, "critic_dropout", "must be in [0, 1)")
    need(not (config.critic_dropout > 0 and config.crossq), "critic_dropout",
         "cannot be combined with crossq (dropout inside batch renormalisation's statistics is not CrossQ)")


def _check_networks(config: "SACConfig") -> None:
    """The networks and how they train: kind, widths, normalisation, weight decay, Adam's b1, the entropy target's
    scale, matmul precision."""
    need = _requirer(config)
    need(config.network in ("mlp", "simba"), "network", "must be mlp or simba")
    if config.network == "simba":
        need(not config.crossq, "network", "simba cannot be combined with crossq (SimBa normalises with LayerNorm)")
        need(not config.critic_layer_norm, "critic_layer_norm", "is built into network=simba (pre-LayerNorm blocks)")
        need(config.critic_dropout == 0, "critic_dropout", "applies to mlp critics (network=mlp)")
        for key in ("hidden_sizes", "actor_hidden_sizes", "critic_hidden_sizes"):
            need(len(set(getattr(config, key))) <= 1, key,
                 "with network=simba every entry is a residual block of the one width (e.g. 512,512)")
    for key in ("actor_hidden_sizes", "critic_hidden_sizes"):
        need(all(1 <= h <= 65_536 for h in getattr(config, key)), key, "widths must be between 1 and 65536")
    need(config.weight_decay >= 0.0, "weight_decay", "must be >= 0")
    need(config.weight_decay_layers in ("all", "output"), "weight_decay_layers", "must be all or output")
    need(config.target_entropy_scale > 0.0, "target_entropy_scale", "must be > 0 (target_entropy sets any other target)")
    need(not config.crossq or config.batch_size >= 2, "batch_size", "must be >= 2 with crossq (batch statistics)")
    need(config.crossq or not config.weight_norm, "weight_norm",
         "needs crossq (its batch renormalisation is what makes the weights' scale free)")
    need(0.0 < config.batch_norm_momentum < 1.0, "batch_norm_momentum", "must be in (0, 1)")
    need(config.batch_renorm_warmup >= 0, "batch_renorm_warmup", "must be >= 0")
    need(0.0 <= config.adam_b1 < 1.0, "adam_b1", "must be in [0, 1)")
    need(len(config.hidden_sizes) >= 1, "hidden_sizes", "needs at least one layer")
    need(all(1 <= h <= 65_536 for h in config.hidden_sizes), "hidden_sizes", "widths must be between 1 and 65536")
    need(config.activation in ACTIVATIONS, "activation", f"must be one of {', '.join(ACTIVATIONS)}")
    need(config.init in ("default", "orthogonal"), "init", "must be default or orthogonal")
    need(config.matmul_dtype in ("float32", "bfloat16", "auto"), "matmul_dtype", "must be float32, bfloat16 or auto")


def _check_optimisers_and_policy(config: "SACConfig") -> None:
    """Learning rates, alpha and the policy's log std."""
    need = _requirer(config)
    for key in ("actor_lr", "critic_lr", "alpha_lr"):
        need(0.0 < getattr(config, key) < 1.0, key, "must be in (0, 1)")
    need(config.lr_schedule in ("constant", "linear"), "lr_schedule", "must be constant or linear")
    need(0.0 <= config.lr_end_fraction <= 1.0, "lr_end_fraction", "must be in [0, 1]")
    need(config.alpha > 0.0 if config.autotune_alpha else config.alpha >= 0.0, "alpha",
         "must be > 0 (>= 0 when fixed)")
    need(config.target_entropy == "auto" or isinstance(config.target_entropy, float), "target_entropy",
         "must be auto or a number")
    need(config.log_std_min < config.log_std_max, "log_std_min", "must be below log_std_max")
    need(config.log_std_mode in ("clamp", "tanh"), "log_std_mode", "must be clamp or tanh")


def _check_outputs(config: "SACConfig") -> None:
    """Evaluation, logs, checkpoints and loggers."""
    need = _requirer(config)
    need(config.eval_interval >= 0, "eval_interval", "must be >= 0 (0 disables)")
    need(config.eval_episodes >= 1, "eval_episodes", "must be >= 1")
    need(config.log_interval >= 1, "log_interval", "must be >= 1")
    need(config.checkpoint_interval >= 0, "checkpoint_interval", "must be >= 0")
    try:
        parse_backends(config.loggers)
    except SoftacError as exc:
        raise ConfigError(f"loggers={config.loggers!r}: {exc}") from None


# in the order validate() runs them: the first failing key is the one reported
CHECKS = (_check_env_and_images, _check_collection, _check_targets_and_critics, _check_networks,
          _check_optimisers_and_policy, _check_outputs)


ACTIVATIONS = ("relu", "tanh", "elu", "gelu")
GENERIC_PRESETS = ("default", "sb3", "cleanrl", "crossq", "crossq-avg", "crossq-wn", "sac-100k", "tqc", "simba", "droq",
                   "drq")
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


# ---- presets ------------------------------------------------------------

def _preset_dir():
    return resources.files("softac.config") / "presets"


def preset_names() -> list[str]:
    return sorted(p.name[: -len(".yaml")] for p in _preset_dir().iterdir() if p.name.endswith(".yaml"))


def load_preset(name: str, _seen: tuple[str, ...] = ()) -> dict[str, Any]:
    """A preset's values; `extends: OTHER` in a preset file starts from OTHER's values (the MuJoCo env
    presets extend `crossq`, so its settings are written once)."""
    names = preset_names()
    if name not in names:
        close = difflib.get_close_matches(name, names, n=1)
        hint = f" (did you mean {close[0]}?)" if close else ""
        raise ConfigError(f"unknown preset '{name}'{hint}; `softac presets` lists them")
    if name in _seen:
        raise ConfigError(f"preset '{name}' extends itself ({' -> '.join((*_seen, name))})")
    data = _preset_file_values(name)
    base = data.pop("extends", None)
    return {**load_preset(str(base), (*_seen, name)), **data} if base else data


def _preset_text(name: str) -> str:
    return (_preset_dir() / f"{name}.yaml").read_text()


def _preset_file_values(name: str) -> dict[str, Any]:
    """What the preset's own file sets, `extends` included."""
    return dict(yaml.safe_load(_preset_text(name)) or {})


def preset_extends(name: str) -> str | None:
    """The preset a preset's file starts from (`extends:`), or None."""
    base = _preset_file_values(name).get("extends")
    return str(base) if base else None


def _preset_comments(name: str) -> list[str]:
    return [line.lstrip("#").strip() for line in _preset_text(name).splitlines() if line.startswith("#")]


def preset_summary(name: str) -> str:
    """The first comment line of a preset file: what it is for, in one sentence (`softac presets` lists it)."""
    comments = _preset_comments(name)
    return comments[0] if comments else ""


def preset_description(name: str) -> str:
    """The comment lines after the summary: settings, sources, departures and figures (`softac presets NAME`)."""
    return "\n".join(_preset_comments(name)[1:])
