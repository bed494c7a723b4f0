"""Image observations (issue 44): recognising them, and the wrappers that make them.

An image observation is a uint8 Box of three axes. softac keeps images channels-last ([h, w, c]); an env
that gives channels-first images ([c, h, w], PyTorch's layout) is transposed by `ChannelsLast`. `pixels=true`
replaces any renderable env's observation with its rendered frame (`PixelObservation`, `pixel_size` square,
made at that size where the renderer takes one: Gymnasium's MuJoCo envs and the DeepMind Control Suite), and
`FrameStack` keeps the last `frame_stack` frames, oldest first, as one observation [k, h, w, c] (k = 1 too; an
episode starts with k copies of its first frame, as Gymnasium's FrameStackObservation pads). That layout keeps
each frame contiguous: the replay buffer stores and gathers whole frames, and the encoder lays the stack out
along the channels on the device.

A dict observation of one image beside state values (a robot's camera and its joint readings) is carried as one
uint8 frame too (`ImageWithState`): the image's rows, then rows holding the state vector's float32 bytes
(the other keys in the space's order, each flattened; zero-padded to whole rows). Stacked, stored, sent to env
workers and checkpointed like any frame, the state rides along at one row or two per frame; the learner reads
the newest frame's state bytes back as float32 (`softac.learner.encoder.split_image_and_state`) and puts the values
beside the encoder's features.
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import weakref
from typing import Any

import gymnasium as gym
import numpy as np

from softac.errors import EnvError
from softac.envs.families import renders_at_size
from softac.envs.goals import DictLayout, dict_layout



def is_image_space(space: gym.Space) -> bool:
    """One image: a uint8 Box of three axes."""
    return isinstance(space, gym.spaces.Box) and space.dtype == np.uint8 and len(space.shape) == 3


def is_frame_stack_space(space: gym.Space) -> bool:
    """A stack of images as FrameStack makes it: a uint8 Box [k, h, w, c]."""
    return isinstance(space, gym.spaces.Box) and space.dtype == np.uint8 and len(space.shape) == 4


def image_key_of(space: gym.Space) -> str | None:
    """The key of a Dict space's one image subspace (None for a Dict without one, or any other space)."""
    if not isinstance(space, gym.spaces.Dict):
        return None
    keys = [key for key, sub in space.spaces.items() if is_image_space(sub)]
    if len(keys) > 1:
        raise EnvError(f"the observation dict has {len(keys)} image keys ({', '.join(keys)}); softac's encoder takes "
                       "one (stack the cameras into one image's channels, or drop all but one)")
    return keys[0] if keys else None


