"""A softac config's settings in a peer's keywords, for the peers that run "at the same settings" (softac.peers):
SBX's CrossQ at the `crossq` preset's, SBX's TQC at a sweep's own (`--framework sbx-tqc-softac`). Every setting
that changes what is computed is carried over or checked to be the peer's own already; one the peer cannot take
is refused (ValueError naming it), so "same settings" stays true when a preset or a sweep's --set changes."""

from __future__ import annotations

import copy
from typing import Any

from softac.config.sac_config import SACConfig


def refuse_settings(peer: str, untranslatable: dict[str, bool]) -> None:
    """ValueError naming each setting `peer` cannot take (those whose test is true)."""
    bad = [name for name, differs in untranslatable.items() if differs]
    if bad:
        raise ValueError(f"settings {peer} cannot take: {', '.join(bad)}")


def untranslatable_common(c: SACConfig) -> dict[str, bool]:
    """What none of SBX's SAC family takes (nor Brax's SAC, but for those brax_sac_settings lifts): SBX's own is on
    the right of each test."""
    return {"actor_lr != alpha_lr": c.actor_lr != c.alpha_lr, "obs_norm": c.obs_norm, "n_step": c.n_step != 1,
            "policy_frequency": c.policy_frequency != 1, "reset_interval": c.reset_interval > 0,
            "activation": c.activation != "relu", "fixed alpha": not c.autotune_alpha, "n_envs": c.n_envs != 1,
            "log_std bounds": (c.log_std_mode, c.log_std_min, c.log_std_max) != ("clamp", -20.0, 2.0),
            "network": c.network != "mlp", "her": c.her == "on", "random_action_prob": c.random_action_prob > 0,
            "exploration_noise": c.exploration_noise != "gaussian",
            "lr_schedule": c.lr_schedule != "constant",
            "n_atoms (SBX has no categorical critic)": c.n_atoms > 0, "reward_scale": c.reward_scale != "off",
            "target_entropy_std": c.target_entropy_std > 0, "target_q": c.target_q != "min",
            "actor_q": c.actor_q != "min", "actor_layer_norm": c.actor_layer_norm,
            "zero_actor_head": c.zero_actor_head, "init": c.init != "default",
            "warmup_actions": c.warmup_actions != "uniform",
            "layer_norm_position": c.layer_norm_position != "before", "offline_data": bool(c.offline_data)}  # action_repeat: the peer's env (peers.py)


def crossq_settings(c: SACConfig) -> dict[str, Any]:
    """SBX's CrossQ keywords (ReLU, autotuned alpha from 1.0, target entropy -act_dim, one update per env step,
    one env are SBX's own)."""
    refuse_settings("SBX's CrossQ", {
        **untranslatable_common(c), "critic_layer_norm": c.critic_layer_norm, "not crossq": not c.crossq,
        "gradient_steps": c.gradient_steps != 1, "target_entropy": c.target_entropy != "auto"
        or c.target_entropy_scale != 1.0, "initial alpha": c.alpha != 1.0,
        "target_critics": c.target_critics == "on", "weight_norm": c.weight_norm,
        "weight_decay": c.weight_decay > 0, "n_quantiles": c.n_quantiles > 0,
        "critic_dropout": c.critic_dropout > 0, "batch_norm_eps": c.batch_norm_eps != 1e-3,
        "actor and critic widths differ": c.actor_widths != c.critic_widths})
    return {"learning_rate": c.actor_lr, "qf_learning_rate": c.critic_lr, "buffer_size": c.buffer_size,
            "learning_starts": c.learning_starts, "batch_size": c.batch_size, "gamma": c.gamma,
            "policy_delay": c.policy_delay,
            "policy_kwargs": {"net_arch": {"pi": list(c.hidden_sizes), "qf": list(c.hidden_sizes)},
                              "n_critics": c.n_critics, "batch_norm_momentum": c.batch_norm_momentum,
                              "renorm_warmup_steps": c.batch_renorm_warmup,
                              "optimizer_kwargs": {"b1": c.adam_b1, "b2": c.adam_b2}}}


def tqc_settings(c: SACConfig, act_dim: int) -> dict[str, Any]:
    """SBX's TQC keywords: two critics (SBX's TQC has two), their quantiles and the atoms dropped, the widths,
    rates, batch, UTD, policy delay, tau, gamma, the entropy target and initial alpha, Adam's b1 and AdamW's
    decay on every parameter (optax.adamw; SBX cannot mask it to the output layers)."""
    refuse_settings("SBX's TQC", {
        **untranslatable_common(c), "n_quantiles 0 (not TQC)": c.n_quantiles == 0,
        "n_critics != 2": c.n_critics != 2, "crossq": c.crossq, "target_critics off": c.target_critics == "off",
        "target_update_interval": c.target_update_interval != 1,
        "critic_layer_norm (SBX's LayerNorm learns scale and bias)": c.critic_layer_norm,
        "weight_decay on the output layers only": c.weight_decay > 0 and c.weight_decay_layers == "output"})
    settings = _sac_family(c, act_dim)
    settings["top_quantiles_to_drop_per_net"] = c.top_quantiles_to_drop_per_net
    settings["policy_kwargs"].update(n_quantiles=c.n_quantiles, dropout_rate=c.critic_dropout)
    return settings


