"""Image observations (issue 44): the DrQ encoder against a hand computation, the random-shift augmentation's
statistics, and the frame-once replay buffer against a plain buffer of the same transitions."""

from __future__ import annotations

import numpy as np
import pytest

from softac.replay.buffer import ReplayBuffer
from softac.learner.encoder import (CONV_STRIDES, conv_features, conv_output_size, encode, encoder_parameters, init_encoder,
                            random_shift, smallest_image, stack_channels)
from softac.errors import SoftacError
from softac.replay.image_buffer import FrameReplayBuffer
from softac.learner.metrics import zero_totals

jax = pytest.importorskip("jax")
jnp = jax.numpy


# ---- the encoder -------------------------------------------------------------------------------------------

def test_conv_output_sizes_follow_drq():
    assert [conv_output_size(84, CONV_STRIDES[:i]) for i in range(5)] == [84, 41, 39, 37, 35]
    assert conv_output_size(smallest_image()) == 1
    assert conv_output_size(smallest_image() - 1) < 1


def _conv_reference(x: np.ndarray, w: np.ndarray, b: np.ndarray, stride: int) -> np.ndarray:
    """A VALID 2-D convolution (cross-correlation, as every DL framework), [h, w, c_in] -> [h', w', c_out]."""
    k = w.shape[0]
    out_h, out_w = (x.shape[0] - k) // stride + 1, (x.shape[1] - k) // stride + 1
    out = np.zeros((out_h, out_w, w.shape[-1]))
    for i in range(out_h):
        for j in range(out_w):
            patch = x[i * stride:i * stride + k, j * stride:j * stride + k]  # [k, k, c_in]
            out[i, j] = np.einsum("abc,abcd->d", patch, w) + b
    return out


@pytest.mark.parametrize("offset", [0.0, 0.5])  # pixel_range unit (DrQ's [0, 1]) and centered ([-0.5, 0.5])
def test_encoder_matches_a_hand_computation(offset):
    rng = np.random.default_rng(0)
    shape = (15, 13, 6)
    params = init_encoder(rng, shape, channels=4, features=5)
    # random weights everywhere (the delta-orthogonal init is mostly zeros, which would hide index mistakes)
    params = {"convs": [{"w": rng.normal(size=c["w"].shape).astype(np.float32) * 0.3,
                         "b": rng.normal(size=c["b"].shape).astype(np.float32) * 0.1} for c in params["convs"]],
              "head": {k: rng.normal(size=v.shape).astype(np.float32) * 0.3 for k, v in params["head"].items()}}
    images = rng.integers(0, 256, (2, *shape), dtype=np.uint8)
    expected = []
    for image in images:
        x = image.astype(np.float64) / 255.0 - offset
        for layer, stride in zip(params["convs"], CONV_STRIDES):
            x = np.maximum(_conv_reference(x, layer["w"], layer["b"], stride), 0.0)
        h = x.reshape(-1) @ params["head"]["w"] + params["head"]["b"]
        h = (h - h.mean()) / np.sqrt(h.var() + 1e-5) * params["head"]["ln_scale"] + params["head"]["ln_bias"]
        expected.append(np.tanh(h))
    got = np.asarray(jax.jit(encode, static_argnums=(2, 3))(params, images, 0, offset))
    assert got.shape == (2, 5)
    # float32 convolutions of a few hundred terms, then tanh: errors of order 1e-6 relative; 1e-4 leaves room
    np.testing.assert_allclose(got, np.array(expected), rtol=0, atol=1e-4)
    assert np.asarray(conv_features(params, images)).shape == (2, conv_output_size(15) * conv_output_size(13) * 4)


def test_encoder_init_is_drq_and_counts_its_parameters():
    rng = np.random.default_rng(1)
    params = init_encoder(rng, (84, 84, 9))
    first = params["convs"][0]["w"]
    assert first.shape == (3, 3, 9, 32)
    centre = first[1, 1]  # delta-orthogonal: an orthogonal 9x32 matrix (gain sqrt 2) at the centre, zero elsewhere
    np.testing.assert_allclose(centre @ centre.T, 2.0 * np.eye(9), atol=1e-5)
    assert np.count_nonzero(first) == np.count_nonzero(centre)
    assert params["head"]["w"].shape == (35 * 35 * 32, 50)
    count = sum(np.size(leaf) for leaf in jax.tree_util.tree_leaves(params))
    assert count == encoder_parameters((84, 84, 9))
    features = np.asarray(encode(params, np.zeros((1, 84, 84, 9), np.uint8)))
    assert features.shape == (1, 50) and np.all(np.abs(features) < 1.0)


def test_the_encoder_in_pieces_gives_each_image_the_features_and_gradients_of_the_whole_batch():
    """chunked_encode (the CPU update's) is `encode` of each image: the same features and parameter gradients,
    a remainder piece included (10 images in pieces of 4)."""
    params = jax.tree_util.tree_map(jnp.asarray, init_encoder(np.random.default_rng(0), (16, 16, 6), 8, 12))
    images = jnp.asarray(np.random.default_rng(1).integers(0, 256, (10, 16, 16, 6), dtype=np.uint8))
    # jitted, as the update runs it (op by op the test spent ~20 s compiling each op: issue 64)
    jit_encode = jax.jit(encode, static_argnums=2)
    whole, pieces = jit_encode(params, images, 0), jit_encode(params, images, 4)
    # the same float32 sums compiled for two batch shapes may round apart by a few units of 2^-24 of the
    # LayerNorm's and tanh's inputs (order ~1); 1e-5 leaves room
    assert pieces.shape == whole.shape and np.abs(np.asarray(pieces) - np.asarray(whole)).max() < 1e-5
    weights = jnp.asarray(np.random.default_rng(2).normal(size=whole.shape), jnp.float32)
    grads = [jax.jit(jax.grad(lambda p, c=c: jnp.sum(encode(p, images, c) * weights)))(params) for c in (0, 4)]
    for a, b in zip(*map(jax.tree_util.tree_leaves, grads)):
        scale = np.abs(np.asarray(a)).max() + 1e-6
        assert np.abs(np.asarray(a) - np.asarray(b)).max() <= 1e-4 * scale


