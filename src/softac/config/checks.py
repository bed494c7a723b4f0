"""SACConfig's checks, section by section, each taking a SACConfig, in the order `SACConfig.validate` runs
them: the first failing key is the one reported, in a ConfigError naming it, its value and what it must be."""

from __future__ import annotations

from typing import Any

from softac.config.names import NETWORK_NAMES, parse_backends
from softac.errors import ConfigError, SoftacError


def _requirer(config: Any):
    """need(ok, key, what): a ConfigError naming key, its value and what it must be, unless ok."""
    def need(ok: bool, key: str, what: str) -> None:
        if not ok:
            raise ConfigError(f"{key}={getattr(config, key)!r}: {what}")
    return need


def _check_env_and_images(config: Any) -> None:
    """The env, its images and how its steps are run."""
    need = _requirer(config)
    need(bool(config.env_id.strip()), "env_id", "must name an environment")
    need(config.total_steps >= 0, "total_steps", "must be >= 0")
    need(config.n_envs >= 1, "n_envs", "must be >= 1")
    need(config.collect_on in ("auto", "host", "device"), "collect_on", "must be auto, host or device")
    device = config.collects_on_device
    # the device's envs are vmapped arrays (FastTD3 and FastSAC run 1024-4096); the host's are objects, one by one
    need(config.n_envs <= (65536 if device else 1024), "n_envs", f"must be <= {65536 if device else 1024}"
         + ("" if device else " (more envs: MuJoCo Playground's on the device, collect_on=device)"))
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


def _check_collection(config: Any) -> None:
    """The replay buffer, the warm-up, exploration and HER."""
    need = _requirer(config)
    need(config.buffer_size >= 1, "buffer_size", "must be >= 1")
    need(config.batch_size >= 1, "batch_size", "must be >= 1")
    need(config.learning_starts >= 0, "learning_starts", "must be >= 0")
    need(config.warmup_actions in ("uniform", "policy"), "warmup_actions", "must be uniform or policy")
    need(0.0 <= config.random_action_prob <= 1.0, "random_action_prob", "must be in [0, 1]")
    need(config.exploration_noise in ("gaussian", "pink", "gsde", "repeat"), "exploration_noise",
         "must be gaussian, pink, gsde or repeat")
    need(0.0 <= config.noise_repeat_mu <= 100.0, "noise_repeat_mu", "must be in [0, 100]")
    need(1 <= config.noise_repeat_max <= 100_000, "noise_repeat_max", "must be between 1 and 100,000")
    need(1 <= config.sde_sample_freq <= 1_000_000, "sde_sample_freq", "must be between 1 and 1,000,000")
    need(-20.0 <= config.sde_log_std_init <= 2.0, "sde_log_std_init", "must be in [-20, 2]")
    need(0.0 <= config.noise_beta <= 4.0, "noise_beta", "must be in [0, 4]")
    need(2 <= config.noise_sequence_length <= 1_000_000, "noise_sequence_length", "must be between 2 and 1,000,000")
    need(config.obs_norm_clip > 0.0, "obs_norm_clip", "must be > 0")
    need(config.her in ("auto", "on", "off"), "her", "must be auto, on or off")
    need(config.offline_mode in ("mix", "prefill"), "offline_mode", "must be mix or prefill")
    need(0.0 < config.offline_fraction < 1.0, "offline_fraction",
         "must be in (0, 1): each batch part offline, part online (offline_mode prefill samples one replay)")
    if config.offline_data:
        need(config.n_step == 1, "n_step", "offline_data's transitions are one-step: set n_step=1")
        need(not (config.offline_mode == "prefill" and config.buffer_obs_once), "buffer_obs_once",
             "offline_mode prefill copies whole transitions: set buffer_obs_once=false")
    need(config.her_strategy in ("future", "final", "episode"), "her_strategy", "must be future, final or episode")
    need(1 <= config.her_k <= 1000, "her_k", "must be between 1 and 1000")