def _sac_family(c: SACConfig, act_dim: int) -> dict[str, Any]:
    """The keywords SBX's SAC and TQC share: rates, buffer, batch, UTD, delay, tau, gamma, entropy, optimiser."""
    import optax

    optimizer: dict[str, Any] = {"optimizer_kwargs": {"b1": c.adam_b1, "b2": c.adam_b2}}
    if c.weight_decay > 0:
        optimizer = {"optimizer_class": optax.adamw,
                     "optimizer_kwargs": {"b1": c.adam_b1, "b2": c.adam_b2, "weight_decay": c.weight_decay}}
    target_entropy = (-c.target_entropy_scale * act_dim if c.target_entropy == "auto" else float(c.target_entropy))
    return {"learning_rate": c.actor_lr, "qf_learning_rate": c.critic_lr, "buffer_size": c.buffer_size,
            "learning_starts": c.learning_starts, "batch_size": c.batch_size, "tau": c.tau, "gamma": c.gamma,
            "gradient_steps": c.gradient_steps, "policy_delay": c.policy_delay, "ent_coef": f"auto_{c.alpha}",
            "target_entropy": target_entropy,
            "policy_kwargs": {"net_arch": {"pi": c.actor_widths, "qf": c.critic_widths}, **optimizer}}


def simba_settings(c: SACConfig, act_dim: int) -> dict[str, Any]:
    """SBX's SAC with its SimbaPolicy (residual blocks, one per width; LayerNorms): the SAC family's keywords and
    the number of critics. Observation normalisation goes to SB3's VecNormalize around the peer's env (the same
    running mean and variance, epsilon 1e-8 and clip as softac's obs_norm; softac.peers.peer_model)."""
    common = {k: v for k, v in untranslatable_common(c).items() if k not in ("obs_norm", "network")}
    refuse_settings("SBX's SAC with SimbaPolicy", {
        **common, "network != simba": c.network != "simba", "crossq": c.crossq, "n_quantiles": c.n_quantiles > 0,
        "target_critics off": c.target_critics == "off", "target_update_interval": c.target_update_interval != 1,
        "critic_dropout": c.critic_dropout > 0,
        "weight_decay on the output layers only": c.weight_decay > 0 and c.weight_decay_layers == "output"})
    settings = _sac_family(c, act_dim)
    settings["policy_kwargs"]["n_critics"] = c.n_critics
    return settings


BRAX_ALPHA_LR = 3e-4  # brax/training/agents/sac/train.py: optax.adam(learning_rate=3e-4) for alpha, fixed
BRAX_LOG_STD_MIN = -6.9078  # log(0.001), brax/training/distribution.py NormalTanhDistribution's min_std, to 4 places


def brax_sac_settings(c: SACConfig, act_dim: int) -> dict[str, Any]:
    """`brax.training.agents.sac.train`'s keywords for config `c` (ValueError naming what Brax cannot take): the
    env's own keywords (episode length, its action repeat, the env) and the run's (steps, evaluations, seed,
    progress) are the runner's. Brax's SAC has one learning rate for actor and critics, alpha's fixed at 3e-4
    from alpha 1, two critics, the target entropy -|A|/2, one MLP width list for both networks, a running
    observation normaliser without a clip, LeCun-uniform weights, LayerNorm after each hidden activation, a std of
    softplus + 0.001, and a replay prefilled by its initial policy: each of those a setting a config must match."""
    common = {k: v for k, v in untranslatable_common(c).items()
              if k not in ("obs_norm", "n_envs", "actor_lr != alpha_lr", "activation", "log_std bounds", "init",
                           "warmup_actions", "layer_norm_position")}
    refuse_settings("Brax's SAC", {
        **common, "actor_lr != critic_lr (Brax has one rate)": c.actor_lr != c.critic_lr,
        f"alpha_lr != {BRAX_ALPHA_LR:g} (Brax's)": c.alpha_lr != BRAX_ALPHA_LR,
        "initial alpha != 1 (Brax's)": c.alpha != 1.0,
        "target entropy other than -|A|/2 (Brax's)": c.target_entropy != "auto" or c.target_entropy_scale != 0.5,
        "n_critics != 2": c.n_critics != 2, "crossq": c.crossq, "n_quantiles": c.n_quantiles > 0,
        "target_critics off": c.target_critics == "off", "target_update_interval": c.target_update_interval != 1,
        "policy_delay": c.policy_delay != 1, "critic_dropout": c.critic_dropout > 0, "weight_decay": c.weight_decay > 0,
        "Adam's b1/b2": (c.adam_b1, c.adam_b2) != (0.9, 0.999), "policy_average_tau": c.policy_average_tau > 0,
        "actor and critic widths differ (Brax has one list)": c.actor_widths != c.critic_widths,
        "zero_actor_head": c.zero_actor_head,
        "log_std other than softplus with floor 0.001 (Brax's)": (c.log_std_mode, round(c.log_std_min, 4))
        != ("softplus", BRAX_LOG_STD_MIN),
        "init other than lecun_uniform (Brax's)": c.init != "lecun_uniform",
        "warmup_actions other than policy (Brax's prefill)": c.warmup_actions != "policy",
        "layer_norm_position other than after (Brax's MLP)": (c.critic_layer_norm or c.actor_layer_norm)
        and c.layer_norm_position != "after"})
    return {"num_envs": c.n_envs, "learning_rate": c.critic_lr, "discounting": c.gamma, "batch_size": c.batch_size,
            "normalize_observations": c.obs_norm, "tau": c.tau, "min_replay_size": c.learning_starts,
            "max_replay_size": c.buffer_size, "grad_updates_per_step": c.gradient_steps, "deterministic_eval": True,
            "network": {"hidden_layer_sizes": list(c.critic_widths), "activation": c.activation,
                        "q_network_layer_norm": c.critic_layer_norm, "policy_network_layer_norm": c.actor_layer_norm}}