def test_a_black_image_reads_as_zero_at_the_unit_range_and_not_at_the_centered_one():
    """DrQ's obs / 255: at [0, 1] the fresh convolutions (zero biases) give a black background zero, so only what is
    drawn moves the features; at [-0.5, 0.5] the background itself gives large activations (issue 44: the
    pendulum's dark scene)."""
    params = jax.tree_util.tree_map(jnp.asarray, init_encoder(np.random.default_rng(0), (16, 16, 6), 8, 12))
    black = jnp.zeros((2, 16, 16, 6), jnp.uint8)
    assert np.all(np.asarray(conv_features(params, black)) == 0.0)
    assert np.abs(np.asarray(conv_features(params, black, 0.5))).max() > 0.1


def test_checkpoints_and_numpy_exports_from_before_pixel_range_keep_the_centered_pixels(tiny, tmp_path):
    """A checkpoint whose config has no pixel_range, or a NumPy export without pixel_offset, was made when
    softac scaled pixels to [-0.5, 0.5]: loaded, it acts as it did."""
    import json

    from softac import SAC
    from softac.outputs.export import export_policy
    from softac.learner.numpy_forward import policy_forward

    agent = SAC(tiny("softac_test_envs:DotImage-v0", **IMAGE, learning_starts=100, pixel_range="centered"))
    agent.learn(150, progress=False)
    path = agent.save(tmp_path / "agent")
    meta_path = path / "meta.json"
    meta = json.loads(meta_path.read_text())
    del meta["config"]["pixel_range"]
    meta_path.write_text(json.dumps(meta))
    loaded = SAC.load(path)
    assert loaded.config.pixel_range == "centered"
    env = agent.make_env()
    obs = np.stack([env.reset(seed=seed)[0] for seed in range(4)])
    env.close()
    np.testing.assert_array_equal(loaded.predict(obs), agent.predict(obs))
    meta["config"]["pixel_range"] = "unit"  # the same weights read at the other range act otherwise
    meta_path.write_text(json.dumps(meta))
    assert np.abs(SAC.load(path).predict(obs) - agent.predict(obs)).max() > 1e-3
    with np.load(export_policy(agent, tmp_path / "policy.npz", "numpy")) as npz:
        params = dict(npz)
    old = {key: value for key, value in params.items() if key != "pixel_offset"}
    np.testing.assert_array_equal(policy_forward(old, obs), policy_forward(params, obs))


def test_encoder_is_differentiable_in_its_parameters():
    rng = np.random.default_rng(2)
    params = init_encoder(rng, (15, 15, 3), channels=4, features=3)
    images = rng.integers(0, 256, (4, 15, 15, 3), dtype=np.uint8)
    grads = jax.grad(lambda p: jnp.sum(encode(p, images) * jnp.arange(3.0)))(params)
    assert all(np.all(np.isfinite(g)) for g in jax.tree_util.tree_leaves(grads))
    assert np.any(np.asarray(grads["convs"][0]["w"]) != 0)


def test_stack_channels_lays_the_frames_along_the_channels_oldest_first():
    stacks = np.random.default_rng(9).integers(0, 256, (2, 3, 5, 4, 3), dtype=np.uint8)  # [batch, k, h, w, c]
    images = np.asarray(stack_channels(stacks))
    assert images.shape == (2, 5, 4, 9)
    for b in range(2):
        np.testing.assert_array_equal(images[b], np.concatenate(list(stacks[b]), axis=-1))


# ---- random shift --------------------------------------------------------------------------------------------

def test_random_shift_crops_the_edge_padded_image_at_offsets_within_pad():
    rng = np.random.default_rng(3)
    images = rng.integers(0, 256, (64, 10, 9, 2), dtype=np.uint8)
    pad = 2
    shifted = np.asarray(jax.jit(random_shift, static_argnums=2)(images, jax.random.PRNGKey(0), pad))
    assert shifted.shape == images.shape and shifted.dtype == np.uint8
    padded = np.pad(images, ((0, 0), (pad, pad), (pad, pad), (0, 0)), mode="edge")
    offsets = []
    for image, padded_image in zip(shifted, padded):
        found = [(dy, dx) for dy in range(2 * pad + 1) for dx in range(2 * pad + 1)
                 if np.array_equal(padded_image[dy:dy + 10, dx:dx + 9], image)]
        assert found, "each output is a crop of its edge-padded image"
        offsets.append(found[0])
    # 64 draws of 25 equally likely offsets: all the same would be a broken draw (chance 25^-63)
    assert len(set(offsets)) > 5
    assert {dy for dy, _ in offsets} == set(range(2 * pad + 1))


def test_random_shift_without_pad_and_of_a_flat_image_changes_nothing():
    images = np.full((3, 8, 8, 3), 7, np.uint8)
    key = jax.random.PRNGKey(1)
    np.testing.assert_array_equal(np.asarray(random_shift(images, key, 4)), images)
    varied = np.arange(3 * 8 * 8 * 3, dtype=np.uint8).reshape(3, 8, 8, 3)
    assert random_shift(varied, key, 0) is varied


