"""Videos of an agent: MuJoCo rendered offscreen (EGL or OSMesa, chosen by softac.base.opengl) to MP4."""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from softac.errors import SoftacError
from softac.base.opengl import NO_GL_MESSAGE

def _label(frame: np.ndarray, text: str) -> np.ndarray:
    from PIL import Image, ImageDraw, ImageFont

    image = Image.fromarray(frame)
    draw = ImageDraw.Draw(image)
    try:
        font = ImageFont.load_default(size=max(14, frame.shape[0] // 24))
    except TypeError:  # Pillow < 10.1 has no sized default font
        font = ImageFont.load_default()
    box = draw.textbbox((8, 6), text, font=font)
    draw.rectangle((box[0] - 4, box[1] - 3, box[2] + 4, box[3] + 3), fill=(0, 0, 0))
    draw.text((8, 6), text, fill=(255, 255, 255), font=font)
    return np.asarray(image)


def record(agent: Any, out: Path, episodes: int = 1, deterministic: bool = True, seed: int | None = None,
           width: int = 640, height: int = 480, max_steps: int | None = None,
           policy: str = "deployed") -> dict[str, Any]:
    """Render `episodes` episodes of `agent` into one MP4 at `out`; returns returns and lengths. The default seed
    is the one evaluations use (episode i: seed + i). `policy`: "deployed", "actor" or "average" (SAC.predict)."""
    import imageio.v2 as imageio

    from softac.envs.make import observation_array
    from softac.errors import EnvError
    from softac.run.evaluation import EVAL_SEED_OFFSET, acting

    from softac.base.opengl import choose_gl_backend

    choose_gl_backend()  # before the env's first render: EGL or OSMesa where MUJOCO_GL leaves it open
    seed = agent.config.seed + EVAL_SEED_OFFSET if seed is None else seed
    act = acting(agent, deterministic, policy)
    images = agent.spaces.image_shape is not None
    try:
        # an image agent's env renders what the agent sees (pixels: at pixel_size), enlarged for the video
        env = agent.make_env(render_mode="rgb_array", **({} if images else {"width": width, "height": height}))
    except EnvError:
        env = agent.make_env(render_mode="rgb_array")
    if env.render_mode != "rgb_array":
        raise SoftacError(f"env {agent.config.env_id} cannot render rgb_array frames")
    fps = int(env.metadata.get("render_fps") or 30)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.stem}.partial{out.suffix}")
    returns, lengths = [], []

    def caption(episode: int, steps: int, total: float) -> str:
        return f"episode {episode + 1}/{episodes}  step {steps}  return {total:.1f}"

    with warnings.catch_warnings():
        # imageio starts ffmpeg (fork+exec of a binary) on the first frame: safe beside JAX's threads
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
        try:
            writer = imageio.get_writer(tmp, fps=fps, codec="libx264", quality=7, macro_block_size=1,
                                        ffmpeg_log_level="error", format="FFMPEG")
            try:
                for episode in range(episodes):
                    obs, _ = env.reset(seed=seed + episode)
                    total, steps, done = 0.0, 0, False
                    while not done:
                        frame = _enlarged(_render(env), height) if images else _render(env)
                        writer.append_data(_label(frame, caption(episode, steps, total)))
                        action = act(observation_array(obs))
                        obs, reward, terminated, truncated, _ = env.step(action)
                        total += float(reward)
                        steps += 1
                        done = terminated or truncated or (max_steps is not None and steps >= max_steps)
                    final = _label(_enlarged(_render(env), height) if images else _render(env),
                                   caption(episode, steps, total))
                    for _ in range(fps // 2):  # hold the last frame half a second, return visible
                        writer.append_data(final)
                    returns.append(total)
                    lengths.append(steps)
            finally:
                writer.close()
            os.replace(tmp, out)
        finally:
            env.close()
            if tmp.exists():
                tmp.unlink()
    return {"path": str(out), "returns": returns, "lengths": lengths, "fps": fps,
            "mean_return": float(np.mean(returns))}


def _render(env) -> np.ndarray:
    try:
        frame = env.render()
    except Exception as exc:
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise SoftacError(f"rendering failed ({message}); {NO_GL_MESSAGE}") from None
    if frame is None:
        raise SoftacError("the env returned no frame; it may not support rgb_array rendering")
    return np.asarray(frame, np.uint8)


def _enlarged(frame: np.ndarray, height: int) -> np.ndarray:
    """A small frame (an image agent's view) repeated pixel by pixel to about `height` rows."""
    k = max(1, round(height / frame.shape[0]))
    return np.repeat(np.repeat(frame, k, axis=0), k, axis=1) if k > 1 else frame


def default_video_path(run_or_ckpt: Path, step: int, mean_return: float | None = None,
                       policy: str = "deployed") -> Path:
    from softac.run.checkpoint import is_checkpoint

    base = run_or_ckpt
    if is_checkpoint(run_or_ckpt) and run_or_ckpt.parent.name == "checkpoints":
        base = run_or_ckpt.parent.parent
    name = (f"step{step}" + (f"-{policy}" if policy != "deployed" else "")
            + (f"-return{mean_return:.0f}" if mean_return is not None else "") + ".mp4")
    return base / "videos" / name