# the peers that run at a sweep's own settings, and how their keywords are made
SWEEP_TRANSLATORS = {"sbx-tqc-softac": tqc_settings, "sbx-simba-softac": simba_settings,
                     "brax-sac": brax_sac_settings}


# ---- RL Zoo's tuned SAC settings (the classic set of issue 43) ------------------------------------------
# DLR-RM/rl-baselines3-zoo, hyperparams/sac.yml at commit 00128b5d46d497b772f3bd891ae9f520919e8971, as SB3's
# SAC keywords (`--framework sb3-zoo`); n_timesteps is the sweep's --steps (a linear schedule decays over it).
# RL Zoo lists LunarLanderContinuous-v2; Gymnasium 1.x has only -v3 (same dynamics and reward).
class LinearSchedule:
    """RL Zoo's `lin_X`: a learning rate decayed linearly from X to 0 over the run (SB3 calls it with the
    progress remaining, 1 -> 0). A class, not a lambda, so that config.yaml names it and SB3's zip loads it."""

    def __init__(self, initial: float):
        self.initial = float(initial)

    def __call__(self, progress_remaining: float) -> float:
        return progress_remaining * self.initial

    def __repr__(self) -> str:
        return f"lin_{self.initial:g}"


# env -> SB3 SAC's keywords (the rest SB3's defaults); "Tuned" where RL Zoo marks the entry so
RL_ZOO_SAC: dict[str, dict[str, Any]] = {
    "Pendulum-v1": {"learning_rate": 1e-3},
    "MountainCarContinuous-v0": {  # "Tuned"
        "learning_rate": 3e-4, "buffer_size": 50_000, "batch_size": 512, "ent_coef": 0.1, "train_freq": 32,
        "gradient_steps": 32, "gamma": 0.9999, "tau": 0.01, "learning_starts": 0, "use_sde": True,
        "policy_kwargs": {"log_std_init": -3.67, "net_arch": [64, 64]}},
    "LunarLanderContinuous-v3": {
        "learning_rate": LinearSchedule(7.3e-4), "buffer_size": 1_000_000, "batch_size": 256, "ent_coef": "auto",
        "gamma": 0.99, "tau": 0.01, "train_freq": 1, "gradient_steps": 1, "learning_starts": 10_000,
        "policy_kwargs": {"net_arch": [400, 300]}},
    "BipedalWalker-v3": {  # "Tuned"
        "learning_rate": 7.3e-4, "buffer_size": 300_000, "batch_size": 256, "ent_coef": "auto", "gamma": 0.98,
        "tau": 0.02, "train_freq": 64, "gradient_steps": 64, "learning_starts": 10_000, "use_sde": True,
        "policy_kwargs": {"log_std_init": -3, "net_arch": [400, 300]}},
}


def rl_zoo_sac_settings(env_id: str) -> dict[str, Any]:
    """SB3 SAC's keywords at RL Zoo's tuned settings for `env_id` (ValueError where RL Zoo has none here)."""
    if env_id not in RL_ZOO_SAC:
        raise ValueError(f"RL Zoo's SAC settings are here for {', '.join(RL_ZOO_SAC)}; not for {env_id}")
    return copy.deepcopy(RL_ZOO_SAC[env_id])  # SB3 may change policy_kwargs in place