# ---- the frame-once replay buffer ----------------------------------------------------------------------------

def _stacked_episodes(rng: np.random.Generator, n_envs: int, steps: int, k: int, episode_len: int,
                      frame: tuple[int, int, int] = (5, 4, 3)):
    """Transitions as a frame-stacking env yields them: each env's stack moves on by one frame a step, and a
    new episode starts with k copies of its first frame (Gymnasium's FrameStackObservation)."""
    h, w, c = frame
    stacks = [None] * n_envs
    t = np.zeros(n_envs, int)

    def fresh():
        first = rng.integers(0, 256, frame, dtype=np.uint8)
        return [first] * k

    out = []
    for step in range(steps):
        obs, next_obs, terminated, done = [], [], [], []
        for e in range(n_envs):
            if stacks[e] is None:
                stacks[e] = fresh()
            new = rng.integers(0, 256, frame, dtype=np.uint8)
            nxt = stacks[e][1:] + [new]
            t[e] += 1
            end = t[e] % episode_len == 0
            obs.append(np.stack(stacks[e]))
            next_obs.append(np.stack(nxt))
            terminated.append(end and e % 2 == 0)
            done.append(end)
            stacks[e] = fresh() if end else nxt
        actions = rng.normal(size=(n_envs, 2)).astype(np.float32)
        rewards = rng.normal(size=n_envs).astype(np.float32)
        out.append((np.array(obs), actions, rewards, np.array(next_obs), np.array(terminated, np.float32),
                    np.array(done)))
    return out


@pytest.mark.parametrize("n_step", [1, 3])
def test_frame_buffer_gives_the_transitions_a_plain_buffer_gives(n_step):
    rng = np.random.default_rng(4)
    n_envs, k, frame = 2, 3, (5, 4, 3)
    obs_shape = (k, *frame)
    frames = FrameReplayBuffer(64, obs_shape, 2, n_envs=n_envs, n_step=n_step)
    plain = ReplayBuffer(64, int(np.prod(obs_shape)), 2, n_envs=n_envs, n_step=n_step)
    for obs, actions, rewards, next_obs, terminated, done in _stacked_episodes(rng, n_envs, 50, k, 40, frame):
        frames.add(obs, actions, rewards, next_obs, terminated, done)
        plain.add(obs.reshape(n_envs, -1), actions, rewards, next_obs.reshape(n_envs, -1), terminated, done)
    # 100 transitions through 64 rows: the ring wrapped, and with episodes of 40 steps every row kept its frames
    assert frames._valid(np.arange(frames.size)).all()
    got = frames.sample(np.random.default_rng(5), 16, 3)
    want = plain.sample(np.random.default_rng(5), 16, 3)
    assert got["obs"].dtype == np.uint8 and got["obs"].shape == (3, 16, *obs_shape)
    for key in ("obs", "next_obs"):
        np.testing.assert_array_equal(got[key].reshape(3, 16, -1), want[key].astype(np.uint8))
    for key in ("actions", "rewards", "terminated", "steps"):
        np.testing.assert_array_equal(got[key], want[key])
    # a step stores one frame; each episode's start k: far fewer than the 2k of two whole observations
    assert frames.frames_written == 100 + 2 * n_envs * k  # one frame a step, k at each of the 4 episodes' starts


def test_frame_buffer_never_samples_a_row_that_lost_its_frames():
    rng = np.random.default_rng(6)
    k = 4
    buffer = FrameReplayBuffer(16, (k, 3, 3, 1), 2, n_envs=1)
    # one-step episodes store k + 1 frames per transition: the frame ring (16 + 2 + 4) overwrites rows' frames
    for obs, actions, rewards, next_obs, terminated, done in _stacked_episodes(rng, 1, 40, k, 1, (3, 3, 1)):
        buffer.add(obs, actions, rewards, next_obs, terminated, done)
    valid = buffer._valid(np.arange(buffer.size))
    assert 0 < valid.sum() < buffer.size
    batch = buffer.sample(np.random.default_rng(7), 64)
    # every sampled obs is one the env produced: its frames are k copies of an episode's first frame
    for obs in batch["obs"][0]:
        assert all(np.array_equal(obs[i], obs[0]) for i in range(k))


def test_frame_buffer_resumes_exactly_and_states_its_memory():
    rng = np.random.default_rng(8)
    data = _stacked_episodes(rng, 2, 30, 3, 9)
    a = FrameReplayBuffer(50, (3, 5, 4, 3), 2, n_envs=2)
    for t in data[:20]:
        a.add(*t)
    b = FrameReplayBuffer(50, (3, 5, 4, 3), 2, n_envs=2)
    b.load_state_dict({k: np.array(v) for k, v in a.state_dict().items()})
    for t in data[20:]:
        a.add(*t)
        b.add(*t)
    for key, value in a.state_dict().items():
        np.testing.assert_array_equal(b.state_dict()[key], value)
    sa, sb = a.sample(np.random.default_rng(9), 8), b.sample(np.random.default_rng(9), 8)
    for key in sa:
        np.testing.assert_array_equal(sa[key], sb[key])
    per = FrameReplayBuffer.bytes_per_transition((3, 84, 84, 3), 6, 100_000, 1)
    assert 84 * 84 * 3 < per < 1.2 * 84 * 84 * 3  # one RGB frame and a little
    text = FrameReplayBuffer(1000, (3, 84, 84, 3), 6).describe_memory()
    assert text.startswith("1,000 transitions x 23.") and text.endswith("MiB")  # ~24 KiB each, ~23.5 MiB