def _check_device_collection(config: Any) -> None:
    """What the device's collection (issue 67) runs: Playground's envs, exploration from the policy (white, pink,
    held as FlashSAC's, or gSDE's; with random_action_prob's uniform rows), n-step targets (observations raw or normalised, obs_norm; rewards raw or
    scaled, reward_scale), offline data mixed into each batch or prefilled; the host's parts it has no counterpart of
    yet are refused by name."""
    if not config.collects_on_device:
        return
    need = _requirer(config)
    from softac.config.names import is_playground_id

    need(is_playground_id(config.env_id), "collect_on",
         f"device collection steps MuJoCo Playground's envs (playground:NAME), not {config.env_id}: use collect_on=host")
    host_only = "is not run by device collection yet (collect_on=device): set it off, or collect_on=host"
    need(config.env_workers == 0, "env_workers", "device collection steps its envs inside the update's jit: set 0")
    need(not config.pixels, "pixels", host_only)


def _check_targets_and_critics(config: Any) -> None:
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
    need(config.layer_norm_position in ("before", "after"), "layer_norm_position", "must be before or after")
    need(not config.layer_norm_affine or config.critic_layer_norm or config.actor_layer_norm, "layer_norm_affine",
         "needs critic_layer_norm or actor_layer_norm")
    need(config.target_critics in ("auto", "on", "off"), "target_critics", "must be auto, on or off")
    need(config.target_q in ("min", "each", "subset"), "target_q", "must be min, each or subset")
    if config.target_q == "subset":
        need(1 <= config.target_q_subset <= config.n_critics, "target_q_subset",
             f"must be between 1 and n_critics ({config.n_critics})")
        need(config.n_atoms == 0 and config.n_quantiles == 0, "target_q",
             "subset draws scalar critics (REDQ's): not with n_atoms or n_quantiles")
    need(config.actor_q in ("min", "mean"), "actor_q", "must be min or mean")
    need(not (config.n_quantiles and config.target_q != "min"), "target_q",
         "TQC's quantile critics pool their atoms for the target (n_quantiles > 0): leave target_q at min")
    need(not (config.target_encoder and not config.has_target_critics), "target_encoder",
         "copies the encoder for the target critics, and these critics have none (target_critics=on gives them)")
    need(0 <= config.n_quantiles <= 1000, "n_quantiles", "must be between 0 (SAC's critics) and 1000")
    need(config.top_quantiles_to_drop_per_net >= 0 and (
        config.n_quantiles == 0 or config.top_quantiles_to_drop_per_net < config.n_quantiles),
        "top_quantiles_to_drop_per_net", f"must be >= 0 and below n_quantiles={config.n_quantiles}")
    need(config.n_atoms == 0 or 2 <= config.n_atoms <= 1000, "n_atoms",
         "must be 0 (one Q-value per critic) or between 2 and 1000")
    need(not (config.n_atoms and config.n_quantiles), "n_atoms",
         f"categorical critics cannot also be quantile critics (n_quantiles={config.n_quantiles}): set one of them")
    need(config.categorical_target in ("c51", "two_hot", "hl_gauss"), "categorical_target",
         "must be c51, two_hot or hl_gauss")
    need(config.v_min < config.v_max, "v_min", f"must be below v_max={config.v_max}")
    need(config.reward_scale in ("off", "std", "std_max"), "reward_scale", "must be off, std or std_max")
    need(config.reward_scale != "std_max" or config.v_max > 0, "reward_scale",
         f"std_max keeps the largest return below v_max, which must then be > 0 (v_max={config.v_max})")
    need(0.0 < config.hl_gauss_sigma <= 100.0, "hl_gauss_sigma", "must be in (0, 100] atom spacings")
    need(0.0 <= config.critic_dropout < 1.0, "critic_dropout", "must be in [0, 1)")
    need(not (config.critic_dropout > 0 and config.crossq), "critic_dropout",
         "cannot be combined with crossq (dropout inside batch renormalisation's statistics is not CrossQ)")


