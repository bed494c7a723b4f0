"""Machine leaves: CPUs and pinning, the JAX device, memory, headless OpenGL, stop signals."""
