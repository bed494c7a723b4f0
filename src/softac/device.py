"""Pick the JAX platform (cpu, gpu or auto) before JAX starts its backends."""

from __future__ import annotations

import os

from softac.errors import SoftacError

_chosen: str | None = None


def select_device(device: str) -> str:
    """Returns the platform in use: 'cpu' or 'gpu'. The first call in a process decides."""
    global _chosen
    device = "gpu" if device == "cuda" else device
    import jax

    if _chosen is None:
        if device == "cpu":
            jax.config.update("jax_platforms", "cpu")
        elif device == "gpu":
            jax.config.update("jax_platforms", "cuda,rocm" if not os.environ.get("JAX_PLATFORMS") else os.environ["JAX_PLATFORMS"])
        try:
            platform = jax.default_backend()
        except RuntimeError as exc:
            if device == "gpu":
                raise SoftacError("device=gpu but JAX finds no GPU; install jax[cuda12] "
                                  "(pip install -U 'jax[cuda12]') or use --device cpu") from None
            raise SoftacError(f"JAX could not start: {exc}".splitlines()[0]) from None
        _chosen = "cpu" if platform == "cpu" else "gpu"
    if device == "gpu" and _chosen != "gpu":
        raise SoftacError("device=gpu but JAX runs on the CPU in this process; use --device cpu")
    return _chosen
