"""The image encoder's four convolutions, forward and backward, in float32 against bfloat16 inputs and kernels
(float32 accumulation, as the bf16 matmuls of the MLPs), on random frames (issue 44: "bf16 where it pays").

    taskset -c 1 python benchmarks/conv_dtype.py 84 32     # side, batch; 9 channels (3 frames of RGB)

Prints the median of 5 timed calls per dtype, twice over, alternating (the machine drifts).
"""

from __future__ import annotations

import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from softac.learner.encoder import CONV_STRIDES, init_encoder


def conv_loss(convs, images, dtype):
    h = images.astype(jnp.float32) / 255 - 0.5
    for layer, stride in zip(convs, CONV_STRIDES):
        h = jax.lax.conv_general_dilated(h.astype(dtype), layer["w"].astype(dtype), (stride, stride), "VALID",
                                         dimension_numbers=("NHWC", "HWIO", "NHWC"),
                                         preferred_element_type=jnp.float32)
        h = jax.nn.relu(h + layer["b"])
    return jnp.sum(h * h)


def main(argv: list[str]) -> None:
    size, batch = (int(a) for a in argv[:2]) if len(argv) >= 2 else (84, 32)
    params = init_encoder(np.random.default_rng(0), (size, size, 9))
    convs = [{k: jnp.asarray(v) for k, v in layer.items()} for layer in params["convs"]]
    images = jnp.asarray(np.random.default_rng(1).integers(0, 255, (batch, size, size, 9)), jnp.uint8)
    for dtype in (jnp.float32, jnp.bfloat16) * 2:
        grad = jax.jit(jax.grad(lambda c, x, d=dtype: conv_loss(c, x, d)))
        jax.block_until_ready(grad(convs, images))
        times = []
        for _ in range(5):
            start = time.perf_counter()
            jax.block_until_ready(grad(convs, images))
            times.append(time.perf_counter() - start)
        print(f"{size}x{size}x9, batch {batch}, {jnp.dtype(dtype).name}: {sorted(times)[2] * 1000:.1f} ms")


if __name__ == "__main__":
    main(sys.argv[1:])