def test_frame_buffer_refuses_what_does_not_fit_or_match():
    with pytest.raises(SoftacError, match="buffer_size"):
        FrameReplayBuffer(10**12, (3, 84, 84, 3), 6)
    with pytest.raises(SoftacError, match="frame stacks"):
        FrameReplayBuffer(10, (8, 8, 9), 1)
    buffer = FrameReplayBuffer(10, (1, 4, 4, 3), 1)
    with pytest.raises(SoftacError, match="no complete transition"):
        buffer.sample(np.random.default_rng(0), 4)
    other = FrameReplayBuffer(10, (2, 4, 4, 3), 1)
    with pytest.raises(SoftacError, match="image shape"):
        buffer.load_state_dict(other.state_dict())


# ---- the wrappers ----------------------------------------------------------------------------------------------

def test_resize_averages_areas_when_shrinking_and_repeats_pixels_when_growing():
    from softac.envs.pixels import resize

    image = np.arange(4 * 6 * 1, dtype=np.uint8).reshape(4, 6, 1) * 10
    small = resize(image, 2)
    # each output pixel the mean of a 2x3 block
    expected = image.reshape(2, 2, 2, 3, 1).mean(axis=(1, 3)).round()
    np.testing.assert_array_equal(small, expected.astype(np.uint8))
    big = resize(np.array([[[1], [2]], [[3], [4]]], np.uint8), 4)
    np.testing.assert_array_equal(big[..., 0], [[1, 1, 2, 2], [1, 1, 2, 2], [3, 3, 4, 4], [3, 3, 4, 4]])


def test_frame_stack_pads_with_the_first_frame_moves_on_and_restores_its_frames():
    from softac.envs.pixels import FrameStack
    from softac_test_envs import DotImageEnv

    env = FrameStack(DotImageEnv(), 3)
    assert env.observation_space.shape == (3, 16, 16, 3)
    obs, _ = env.reset(seed=0)
    np.testing.assert_array_equal(obs[0], obs[2])  # k copies of the first frame
    frames = [obs[2]]
    for _ in range(3):
        obs, *_ = env.step(np.zeros(1))
        frames.append(obs[2])
    np.testing.assert_array_equal(obs, np.stack(frames[-3:]))  # oldest first
    other = FrameStack(DotImageEnv(), 3)
    other.reset(seed=1)
    other.load_frames(obs)
    other.unwrapped.load_state(env.unwrapped.save_state())
    other.unwrapped.np_random.bit_generator.state = env.unwrapped.np_random.bit_generator.state
    np.testing.assert_array_equal(other.step(np.zeros(1))[0], env.step(np.zeros(1))[0])


# ---- training on images ----------------------------------------------------------------------------------------

IMAGE = dict(encoder_channels=8, encoder_features=16, augment_pad=2, frame_stack=2)


def test_an_agent_learns_from_images_what_the_image_shows(tiny):
    """DotImage pays the action that points to the square's side: only an agent that reads the image can beat
    a constant action's return of 0 per episode (the best is 20; uniform actions average -6.7)."""
    from softac import SAC, evaluate

    agent = SAC(tiny("softac_test_envs:DotImage-v0", **IMAGE, learning_starts=200, actor_lr=3e-3, critic_lr=3e-3,
                     alpha_lr=3e-3))
    assert agent.spaces.image_shape == (2, 16, 16, 3)
    agent.learn(1000, progress=False)
    stats = evaluate(agent, episodes=4)
    assert stats["mean_return"] > 12.0, stats
    env = agent.make_env()
    obs, _ = env.reset(seed=3)
    assert agent.predict(obs).shape == (1,) and agent.predict(np.stack([obs, obs])).shape == (2, 1)
    with pytest.raises(SoftacError, match="expects uint8 frame stacks of shape"):
        agent.predict(obs[:1])
    env.close()


def test_channels_first_images_and_rendered_frames_become_channels_last_stacks(tiny):
    from softac import SAC
    from softac.envs.pixels import resize
    from softac_test_envs import DotImageEnv

    first = SAC(tiny("DotImage", **{**IMAGE, "frame_stack": 3}), env=DotImageEnv(channels_first=True))
    assert first.spaces.image_shape == (3, 16, 16, 3)
    obs, _ = first.make_env().reset(seed=0)
    assert obs.shape == (3, 16, 16, 3) and obs.dtype == np.uint8
    # pixels=true: the env's 30x40 rendering, resized to pixel_size, in place of its own observation
    rendered = SAC(tiny("softac_test_envs:DotImage-v0", **{**IMAGE, "frame_stack": 1}, pixels=True, pixel_size=20))
    assert rendered.spaces.image_shape == (1, 20, 20, 3)
    env = rendered.make_env()
    obs, _ = env.reset(seed=0)
    np.testing.assert_array_equal(obs[0], resize(env.render(), 20))
    rendered.learn(250, progress=False)
    assert rendered.num_steps == 250


@pytest.mark.exact
@pytest.mark.parametrize("env_id, drq", [("DotImage-v0", False), ("DotStateImage-v0", False),
                                         ("DotStateImage-v0", True)])
