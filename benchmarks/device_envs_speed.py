"""Env steps per second of MuJoCo Playground's envs collected on the device (issue 67): `DeviceEnvs.step` (vmapped,
auto-reset) in one jitted scan of STEPS vector steps with uniform actions, after a first call that compiles it.
Usage: python benchmarks/device_envs_speed.py [--envs CartpoleSwingup,CheetahRun] [--n 1,16,128] [--steps 200]
(run it pinned, e.g. `taskset -c 0`, and say which machine; on a GPU add nothing: JAX picks it)."""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp

from softac.envs import playground
from softac.envs.device_envs import DeviceEnvs


def speed(name: str, n: int, steps: int) -> str:
    env = playground.load(name)[0]
    envs = DeviceEnvs(env, n, 1000)

    @jax.jit
    def run(batch, key):
        def one(b, k):
            b, s = envs.step(b, jax.random.uniform(k, (n, env.action_size), minval=-1.0, maxval=1.0))
            return b, s.rewards.sum()
        return jax.lax.scan(one, batch, jax.random.split(key, steps))

    start = time.perf_counter()
    out = run(jax.jit(envs.reset)(jax.random.PRNGKey(0)), jax.random.PRNGKey(1))
    jax.block_until_ready(out)
    compiled = time.perf_counter() - start
    start = time.perf_counter()
    jax.block_until_ready(run(out[0], jax.random.PRNGKey(2)))
    took = time.perf_counter() - start
    return (f"{name} n={n}: compile and first call {compiled:.1f} s, {steps * n / took:,.0f} env steps/s "
            f"({took / steps * 1e3:.2f} ms a vector step) on {jax.devices()[0].platform}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", default="CartpoleSwingup,CheetahRun")
    parser.add_argument("--n", default="1,16,128")
    parser.add_argument("--steps", type=int, default=200)
    args = parser.parse_args()
    for name in args.envs.split(","):
        for n in (int(v) for v in args.n.split(",")):
            print(speed(name, n, args.steps), flush=True)


if __name__ == "__main__":
    main()