def state_rows(state_dim: int, width: int, channels: int) -> int:
    """The rows of a [*, width, channels] uint8 frame that hold `state_dim` float32 values."""
    return -(-4 * state_dim // (width * channels))


def channels_first(shape: tuple[int, ...]) -> bool:
    """[c, h, w] rather than [h, w, c]: the first axis is smaller than the last (3x84x84 against 84x84x3)."""
    return shape[0] < shape[-1]


def resize(image: np.ndarray, size: int) -> np.ndarray:
    """An [h, w, c] image as [size, size, c]: each output pixel the mean of the input pixels its cell covers
    (area averaging, as OpenCV's INTER_AREA for shrinking), nearest pixel when growing."""
    h, w = image.shape[:2]
    if (h, w) == (size, size):
        return image
    if h < size or w < size:
        rows = np.minimum((np.arange(size) + 0.5) * h / size, h - 1).astype(int)
        cols = np.minimum((np.arange(size) + 0.5) * w / size, w - 1).astype(int)
        return image[rows][:, cols]
    row_edges = np.linspace(0, h, size + 1).astype(int)
    col_edges = np.linspace(0, w, size + 1).astype(int)
    summed = np.add.reduceat(np.add.reduceat(image.astype(np.float64), row_edges[:-1], axis=0), col_edges[:-1], axis=1)
    counts = np.outer(np.diff(row_edges), np.diff(col_edges))[..., None]
    return np.round(summed / counts).astype(np.uint8)


class ChannelsLast(gym.ObservationWrapper, gym.utils.RecordConstructorArgs):
    """A channels-first image env's observations as [h, w, c]."""

    def __init__(self, env: gym.Env):
        gym.utils.RecordConstructorArgs.__init__(self)
        gym.ObservationWrapper.__init__(self, env)
        space = env.observation_space
        self.observation_space = gym.spaces.Box(0, 255, (space.shape[1], space.shape[2], space.shape[0]), np.uint8)

    def observation(self, observation: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(np.transpose(observation, (1, 2, 0)))


@dataclasses.dataclass(frozen=True)
class ImageStateLayout:
    """How `ImageWithState` packs a dict observation: the image key, where the other keys sit in the state vector
    (a DictLayout: the space's order, each flattened), and whether the image comes channels-first."""
    image_key: str
    state: DictLayout
    channels_first: bool

    @classmethod
    def of(cls, space: gym.spaces.Dict) -> ImageStateLayout:
        image_key = image_key_of(space)
        keys = tuple(key for key in space.spaces if key != image_key)
        odd = [key for key in keys if not isinstance(space[key], gym.spaces.Box)]
        if odd:
            raise EnvError(f"beside its image, the observation dict's {', '.join(odd)} are not Box spaces; softac "
                           "reads the state beside an image from Box keys only")
        state = dict_layout(gym.spaces.Dict([(key, space[key]) for key in keys]))  # a sequence keeps the order
        return cls(image_key, state, channels_first(space[image_key].shape))

    @property
    def state_keys(self) -> tuple[str, ...]:
        return self.state.keys

    @property
    def state_dim(self) -> int:
        return self.state.dim

    def image(self, image: Any) -> np.ndarray:
        """An image (or a stack, or a batch: the last three axes) as uint8 channels-last."""
        image = np.asarray(image, np.uint8)
        return np.moveaxis(image, -3, -1) if self.channels_first else image

    def state_vector(self, obs: dict[str, Any]) -> np.ndarray:
        """The state keys' values as one float32 vector, or [batch, state_dim] for a dict of batches."""
        if self.image_key not in obs:
            raise EnvError(f"observation dict lacks {self.image_key}; this agent expects keys "
                           f"{', '.join((self.image_key, *self.state_keys))}")
        return self.state.flatten(obs) if self.state_keys else np.zeros(0, np.float32)

    def pack(self, image: np.ndarray, state: np.ndarray) -> np.ndarray:
        """Channels-last images [..., h, w, c] and state vectors [..., state_dim] as frames [..., h + r, w, c]:
        r rows hold the state's float32 bytes (little-endian, as x86 and ARM hosts and XLA read them)."""
        *lead, height, width, channels = image.shape
        rows = state_rows(self.state_dim, width, channels)
        raw = np.zeros((*lead, rows * width * channels), np.uint8)
        raw[..., : 4 * self.state_dim] = np.ascontiguousarray(state, "<f4").view(np.uint8).reshape(*lead, -1)
        return np.concatenate([image, raw.reshape(*lead, rows, width, channels)], axis=-3)


class ImageWithState(gym.ObservationWrapper, gym.utils.RecordConstructorArgs):
    """A dict observation of one image (HxWxC or CxHxW uint8) and state values as one frame [h + r, w, c]: the
    image, then r rows of the state vector's float32 bytes (`ImageStateLayout.pack`)."""

    def __init__(self, env: gym.Env):
        gym.utils.RecordConstructorArgs.__init__(self)
        gym.ObservationWrapper.__init__(self, env)
        self.layout = ImageStateLayout.of(env.observation_space)
        shape = env.observation_space[self.layout.image_key].shape
        height, width, channels = (shape[1], shape[2], shape[0]) if self.layout.channels_first else shape
        rows = state_rows(self.layout.state_dim, width, channels)
        self.observation_space = gym.spaces.Box(0, 255, (height + rows, width, channels), np.uint8)

    def observation(self, observation: dict[str, Any]) -> np.ndarray:
        return self.layout.pack(self.layout.image(observation[self.layout.image_key]),
                                self.layout.state_vector(observation))


class PixelObservation(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """The env's rendered frame as its observation, [size, size, 3] uint8 (the env must render rgb_array)."""

    def __init__(self, env: gym.Env, size: int):
        gym.utils.RecordConstructorArgs.__init__(self, size=size)
        gym.Wrapper.__init__(self, env)
        if env.render_mode != "rgb_array":
            raise EnvError(f"pixels=true needs an env that renders rgb_array frames; this one's render_mode is "
                           f"{env.render_mode!r} (make it with render_mode='rgb_array')")
        self.size = int(size)
        self.observation_space = gym.spaces.Box(0, 255, (self.size, self.size, 3), np.uint8)

    def _frame(self) -> np.ndarray:
        frame = self.env.render()
        _close_at_exit(self)  # after the first render made the renderer (and loaded its GL module)
        if not isinstance(frame, np.ndarray) or frame.ndim != 3 or frame.shape[-1] < 3:
            raise EnvError(f"pixels=true: the env rendered {type(frame).__name__} "
                           f"{getattr(frame, 'shape', '')}, not an RGB image")
        return resize(np.asarray(frame[..., :3], np.uint8), self.size)

    def reset(self, **kwargs: Any):
        _, info = self.env.reset(**kwargs)
        return self._frame(), info

    def step(self, action: Any):
        _, reward, terminated, truncated, info = self.env.step(action)
        return self._frame(), reward, terminated, truncated, info


_OPEN: weakref.WeakSet = weakref.WeakSet()  # pixel envs alive, to close at exit


def _close_at_exit(env: gym.Env) -> None:
    """Close `env` at exit if it is still open then. Its renderer's GL context must be freed before the
    interpreter tears down its modules (OSMesa's and EGL's __del__ raise otherwise), and before MuJoCo's own exit
    hook releases the display: hooks run last-registered first, and this one is registered after the env's first
    render loaded MuJoCo's GL module."""
    if env in _OPEN:
        return
    if not _OPEN:
        atexit.register(_close_all)
    _OPEN.add(env)


def _close_all() -> None:
    for env in list(_OPEN):
        with contextlib.suppress(Exception):
            env.close()
    _OPEN.clear()


class FrameStack(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """The last k image observations as one, [k, h, w, c], oldest first. `load_frames` puts a saved
    observation's frames back (exact resume restores the env's physics, then this)."""

    def __init__(self, env: gym.Env, k: int):
        gym.utils.RecordConstructorArgs.__init__(self, k=k)
        gym.Wrapper.__init__(self, env)
        self.k = int(k)
        self.observation_space = gym.spaces.Box(0, 255, (self.k, *env.observation_space.shape), np.uint8)
        self.frames: list[np.ndarray] = []

    def _stacked(self) -> np.ndarray:
        return np.stack(self.frames)

    def reset(self, **kwargs: Any):
        obs, info = self.env.reset(**kwargs)
        self.frames = [np.asarray(obs, np.uint8)] * self.k
        return self._stacked(), info

    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.frames = [*self.frames[1:], np.asarray(obs, np.uint8)]
        return self._stacked(), reward, terminated, truncated, info

    def load_frames(self, stacked: np.ndarray) -> None:
        self.frames = [np.array(frame, np.uint8) for frame in stacked]


def wrapper_of(env: gym.Env, cls: type) -> Any:
    """The outermost wrapper of class `cls` around `env`, or None."""
    while isinstance(env, gym.Wrapper):
        if isinstance(env, cls):
            return env
        env = env.env
    return None


def frame_stack_of(env: gym.Env) -> FrameStack | None:
    """The FrameStack wrapper around `env` (the outermost), or None."""
    return wrapper_of(env, FrameStack)


def _wrapper_spec(cls: type, **kwargs: Any) -> gym.envs.registration.WrapperSpec:
    return gym.envs.registration.WrapperSpec(cls.__name__, f"{__name__}:{cls.__name__}", kwargs)


def with_image_wrappers(source: Any, observation_space: gym.Space, pixels: bool, size: int, frame_stack: int) -> Any:
    """`source` (a spec, or an instance) whose raw observations are `observation_space`, with them made images
    where asked (pixels), turned channels-last where they are channels-first, a dict of an image and state values
    packed into one frame (ImageWithState), and stacked ([frame_stack, h, w, c]). A spec keeps the wrappers
    among its own, so copies and env workers make the env the same way. Apply after ActionRepeat: a repeated
    action yields one frame."""
    with_state = not pixels and image_key_of(observation_space) is not None
    first = not pixels and is_image_space(observation_space) and channels_first(observation_space.shape)
    if isinstance(source, gym.Env):
        env = PixelObservation(source, size) if pixels else source
        env = ChannelsLast(env) if first else env
        env = ImageWithState(env) if with_state else env
        return FrameStack(env, frame_stack)
    spec, wrappers = source, list(source.additional_wrappers)
    if pixels:
        kwargs = {**spec.kwargs, "render_mode": "rgb_array"}
        if renders_at_size(str(spec.entry_point)):
            kwargs.update(width=size, height=size)
        spec = dataclasses.replace(spec, kwargs=kwargs)
        wrappers.append(_wrapper_spec(PixelObservation, size=size))
    if first:
        wrappers.append(_wrapper_spec(ChannelsLast))
    if with_state:
        wrappers.append(_wrapper_spec(ImageWithState))
    wrappers.append(_wrapper_spec(FrameStack, k=frame_stack))
    return dataclasses.replace(spec, additional_wrappers=tuple(wrappers))