def test_resume_with_images_is_exact(tiny, tmp_path, env_id, drq):
    """N+M steps in one go equals N, save, load, M: the frame buffer, the envs' frame stacks and the encoder
    with its optimiser carry over bit for bit (images alone, and an image beside state values; DrQ's form, with
    the encoder's target copy and the actor's own head, too)."""
    from conftest import assert_same_training
    from softac import SAC

    cfg = tiny(f"softac_test_envs:{env_id}", **IMAGE, n_envs=2, gradient_steps=2, eval_interval=300,
               learning_starts=100, target_encoder=drq, actor_encoder_head=drq)
    straight = SAC(cfg)
    straight.learn(500, run_dir=tmp_path / "straight", progress=False)
    first = SAC(cfg)
    first.learn(300, run_dir=tmp_path / "split", progress=False)
    resumed = SAC.load(tmp_path / "split", which="last")
    assert len(resumed.collector.buffer) == 300
    resumed.learn(200, run_dir=tmp_path / "split", progress=False)
    assert_same_training(straight, resumed)
    for name in ("eval.csv", "episodes.csv"):
        assert (tmp_path / "straight" / name).read_text() == (tmp_path / "split" / name).read_text(), name


# ---- an image beside state values ---------------------------------------------------------------------------

def test_state_values_packed_beside_an_image_come_back_bit_for_bit():
    """ImageWithState's packing (NumPy, on the host) and the learner's unpacking (XLA, in the jitted functions)
    agree exactly, whatever the values: the state's float32 bytes travel as uint8 pixels."""
    import gymnasium as gym

    from softac.learner.encoder import image_only_shape, split_image_and_state
    from softac.envs.pixels import ImageStateLayout, state_rows

    space = gym.spaces.Dict({"joints": gym.spaces.Box(-np.inf, np.inf, (2, 3), np.float32),
                             "camera": gym.spaces.Box(0, 255, (3, 5, 4), np.uint8),  # channels-first
                             "touch": gym.spaces.Box(0, 1, (1,), np.float32)})
    layout = ImageStateLayout.of(space)
    assert (layout.image_key, layout.state_keys, layout.state_dim, layout.channels_first) == \
        ("camera", ("joints", "touch"), 7, True)
    assert state_rows(7, 4, 3) == 3 and state_rows(3, 16, 3) == 1 and state_rows(0, 16, 3) == 0
    rng = np.random.default_rng(0)
    values = [np.array([1e-30, -3.5, 1e30, np.pi, -0.0, 65504.0, 7.0], np.float32), rng.normal(size=7).astype(np.float32)]
    stacks, images = [], []
    for state in values:
        image = rng.integers(0, 256, (3, 5, 4), dtype=np.uint8)  # [c, h, w]
        obs = {"camera": image, "joints": state[:6].reshape(2, 3), "touch": state[6:]}
        frame = layout.pack(layout.image(obs["camera"]), layout.state_vector(obs))
        assert frame.shape == (5 + 3, 4, 3)
        stacks.append(np.stack([np.zeros_like(frame), frame]))  # k = 2: the newest frame's state is read
        images.append(np.transpose(image, (1, 2, 0)))
    assert image_only_shape(stacks[0].shape, 7) == (2, 5, 4, 3)
    got_images, got_state = jax.jit(split_image_and_state, static_argnums=1)(np.stack(stacks), 7)
    np.testing.assert_array_equal(np.asarray(got_images)[:, 1], np.stack(images))
    np.testing.assert_array_equal(np.asarray(got_state).view(np.uint32), np.stack(values).view(np.uint32))


def test_an_agent_learns_from_an_image_and_state_values_together(tiny):
    """DotStateImage pays the action pointing to the square's side times the state's flip: an agent that reads
    only the image, or only the state, cannot beat a return of 0 per episode (the best is 20)."""
    from softac import SAC, evaluate

    agent = SAC(tiny("softac_test_envs:DotStateImage-v0", **IMAGE, learning_starts=200, actor_lr=3e-3,
                     critic_lr=3e-3, alpha_lr=3e-3))
    # 3 state values (12 bytes) ride in one extra row of each 16x16 RGB frame; the networks read 16 + 3 values
    assert agent.spaces.image_shape == (2, 17, 16, 3) and agent.spaces.image_state_dim == 3
    assert agent.learner.state.actor[0]["w"].shape[0] == 16 + 3
    agent.learn(1000, progress=False)
    stats = evaluate(agent, episodes=4)
    assert stats["mean_return"] > 12.0, stats
    # predict takes the packed stacks the agent's env makes, or the env's own dict with the image as a stack
    env = agent.make_env()
    packed, _ = env.reset(seed=3)
    raw = env.unwrapped._obs()
    as_dict = {"camera": np.stack([raw["camera"]] * 2), "flip": raw["flip"], "clock": raw["clock"]}
    np.testing.assert_array_equal(agent.predict(as_dict), agent.predict(packed))
    batch = {key: np.stack([value, value]) for key, value in as_dict.items()}
    assert agent.predict(batch).shape == (2, 1)
    with pytest.raises(SoftacError, match="lacks flip"):
        agent.predict({"camera": as_dict["camera"], "clock": raw["clock"]})
    env.close()


