"""Stable-Baselines3's SAC with its CnnPolicy on the frames softac trains on (issue 44's peer from pixels).

    python benchmarks/sb3_pixels.py --env InvertedPendulum-v5 --steps 10000 --seed 0 --out runs/sb3-pixels-s0

The env is softac's own pixel env (`pixels=true`: rendered RGB frames, `--pixel-size`, the last `--frames`
stacked, `--action-repeat` inside), its frame stack [k, h, w, 3] laid along the channels as [h, w, 3k], which
SB3's CnnPolicy reads (NatureCNN, transposed to channels-first by SB3's VecTransposeImage). SB3's SAC at its
defaults (lr 3e-4, batch 256, one gradient step per env step, tau 0.005, automatic entropy) except: the replay
buffer holds `--buffer` transitions (SB3's 1M of 84x84x9 frames, stored twice, would take ~127 GB) and
learning starts after 1,000 steps (the drq preset's random steps). Every `--eval-interval` steps, `--eval-episodes`
deterministic episodes on a second env (`--target-return`: the run stops at the first that reaches it); writes
eval.csv (step, return_mean, return_std, wall_s) and summary.json (wall seconds, train-only seconds, the final
evaluation and its step, the machine). Needs torch and stable-baselines3.
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import gymnasium as gym
import numpy as np


class ChannelStack(gym.ObservationWrapper):
    """[k, h, w, c] frame stacks as [h, w, k*c] images (oldest frame's channels first)."""

    def __init__(self, env: gym.Env):
        super().__init__(env)
        k, h, w, c = env.observation_space.shape
        self.observation_space = gym.spaces.Box(0, 255, (h, w, k * c), np.uint8)

    def observation(self, observation: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(np.moveaxis(observation, 0, 2).reshape(self.observation_space.shape))


def make_pixel_env(env_id: str, pixel_size: int, frames: int, action_repeat: int) -> gym.Env:
    from softac.config.sac_config import SACConfig
    from softac.envs.make import make_env, training_env_source

    config = SACConfig(pixels=True, pixel_size=pixel_size, frame_stack=frames, action_repeat=action_repeat)
    source, probe = training_env_source(env_id, config)
    probe.close()
    return ChannelStack(make_env(source))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default="InvertedPendulum-v5")
    p.add_argument("--steps", type=int, default=10_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True)
    p.add_argument("--pixel-size", type=int, default=84)
    p.add_argument("--frames", type=int, default=3)
    p.add_argument("--action-repeat", type=int, default=1)
    p.add_argument("--buffer", type=int, default=100_000)
    p.add_argument("--learning-starts", type=int, default=1_000)
    p.add_argument("--eval-interval", type=int, default=2_000)
    p.add_argument("--eval-episodes", type=int, default=5)
    p.add_argument("--device", default="auto")
    p.add_argument("--target-return", type=float, default=None,
                   help="stop at the first evaluation that reaches this return (softac sweep's --threshold)")
    p.add_argument("--threads", type=int, default=0, help="torch's CPU threads (0: torch's default); 1 beside "
                                                            "`taskset -c N` for a one-core run")
    a = p.parse_args(argv)

    import torch
    from stable_baselines3 import SAC
    from stable_baselines3.common.evaluation import evaluate_policy
    from stable_baselines3.common.monitor import Monitor

    if a.threads:
        torch.set_num_threads(a.threads)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    env = make_pixel_env(a.env, a.pixel_size, a.frames, a.action_repeat)
    eval_env = Monitor(make_pixel_env(a.env, a.pixel_size, a.frames, a.action_repeat))
    eval_env.reset(seed=a.seed + 10_000)
    start = time.perf_counter()
    model = SAC("CnnPolicy", env, buffer_size=a.buffer, learning_starts=a.learning_starts, seed=a.seed, device=a.device,
                verbose=0)
    train_s, rows, done = 0.0, [], 0
    with open(out / "eval.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["step", "return_mean", "return_std", "wall_s"])
        while done < a.steps:
            chunk = min(a.eval_interval, a.steps - done)
            t = time.perf_counter()
            model.learn(chunk, reset_num_timesteps=done == 0, progress_bar=False)
            train_s += time.perf_counter() - t
            done += chunk
            mean, std = evaluate_policy(model, eval_env, n_eval_episodes=a.eval_episodes, deterministic=True)
            rows.append((done, float(mean), float(std), time.perf_counter() - start))
            writer.writerow(rows[-1])
            f.flush()
            print(f"step {done}: eval {mean:.1f} +- {std:.1f} ({rows[-1][3]:.0f} s)", flush=True)
            if a.target_return is not None and mean >= a.target_return:
                break
    from softac.base.cpus import machine_description

    summary = {"framework": "sb3-cnn", "env": a.env, "seed": a.seed, "steps": a.steps, "pixel_size": a.pixel_size,
               "frames": a.frames, "action_repeat": a.action_repeat, "buffer": a.buffer, "learning_starts": a.learning_starts,
               "device": str(model.device), "wall_s": time.perf_counter() - start, "train_s": train_s,
               "batch_size": model.batch_size, "threads": torch.get_num_threads(), "machine": machine_description(),
               "final_return": rows[-1][1], "final_step": rows[-1][0], "target_return": a.target_return}
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    env.close()
    eval_env.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
