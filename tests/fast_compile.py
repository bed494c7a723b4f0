"""XLA flags that make `make test` compile its thousands of tiny programs faster (issue 64), and what the tests
do with them. Run as a script (the Makefile's FAST_COMPILE), it prints those of them the installed jaxlib knows:
a flag XLA does not know aborts every compile, and the flags are XLA's debug options, which a release may drop.

- --xla_backend_optimization_level=0: LLVM at its lowest level, programs compile in about 60% of the time and run
  about 2x slower, which the tests' few hundred updates do not feel.
- --xla_cpu_use_fusion_emitters=false: XLA's earlier code generation for fused loops (its elemental emitters)
  instead of its MLIR fusion emitters; at level 0 a tiny SAC update compiles in a third of the time (crossq at
  32 wide: 2.4 -> 0.8 s of backend compile on an AMD EPYC with AVX-512 BF16, 2026-12-07), and make test took 737 s
  instead of 926 s.

Both compute the same functions, rounded in other orders where XLA fuses otherwise: a test that compares two
*different* programs bit for bit (one agent with a variant and one without, "nothing else changes") holds under
XLA's default code generation, as users compile, and is marked `users_xla`: conftest runs it in a pytest process
of its own with XLA_FLAGS as the user set them (users_xla_flags). The learning test trains with those too."""

from __future__ import annotations

import os
import subprocess
import sys

FLAGS = ("--xla_backend_optimization_level=0", "--xla_cpu_use_fusion_emitters=false")


def users_xla_flags(flags: str | None = None) -> str:
    """XLA_FLAGS without any of FLAGS' options (whatever their values): what the user's own commands compile with."""
    names = {flag.split("=", 1)[0] for flag in FLAGS}
    given = (os.environ.get("XLA_FLAGS", "") if flags is None else flags).split()
    return " ".join(f for f in given if f.split("=", 1)[0] not in names)


def fast_compile_in_effect() -> bool:
    return users_xla_flags() != " ".join(os.environ.get("XLA_FLAGS", "").split())


def known_flags() -> list[str]:
    """FLAGS that this jaxlib compiles a program with (one process each, ~1 s)."""
    probe = "import jax; jax.jit(lambda x: x + 1)(1.0).block_until_ready()"
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    return [flag for flag in FLAGS
            if subprocess.run([sys.executable, "-c", probe], env={**env, "XLA_FLAGS": flag},
                              capture_output=True).returncode == 0]


if __name__ == "__main__":
    print(" ".join(known_flags()))