def test_image_settings_that_cannot_work_are_refused(tiny):
    from softac import SAC, SACConfig
    from softac.config.sac_config import ConfigError
    from softac_test_envs import DriftEnv

    with pytest.raises(ConfigError, match="obs_norm"):
        SACConfig().replace(pixels=True, obs_norm=True)
    with pytest.raises(ConfigError, match="target_encoder=True: copies the encoder for the target critics, and these "
                                          "critics have none"):
        SACConfig().replace(crossq=True, target_encoder=True)
    SACConfig().replace(crossq=True, target_critics="on", target_encoder=True)  # CrossQ+WN's targets take one
    with pytest.raises(ConfigError, match=r"pixel_range=.*must be unit \(\[0, 1\]\) or centered"):
        SACConfig().replace(pixel_range="0,1")
    with pytest.raises(SoftacError, match="obs_norm normalises vector observations"):
        SAC(tiny("softac_test_envs:DotImage-v0", **IMAGE, obs_norm=True))
    from softac.learner.learner import check_model_memory

    with pytest.raises(SoftacError, match="smaller than the encoder's smallest input, 15x15"):
        check_model_memory(tiny(), 12 * 12 * 3, 1, image_shape=(1, 12, 12, 3))
    with pytest.raises(SoftacError, match="renders rgb_array"):
        SAC(tiny("Drift", pixels=True), env=DriftEnv())
    import gymnasium as gym

    from softac_test_envs import DotStateImageEnv

    two_cameras = DotStateImageEnv()
    two_cameras.observation_space = gym.spaces.Dict({**two_cameras.observation_space.spaces,
                                                     "wrist": gym.spaces.Box(0, 255, (16, 16, 3), np.uint8)})
    with pytest.raises(SoftacError, match="2 image keys \\(camera, wrist\\); softac's encoder takes one"):
        SAC(tiny("TwoCameras", **IMAGE), env=two_cameras)
    discrete = DotStateImageEnv()
    discrete.observation_space = gym.spaces.Dict({**discrete.observation_space.spaces, "mode": gym.spaces.Discrete(3)})
    with pytest.raises(SoftacError, match="mode are not Box spaces"):
        SAC(tiny("DiscreteBeside", **IMAGE), env=discrete)


def test_image_envs_in_worker_processes_give_the_same_run(tiny):
    """Frames come back from env worker processes as uint8 images, and the run is the in-process one."""
    from conftest import assert_same_training
    from softac import SAC

    runs = []
    for env_workers in (0, 2):
        agent = SAC(tiny("softac_test_envs:DotImage-v0", **IMAGE, n_envs=2, env_workers=env_workers,
                         learning_starts=100))
        agent.learn(200, progress=False)
        runs.append(agent)
    assert_same_training(*runs)
    assert runs[1].collector.buffer.frames_written == runs[0].collector.buffer.frames_written > 200


def test_the_cli_trains_evaluates_films_reports_and_exports_a_pixel_run(tmp_path):
    """InvertedPendulum-v5 from its rendered frames, as a new user would type it; the video shows the agent's
    own view, enlarged."""
    from conftest import assert_clean_error, run_cli
    from softac.base.opengl import working_gl_backend
    from softac.run.csv_logs import read_csv

    if working_gl_backend() is None:
        pytest.skip("no EGL or OSMesa here (make system-deps installs libosmesa6)")
    run = tmp_path / "run"
    result = run_cli("train", "--env", "InvertedPendulum-v5", "--steps", "200", "--out", str(run), "--no-progress",
                     "--set", "pixels=true", "pixel_size=24", "encoder_channels=8", "encoder_features=16",
                     "hidden_sizes=32,32", "batch_size=16", "learning_starts=100", "eval_interval=200",
                     "eval_episodes=1", "buffer_size=1000")
    assert result.returncode == 0, result.stderr
    assert [int(float(r["step"])) for r in read_csv(run / "eval.csv")] == [200]
    video = run_cli("video", str(run), "--out", str(tmp_path / "p.mp4"), "--max-steps", "10")
    assert video.returncode == 0, video.stderr
    import imageio.v2 as imageio

    with imageio.get_reader(tmp_path / "p.mp4", format="FFMPEG") as reader:
        frame = reader.get_data(0)
    assert frame.shape == (480, 480, 3) and frame.std() > 5  # 24x24 frames enlarged 20x: the agent's view
    report = run_cli("report", str(run))
    assert report.returncode == 0, report.stderr
    exported = run_cli("export", str(run), "--format", "numpy")
    assert exported.returncode == 0, exported.stderr
    assert (run / "export" / "policy.npz").exists()


def test_the_critic_step_trains_the_encoder_and_hands_the_actor_features_from_before_it_moved(tiny):
    """DrQ-v2's order: the critic loss's gradient moves the encoder; the actor's features are the step's augmented
    observations through the encoder as it was, stopped (the actor's loss never reaches the encoder)."""
    from softac.learner import build, losses, sac
    from softac.learner.encoder import random_shift, stack_channels

    config = tiny("softac_test_envs:DotImage-v0", **IMAGE)
    image = (2, 16, 16, 3)
    fns = build.build(config, 0, 1, image_shape=image)
    state = fns.init(0)
    s = build.update_settings(config, 1, fns.matmul_dtype, images=True)
    rng = np.random.default_rng(0)
    batch = losses.Batch(obs=rng.integers(0, 256, (8, *image), dtype=np.uint8),
                      actions=rng.uniform(-1, 1, (8, 1)).astype(np.float32),
                      rewards=rng.normal(size=8).astype(np.float32),
                      next_obs=rng.integers(0, 256, (8, *image), dtype=np.uint8),
                      terminated=np.zeros(8, np.float32), steps=np.ones(8, np.float32))
    key = jax.random.PRNGKey(3)
    new, _, features = jax.jit(lambda st, b, k: sac.critic_step(st, b, k, s))(state, batch, key)
    moved = [np.abs(np.asarray(a) - np.asarray(b)).max()
             for a, b in zip(jax.tree_util.tree_leaves(state.variants.encoder),
                             jax.tree_util.tree_leaves(new.variants.encoder))]
    assert max(moved) > 0  # the critic loss moved the encoder
    augment_key = jax.random.split(key)[0]
    obs_key = jax.random.split(augment_key)[0]
    expected = encode(state.variants.encoder, random_shift(stack_channels(batch.obs), obs_key, IMAGE["augment_pad"]))
    # the same float32 arithmetic compiled in two graphs: they may round apart by a few units of 2^-24 of tanh's
    # inputs (LayerNorm's sums of 16 terms); 1e-5 leaves room, and the moved encoder's features lie far outside it
    before_gap = np.abs(np.asarray(features) - np.asarray(expected)).max()
    assert before_gap < 1e-5
    after = encode(new.variants.encoder, random_shift(stack_channels(batch.obs), obs_key, IMAGE["augment_pad"]))
    assert np.abs(np.asarray(after) - np.asarray(features)).max() > 1e-4