def _check_networks(config: Any) -> None:
    """The networks and how they train: kind, widths, normalisation, weight decay, Adam's b1, the entropy target's
    scale, matmul precision."""
    need = _requirer(config)
    need(config.network in NETWORK_NAMES, "network", f"must be one of {', '.join(NETWORK_NAMES)}")
    if config.network == "simba":
        need(not config.crossq, "network", "simba cannot be combined with crossq (SimBa normalises with LayerNorm)")
        need(not config.critic_layer_norm, "critic_layer_norm", "is built into network=simba (pre-LayerNorm blocks)")
        need(config.critic_dropout == 0, "critic_dropout", "applies to mlp critics (network=mlp)")
        for key in ("hidden_sizes", "actor_hidden_sizes", "critic_hidden_sizes"):
            need(len(set(getattr(config, key))) <= 1, key,
                 "with network=simba every entry is a residual block of the one width (e.g. 512,512)")
    need(config.network not in ("bn_mlp", "flashsac") or config.crossq, "network",
         f"{config.network} normalises with batch statistics: it needs crossq=true (the joint pass and the running "
         "statistics)")
    if config.network == "flashsac":
        for key in ("hidden_sizes", "actor_hidden_sizes", "critic_hidden_sizes"):
            need(len(set(getattr(config, key))) <= 1, key,
                 "with network=flashsac every entry is a residual block of the one width (e.g. 256,256)")
    need(0.0 < config.batch_norm_eps <= 1.0, "batch_norm_eps", "must be in (0, 1]")
    for key in ("actor_hidden_sizes", "critic_hidden_sizes"):
        need(all(1 <= h <= 65_536 for h in getattr(config, key)), key, "widths must be between 1 and 65536")
    need(config.weight_decay >= 0.0, "weight_decay", "must be >= 0")
    need(config.weight_decay_layers in ("all", "output"), "weight_decay_layers", "must be all or output")
    need(0.0 <= config.target_entropy_std <= 100.0, "target_entropy_std", "must be in [0, 100] (0: off)")
    need(config.target_entropy_scale > 0.0, "target_entropy_scale", "must be > 0 (target_entropy sets any other target)")
    need(not config.crossq or config.batch_size >= 2, "batch_size", "must be >= 2 with crossq (batch statistics)")
    need(config.crossq or not config.weight_norm, "weight_norm",
         "needs crossq (its batch renormalisation is what makes the weights' scale free)")
    need(0.0 < config.batch_norm_momentum < 1.0, "batch_norm_momentum", "must be in (0, 1)")
    need(config.batch_renorm_warmup >= 0, "batch_renorm_warmup", "must be >= 0")
    need(0.0 <= config.adam_b1 < 1.0, "adam_b1", "must be in [0, 1)")
    need(0.0 <= config.adam_b2 < 1.0, "adam_b2", "must be in [0, 1)")
    need(not (config.zero_actor_head and config.weight_norm), "zero_actor_head",
         "cannot be combined with weight_norm, which keeps the weights on the unit sphere")
    need(not config.actor_layer_norm or (config.network == "mlp" and not config.crossq), "actor_layer_norm",
         "applies to plain MLP actors (network=mlp without crossq, which normalises with batch renormalisation)")
    need(len(config.hidden_sizes) >= 1, "hidden_sizes", "needs at least one layer")
    need(all(1 <= h <= 65_536 for h in config.hidden_sizes), "hidden_sizes", "widths must be between 1 and 65536")
    need(config.activation in ACTIVATIONS, "activation", f"must be one of {', '.join(ACTIVATIONS)}")
    need(config.init in ("default", "orthogonal", "lecun_uniform", "xavier_uniform"), "init",
         "must be default, orthogonal, lecun_uniform or xavier_uniform")
    need(config.matmul_dtype in ("float32", "bfloat16", "auto"), "matmul_dtype", "must be float32, bfloat16 or auto")


def _check_optimisers_and_policy(config: Any) -> None:
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
    need(config.log_std_mode in ("clamp", "tanh", "softplus"), "log_std_mode", "must be clamp, tanh or softplus")


def _check_outputs(config: Any) -> None:
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
CHECKS = (_check_env_and_images, _check_collection, _check_device_collection, _check_targets_and_critics,
          _check_networks, _check_optimisers_and_policy, _check_outputs)


ACTIVATIONS = ("relu", "tanh", "elu", "gelu", "silu")
