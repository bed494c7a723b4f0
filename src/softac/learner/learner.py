"""`Learner`: what the agent knows and how it acts and learns.

It holds the networks, their optimisers and alpha (`sac.SACState`), the running observation statistics
(obs_norm) and the action scaling, and the jitted functions `build.build` made for them. It acts on
observations (`act` while training; `predict`, the deterministic policy that evaluation runs, and
`sample` for users), learns from a batch (`update`), and gives and takes its arrays for checkpoints. It
knows no env, buffer, run directory or agent: the training loop hands it observations and batches, and
`softac.SAC` builds it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from softac.config.sac_config import SACConfig
from softac.envs.make import SpaceInfo
from softac.errors import CheckpointError, SoftacError
from softac.learner.normalization import RunningObsNorm, RunningReturnScale

if TYPE_CHECKING:  # sac imports JAX, which loads only when a learner is made
    from softac.learner.build import SACFunctions
    from softac.learner.sac import SACState

STATE_PREFIX = "state"  # checkpoint array names: state<path of the leaf in SACState>, obs_norm/<name>
# SACState's variant fields sat beside SAC's before issue 65 put them in SACState.variants: checkpoints written
# then name `state.actor_stats...` what is now `state.variants.actor_stats...` (the same leaves, in the same order)
VARIANTS_PATH = STATE_PREFIX + ".variants."
OBS_NORM_PREFIX = "obs_norm/"
REWARD_SCALE_PREFIX = "reward_scale/"
# which of an agent's policies to act with (Learner.policy_networks); "deployed" is the average where there is one
POLICIES = ("deployed", "actor", "average")
METRICS_PREFIX = "metric_totals/"  # the sums behind the next progress row (a resumed run's first row is whole)


def check_model_memory(config: SACConfig, obs_dim: int, act_dim: int, fraction: float = 0.5,
                       image_shape: tuple[int, int, int, int] | None = None, image_state_dim: int = 0) -> None:
    """Refuse networks and batches the machine cannot hold, before allocating anything."""
    from softac.base.memory import available_memory_bytes, human_bytes, transition_bytes

    batch_row = transition_bytes(obs_dim, act_dim)
    encoder, conv_activations, actor_head = 0, 0, 0
    if image_shape is not None:  # uint8 images in the batch; the networks read the encoder's features
        from softac.learner.encoder import (conv_output_size, encoder_parameters, head_parameters, image_only_shape,
                                    smallest_image, stacked_image_shape)

        images = image_only_shape(image_shape, image_state_dim)  # [k, h, w, c] without the state's rows
        _, h, w, _ = images
        if min(h, w) < smallest_image():
            raise SoftacError(f"image observations of {h}x{w} are smaller than the encoder's smallest input, "
                              f"{smallest_image()}x{smallest_image()}; raise pixel_size")
        # two uint8 frame stacks a row (obs_dim bytes each) where ReplayBuffer's row holds two float32 vectors
        batch_row += obs_dim * (2 - 8)
        obs_dim = config.encoder_features + image_state_dim
        encoder = encoder_parameters(stacked_image_shape(images), config.encoder_channels, config.encoder_features)
        flat = conv_output_size(h) * conv_output_size(w) * config.encoder_channels  # the last feature map's size
        if config.actor_encoder_head:
            actor_head = head_parameters(flat, config.encoder_features)
        # four feature maps of about the last one's size, for obs and next_obs, kept for the backward pass
        conv_activations = 4 * 2 * 4 * flat
    from softac.learner.networks import network_kind

    kind = network_kind(config.network, config.crossq)
    actor = kind.parameters(obs_dim, config.actor_widths, 2 * act_dim)
    critics = config.n_critics * kind.parameters(obs_dim + act_dim, config.critic_widths, config.critic_outputs)
    # weights + Adam moments; critics also have targets (and the encoder with target_encoder)
    parameters = 4 * (3 * actor + 4 * critics + (3 + config.target_encoder) * encoder + 3 * actor_head)
    # activations kept for the backward passes, per gradient step (critics, targets and actor, both phases);
    # a network kind's activation_factor scales a unit's share (SimBa's 4x-wide blocks); an encoder its feature maps
    widths = sum(config.actor_widths) + sum(config.critic_widths) * config.n_critics
    activations = 4 * config.batch_size * (widths * 4 * kind.activation_factor + conv_activations)
    batch = config.batch_size * config.gradient_steps * batch_row
    need, have = parameters + activations + batch, available_memory_bytes()
    if need > fraction * have:
        raise SoftacError(f"networks and batches need about {human_bytes(need)} ({(actor + critics):,} parameters, "
                          f"batch_size={config.batch_size}) but only {human_bytes(have)} is available; "
                          "lower hidden_sizes or batch_size")


class Learner:
    """The networks, optimisers, alpha, observation statistics and action scaling of one config and env shape."""

    def __init__(self, config: SACConfig, spaces: SpaceInfo):
        if config.obs_norm and spaces.image_shape is not None:  # before anything is built or compiled
            raise SoftacError("obs_norm normalises vector observations; this env's are images, which the encoder "
                              "scales itself (pixel_range): set obs_norm=false")
        check_model_memory(config, spaces.obs_dim, spaces.act_dim, image_shape=spaces.image_shape,
                           image_state_dim=spaces.image_state_dim)
        from softac.learner import build, losses

        self.config, self.spaces = config, spaces
        self.Batch = losses.Batch
        self.functions: SACFunctions = build.build(config, spaces.obs_dim, spaces.act_dim, spaces.low, spaces.high,
                                                 spaces.image_shape, spaces.image_state_dim)
        self.scaler = self.functions.scaler
        self.state: SACState = self.functions.init(config.seed)
        self.totals: dict[str, Any] | None = None  # metric sums since the last take_metrics(), on the device
        # running observation statistics (obs_norm): updated while training, applied wherever the actor acts
        self.obs_norm = RunningObsNorm(spaces.obs_dim, config.obs_norm_clip) if config.obs_norm else None
        # the running return's spread (reward_scale): updated with each training step, divides the batches' rewards
        self.return_scale = (RunningReturnScale(config.n_envs, config.gamma, config.reward_scale, config.v_max)
                             if config.reward_scale != "off" else None)

    @property
    def target_entropy(self) -> float:
        return self.functions.target_entropy

    @property
    def matmul_dtype(self) -> str:
        """The matmul dtype as resolved (`auto` becomes float32 or bfloat16)."""
        return self.functions.matmul_dtype

    # ---- observations ---------------------------------------------------------------------------------

    def observe(self, obs: np.ndarray) -> None:
        """Count observations the policy acts on while training into the running statistics (obs_norm)."""
        if self.obs_norm is not None:
            self.obs_norm.update(obs)

    def observe_rewards(self, rewards: np.ndarray, dones: np.ndarray) -> None:
        """Count a training step's rewards into the running return's statistics (reward_scale); `dones`: which
        envs' episodes the step ended (terminated or truncated)."""
        if self.return_scale is not None:
            self.return_scale.update(rewards, dones)

    def normalize_obs(self, obs: np.ndarray) -> np.ndarray:
        """What the networks see: raw observations, or with obs_norm the normalised ones."""
        return obs if self.obs_norm is None else self.obs_norm.normalize(obs)

    def as_batch(self, obs: Any) -> tuple[np.ndarray, bool]:
        """One observation or a batch of them as a float32 batch (images: uint8 [batch, k, h, w, c]), and whether
        it was one. A dict observation (one, or a dict of batches) is flattened in its space's key order, as the
        training envs' were."""
        image = self.spaces.image_shape
        if image is not None and isinstance(obs, dict):
            obs = self.pack_image_and_state(obs)
        if image is not None:
            obs = np.asarray(obs)
            single = obs.shape == image
            if not (single or obs.shape[1:] == image) or obs.dtype != np.uint8:
                raise SoftacError(f"observation of shape {obs.shape} ({obs.dtype}); this agent expects uint8 frame "
                                  f"stacks of shape {image} [frames, height, width, channels] (one, or a batch)")
            return (obs[None] if single else obs), single
        if isinstance(obs, dict):
            if self.spaces.layout is None:
                raise SoftacError(f"this agent's env observes a {self.spaces.obs_dim}-value vector, not a dict")
            obs = self.spaces.layout.flatten(obs)
        obs = np.asarray(obs, np.float32)
        single = obs.ndim <= 1
        batch = obs.reshape(1, -1) if single else obs.reshape(obs.shape[0], -1)
        if batch.shape[1] != self.spaces.obs_dim:
            raise SoftacError(f"observation has {batch.shape[1]} values; this agent expects {self.spaces.obs_dim}")
        return batch, single

    def pack_image_and_state(self, obs: dict[str, Any]) -> np.ndarray:
        """A dict observation of an image and state values (one, or a dict of batches) as the frame stacks the
        training envs make (pixels.ImageWithState): the image key holds a frame stack [k, h, w, c] (or one [h, w, c]
        frame with frame_stack 1; channels-first where the env gives them so), the state keys their current values."""
        layout = self.spaces.image_state
        if layout is None:
            raise SoftacError("this agent's env observes images alone, not a dict of an image and state values")
        k, _, _, channels = self.spaces.image_shape
        images = layout.image(obs[layout.image_key]) if layout.image_key in obs else None
        state = layout.state_vector(obs)  # [state_dim] or [batch, state_dim], or a one-line error
        if images is not None and images.ndim == 3 and k == 1:
            images = images[None]  # frame_stack 1: one frame is the stack
        if images is None or images.ndim not in (4, 5):
            raise SoftacError(f"observation dict's {layout.image_key!r} must hold frame stacks [{k}, h, w, {channels}] "
                              f"(one, or a batch) and its state keys {layout.state_dim} values in all")
        return layout.pack(images, np.broadcast_to(state[..., None, :], (*images.shape[:-3], layout.state_dim)))

    # ---- acting -------------------------------------------------------------------------------------

    def act(self, obs: np.ndarray, key: Any, networks: tuple[Any, Any, Any] | None = None
            ) -> tuple[np.ndarray, np.ndarray, Any]:
        """Sample actions for a batch of raw observations: (in [-1, 1], env-scaled, the next key). `networks`:
        (actor, actor_stats, encoder) to act with, the actor that explores when None."""
        actor, actor_stats, encoder = networks or self.policy_networks("actor")
        # NumPy goes straight into the jitted call: jnp.asarray would cost more than an env step
        actions, env_actions, key = self.functions.act(actor, actor_stats, self.normalize_obs(obs), key, encoder)
        return np.asarray(actions), np.asarray(env_actions), key

    def act_with_noise(self, obs: np.ndarray, noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Actions tanh(mean + std * noise) for a batch of raw observations and given standard-normal noise:
        (in [-1, 1], env-scaled)."""
        actor, actor_stats, encoder = self.policy_networks("actor")
        actions, env_actions = self.functions.act_with_noise(actor, actor_stats, self.normalize_obs(obs), noise,
                                                             encoder)
        return np.asarray(actions), np.asarray(env_actions)

    def act_deterministic(self, obs: np.ndarray, policy: str = "deployed") -> np.ndarray:
        """The env-scaled mean actions of `policy` (see policy_networks) for a batch of raw observations."""
        actor, actor_stats, encoder = self.policy_networks(policy)
        actions = self.functions.act_deterministic(actor, actor_stats, self.normalize_obs(obs), encoder)
        return self.scaler.to_env(np.asarray(actions))

    def deployed_policy(self) -> tuple[Any, Any, Any]:
        """(actor, actor_stats, encoder) that evaluation, predict, sample and export run: with policy_average_tau
        the actor's moving average, else the actor that explores."""
        from softac.learner.sac import deployed

        return deployed(self.state)

    def policy_networks(self, policy: str = "deployed") -> tuple[Any, Any, Any]:
        """(actor, actor_stats, encoder) of one of POLICIES: "deployed" (what evaluation runs), "actor" (the actor
        that explores) or "average" (its weight average, only with policy_average_tau > 0). With averaging one
        training holds two policies; comparing them on the same checkpoint says what the average bought."""
        if policy == "deployed":
            return self.deployed_policy()
        if policy == "actor":
            from softac.learner.sac import acting_actor

            return acting_actor(self.state)
        if policy == "average":
            if not self.state.variants.policy_average:
                raise SoftacError("this agent keeps no weight average of its actor (policy_average_tau is 0): "
                                  "its policies are 'actor' and 'deployed', the same one")
            return self.state.variants.policy_average
        raise SoftacError(f"policy must be one of {', '.join(POLICIES)}, got {policy!r}")

    def predict(self, obs: Any, policy: str = "deployed") -> np.ndarray:
        """The env-scaled mean action for one observation, or for each of a batch: the deterministic policy
        as a function (what evaluation runs)."""
        batch, single = self.as_batch(obs)
        actions = self.act_deterministic(batch, policy)
        return actions[0] if single else actions

    def sample(self, obs: Any, key: Any, policy: str = "deployed") -> tuple[np.ndarray, Any]:
        """An env-scaled action drawn from `policy` for one observation, or for each of a batch; and the
        key to draw with next."""
        batch, single = self.as_batch(obs)
        _, actions, key = self.act(batch, key, self.policy_networks(policy))
        return (actions[0] if single else actions), key

    # ---- learning ----------------------------------------------------------------------------------

    def update(self, batch: dict[str, np.ndarray], step: int | None = None) -> None:
        """All of a vector-env step's gradient steps in one jitted call, on a batch of raw observations
        (normalised here with the current statistics); their metrics are added to the totals on the device.
        `step`: the env steps taken so far, which a learning-rate schedule follows (lr_scale)."""
        batch = dict(batch, obs=self.normalize_obs(batch["obs"]), next_obs=self.normalize_obs(batch["next_obs"]))
        if self.return_scale is not None:
            batch["rewards"] = self.return_scale.scale_rewards(batch["rewards"])
        totals = self.totals
        if totals is None:
            # zeros, never None, after each progress row: a None would be a second pytree structure and so a
            # second compiled update (4-5 s of XLA compilation per process, even for 32-wide networks)
            from softac.learner.metrics import zero_totals

            totals = zero_totals()
        self.state, self.totals = self.functions.update(self.state, self.Batch(**batch), totals, self.lr_scale(step))

    def lr_scale(self, step: int | None) -> np.ndarray | None:
        """The learning rates' factor at env step `step` (None: constant rates). linear: 1 - (1 - lr_end_fraction)
        x step / total_steps, as SB3 computes its progress remaining after each rollout (a resumed run that
        raises total_steps stretches what is left of the schedule, as SB3's does)."""
        c = self.config
        if c.lr_schedule == "constant":
            return None
        if step is None:
            raise ValueError("lr_schedule=linear needs the env step of each update")
        progress = min(step / max(c.total_steps, 1), 1.0)
        return np.float32(1.0 - (1.0 - c.lr_end_fraction) * progress)

    def metrics(self) -> dict[str, float]:
        """Each metric's mean over the gradient steps since the last `take_metrics()` that computed it (the
        actor's over actor steps); {} before any. Reading them waits for the device."""
        from softac.learner.metrics import metric_means

        return metric_means(self.totals) if self.totals is not None else {}

    def take_metrics(self) -> dict[str, float]:
        """`metrics()`, and start the next interval's sums from zero (a progress row does this)."""
        means = self.metrics()
        self.totals = None
        return means

    def reset_networks(self, seed: int, index: int) -> None:
        """The `index`-th periodic reset (reset_interval): fresh networks and optimisers, alpha kept."""
        self.state = self.functions.reset(self.state, seed, index)

    # ---- checkpoints -------------------------------------------------------------------------------

    def arrays(self) -> dict[str, np.ndarray]:
        """Every array the learner holds, by checkpoint name (the state's leaves, the obs statistics)."""
        import jax

        arrays = {STATE_PREFIX + jax.tree_util.keystr(path): np.asarray(leaf)
                  for path, leaf in jax.tree_util.tree_flatten_with_path(self.state)[0]}
        if self.obs_norm is not None:  # in every checkpoint, best too: predict() needs them
            arrays.update({OBS_NORM_PREFIX + k: v for k, v in self.obs_norm.state_dict().items()})
        if self.return_scale is not None:
            arrays.update({REWARD_SCALE_PREFIX + k: v for k, v in self.return_scale.state_dict().items()})
        if self.totals is not None:
            arrays.update({METRICS_PREFIX + k: np.asarray(v) for k, v in self.totals.items()})
        return arrays

    def load_arrays(self, arrays: dict[str, np.ndarray], where: Any = "") -> None:
        """Take the arrays a checkpoint saved (`where` names it in errors)."""
        import jax
        import jax.numpy as jnp

        paths, treedef = jax.tree_util.tree_flatten_with_path(self.state)
        leaves = []
        for path, template in paths:
            name = STATE_PREFIX + jax.tree_util.keystr(path)
            value = arrays.get(name)
            if value is None and name.startswith(VARIANTS_PATH):
                value = arrays.get(STATE_PREFIX + "." + name[len(VARIANTS_PATH):])
            if value is None or value.shape != np.shape(template) or value.dtype != np.asarray(template).dtype:
                raise CheckpointError(f"checkpoint {where} does not match this config/env at {name}")
            # a copy the device owns: jnp.asarray may alias the NumPy array on CPU, and the update donates
            # the state's buffers (older jaxlibs then corrupt the heap; seen with jax 0.4.30 and 0.5.3)
            leaves.append(jnp.array(value, copy=True))
        self.state = jax.tree_util.tree_unflatten(treedef, leaves)
        # a checkpoint written between progress rows holds the sums so far (none: one written at a row, or older)
        totals = {k[len(METRICS_PREFIX):]: v for k, v in arrays.items() if k.startswith(METRICS_PREFIX)}
        self.totals = {k: jnp.array(v, copy=True) for k, v in totals.items()} or None
        if self.obs_norm is not None:
            stats = {k[len(OBS_NORM_PREFIX):]: v for k, v in arrays.items() if k.startswith(OBS_NORM_PREFIX)}
            if set(stats) != {"count", "mean", "m2"}:
                raise CheckpointError(f"checkpoint {where} has obs_norm on but no observation statistics")
            try:
                self.obs_norm.load_state_dict(stats)
            except SoftacError as exc:
                raise CheckpointError(f"checkpoint {where}: {exc}") from None
        if self.return_scale is not None:
            stats = {k[len(REWARD_SCALE_PREFIX):]: v for k, v in arrays.items() if k.startswith(REWARD_SCALE_PREFIX)}
            if set(stats) != {"count", "mean", "m2", "returns", "max_abs"}:
                raise CheckpointError(f"checkpoint {where} has reward_scale on but no return statistics")
            try:
                self.return_scale.load_state_dict(stats)
            except SoftacError as exc:
                raise CheckpointError(f"checkpoint {where}: {exc}") from None