def _image_batch(image: tuple[int, ...], n: int = 8, seed: int = 0, act_dim: int = 1):
    from softac.learner import losses

    rng = np.random.default_rng(seed)
    return losses.Batch(obs=rng.integers(0, 256, (n, *image), dtype=np.uint8),
                     actions=rng.uniform(-1, 1, (n, act_dim)).astype(np.float32),
                     rewards=rng.normal(size=n).astype(np.float32),
                     next_obs=rng.integers(0, 256, (n, *image), dtype=np.uint8),
                     terminated=np.zeros(n, np.float32), steps=np.ones(n, np.float32))


def test_a_target_encoder_starts_as_the_encoder_feeds_the_targets_and_follows_at_tau(tiny):
    """DrQ's target critic carries its own encoder: a copy at the start, Polyak-averaged with the online encoder
    at tau on the targets' schedule, and what the next-state value is read through."""
    from softac.learner import build, sac

    config = tiny("softac_test_envs:DotImage-v0", **IMAGE, target_encoder=True, tau=0.25, target_update_interval=2)
    image = (2, 16, 16, 3)
    fns = build.build(config, 0, 1, image_shape=image)
    state = fns.init(0)
    leaves = jax.tree_util.tree_leaves
    for online, target in zip(leaves(state.variants.encoder), leaves(state.variants.target_encoder)):
        np.testing.assert_array_equal(np.asarray(online), np.asarray(target))
    without = build.build(config.replace(target_encoder=False), 0, 1, image_shape=image).init(0)
    assert without.variants.target_encoder == ()  # and the same networks otherwise
    for a, b in zip(leaves(without.variants.encoder), leaves(state.variants.encoder)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))

    s = build.update_settings(config, 1, fns.matmul_dtype, images=True)
    batch, key = _image_batch(image), jax.random.PRNGKey(3)
    step = jax.jit(lambda st, b, k: sac.critic_step(st, b, k, s)[1]["critic_loss"])
    # with the target encoder equal to the online one, the loss is the online-features one (two graphs of the
    # same float32 arithmetic: a relative 1e-5 leaves room for their rounding)
    s_online = build.update_settings(config.replace(target_encoder=False), 1, fns.matmul_dtype, images=True)
    online_loss = float(jax.jit(lambda st, b, k: sac.critic_step(st, b, k, s_online)[1]["critic_loss"])(
        without, batch, key))
    assert abs(float(step(state, batch, key)) - online_loss) <= 1e-5 * abs(online_loss)
    # a different target encoder changes the next-state values, so the loss
    moved = state.with_variants(target_encoder=jax.tree_util.tree_map(lambda x: x * 0.5, state.variants.target_encoder))
    assert abs(float(step(moved, batch, key)) - online_loss) > 1e-3 * abs(online_loss)

    # one gradient step (the 1st: not due) and a second (due: n_updates 2 % 2 == 0)
    batches = jax.tree_util.tree_map(lambda x: np.stack([x, x]), batch)
    new, _ = fns.update(jax.tree_util.tree_map(jnp.copy, state), batches)
    first = jax.tree_util.tree_map(jnp.copy, state)
    # jitted, as the update runs it (op by op, this one step took about a minute of the suite's time: issue 64)
    (after_one, _), _ = jax.jit(lambda carry, b: sac.gradient_step(s, None, carry, b))((first, zero_totals()),
                                                                                      batch)
    for target, start in zip(leaves(after_one.variants.target_encoder), leaves(state.variants.target_encoder)):
        np.testing.assert_array_equal(np.asarray(target), np.asarray(start))  # not due yet
    for target, start, online in zip(leaves(new.variants.target_encoder), leaves(state.variants.target_encoder),
                                     leaves(new.variants.encoder)):
        expected = 0.75 * np.asarray(start) + 0.25 * np.asarray(online)
        # one multiply-add in float32 each: a few ulps of the operands' size
        bound = 4 * np.finfo(np.float32).eps * (np.abs(np.asarray(start)) + np.abs(np.asarray(online))) + 1e-30
        assert np.all(np.abs(np.asarray(target) - expected) <= bound)
    assert max(float(np.abs(np.asarray(t) - np.asarray(o)).max())
               for t, o in zip(leaves(new.variants.target_encoder),
                               leaves(new.variants.encoder))) > 0  # it lags the encoder


def test_an_actor_head_is_trained_by_the_actor_loss_on_the_shared_convolutions_and_is_what_the_policy_acts_through(
        tiny):
    """DrQ's actor: its own Linear-LayerNorm-tanh head on the encoder's convolutions (stopped). The critic step
    leaves the head alone; the actor step moves the head and the actor and leaves the encoder alone; acting and
    the deployed policy read the shared convolutions through the actor's head."""
    from softac import SAC
    from softac.learner import build, sac

    config = tiny("softac_test_envs:DotStateImage-v0", **IMAGE, actor_encoder_head=True)
    agent = SAC(config)
    state = agent.learner.state
    leaves = jax.tree_util.tree_leaves
    assert state.variants.actor_head["w"].shape[1] == IMAGE["encoder_features"]
    without = SAC(config.replace(actor_encoder_head=False)).learner.state
    for a, b in zip(leaves((without.actor, without.variants.encoder)), leaves((state.actor, state.variants.encoder))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))  # drawn after the encoder: the rest unchanged
    actor, stats, encoder = agent.learner.deployed_policy()
    assert encoder["convs"] is state.variants.encoder["convs"] and encoder["head"] is state.variants.actor_head

    s = build.update_settings(config, 1, agent.learner.functions.matmul_dtype, images=True,
                            image_state_dim=agent.spaces.image_state_dim)
    batch = _image_batch(agent.spaces.image_shape, act_dim=agent.spaces.act_dim)
    after_critic, _, (critic_obs, conv) = jax.jit(lambda st, b, k: sac.critic_step(st, b, k, s))(
        state, batch, jax.random.PRNGKey(1))
    for a, b in zip(leaves(after_critic.variants.actor_head), leaves(state.variants.actor_head)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    flat = state.variants.actor_head["w"].shape[0]
    assert conv.shape == (8, flat + agent.spaces.image_state_dim)
    assert critic_obs.shape == (8, IMAGE["encoder_features"] + agent.spaces.image_state_dim)
    after_actor, _ = jax.jit(lambda st, o, k: sac.actor_and_alpha_step(st, o, k, s))(
        after_critic, (critic_obs, conv), jax.random.PRNGKey(2))
    for tree in (lambda st: st.actor, lambda st: st.variants.actor_head):
        assert max(float(np.abs(np.asarray(a) - np.asarray(b)).max())
                   for a, b in zip(leaves(tree(after_actor)), leaves(tree(after_critic)))) > 0
    for a, b in zip(leaves(after_actor.variants.encoder), leaves(after_critic.variants.encoder)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    agent.learn(300, progress=False)  # trains, acts and evaluates through the head
    assert agent.num_steps == 300 and agent.predict(agent.make_env().reset(seed=0)[0]).shape == (agent.spaces.act_dim,)


# ---- export ------------------------------------------------------------------------------------------------------

@pytest.mark.numerics
@pytest.mark.parametrize("with_state, actor_head, pixel_range", [(False, False, "unit"), (True, False, "centered"),
                                                                 (True, True, "unit")])
def test_exported_image_policies_act_as_predict(tiny, tmp_path, with_state, actor_head, pixel_range):
    """The ONNX graph and the NumPy pass of an image agent (the encoder at either pixel range, the state values
    beside an image, and the actor's own head on the convolutions) each give predict()'s actions within the float32 bound of the exact ones (tests/float_bounds.py: the
    convolutions as dense layers' sums, LayerNorm step by step), for a batch and for one observation; and an
    export with its features flattened in the wrong order, or a kernel transposed, falls outside it."""
    onnxruntime = pytest.importorskip("onnxruntime")
    from float_bounds import action_bound, assert_within_bound
    from softac import SAC
    from softac.outputs.export import export_policy
    from softac.learner.numpy_forward import policy_forward
    from softac_test_envs import DotImageEnv, DotStateImageEnv

    # 20x20 frames: the convolutions end at 3x3 (at 16x16, 1x1, where any flattening order is the same)
    env = (DotStateImageEnv if with_state else DotImageEnv)(size=20)
    agent = SAC(tiny("DotImage20", **IMAGE, learning_starts=100, actor_encoder_head=actor_head,
                     pixel_range=pixel_range), env=env)
    agent.learn(300, progress=False)  # the encoder moved from its init, which is mostly zeros
    env = agent.make_env()
    env.action_space.seed(0)
    obs, _ = env.reset(seed=0)
    rows = []
    for _ in range(60):
        rows.append(obs)
        obs = env.step(env.action_space.sample())[0]
    env.close()
    stacks = np.stack(rows)
    reference, bound = action_bound(agent, stacks)
    assert_within_bound(agent.predict(stacks), reference, bound, "predict()")
    onnx_path = export_policy(agent, tmp_path / "policy.onnx", "onnx")
    with np.load(export_policy(agent, tmp_path / "policy.npz", "numpy")) as npz:
        params = dict(npz)
    layout = agent.spaces.image_state
    if layout is None:  # the frame stacks; the ONNX graph's input is named obs
        inputs, one = stacks, stacks[0]
    else:  # the env's own dict: the image key's frame stacks and each state key's values (keys sorted by the Dict)
        assert layout.state_keys == ("clock", "flip")
        state = stacks[:, -1, 20:].reshape(len(stacks), -1)[:, :12].copy().view("<f4")
        inputs = {"camera": stacks[:, :, :20], "clock": state[:, :2], "flip": state[:, 2:]}
        one = {key: value[0] for key, value in inputs.items()}
    session = onnxruntime.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    feed = {"obs": inputs} if layout is None else inputs
    assert_within_bound(session.run(["action"], feed)[0], reference, bound, "onnx")
    assert_within_bound(policy_forward(params, inputs), reference, bound, "numpy")
    assert_within_bound(policy_forward(params, one), reference[0], bound[0], "numpy, one observation")
    # the bound is a worst case (every rounding the same way), far above the actual errors, yet tight enough
    # to catch an export that flattens the 3x3x8 features channels-first, or transposes a kernel
    w, channels = params["enc_w"], params["conv0_w"].shape[-1]
    nchw = {**params, "enc_w": w.reshape(3, 3, channels, -1).transpose(2, 0, 1, 3).reshape(w.shape)}
    transposed = {**params, "conv1_w": np.ascontiguousarray(np.transpose(params["conv1_w"], (1, 0, 2, 3)))}
    for wrong in (nchw, transposed):
        assert np.any(np.abs(policy_forward(wrong, inputs) - reference) > bound)
