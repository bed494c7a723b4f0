"""Pick the JAX platform (cpu, gpu or auto) before JAX starts its backends."""

from __future__ import annotations

import contextlib
import gc
import importlib.util
import os
import sys

from softac.errors import SoftacError

_chosen: str | None = None


def compile_cache_dir() -> str | None:
    """Where compiled XLA programs are kept between processes (SOFTAC_COMPILE_CACHE=off disables)."""
    setting = os.environ.get("SOFTAC_COMPILE_CACHE", "")
    if setting.lower() in ("off", "0", "no", "false"):
        return None
    if setting:
        return setting
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "softac", "jax")


COMPILE_CACHE_MAX_BYTES = 2 << 30  # least recently used programs go beyond this


def _enable_compile_cache(jax) -> None:
    # a second run of the same config loads its compiled update instead of compiling it again
    # (seconds saved per process start; JAX's persistent compilation cache)
    path = compile_cache_dir()
    if path is None:
        return
    try:
        os.makedirs(path, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", path)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
    except Exception:  # a read-only home or an older JAX: run without the cache
        return
    if importlib.util.find_spec("filelock") is None:  # JAX's eviction needs it (a dependency of softac's)
        return
    with contextlib.suppress(Exception):  # an older JAX, or a cache we cannot write: unbounded, unlocked
        # A size limit turns on JAX's eviction and, with it, a file lock around every read and write of the
        # cache: without one, a process (a sweep's trial, a run beside another) could read an entry another is
        # still writing (JAX then warns and compiles again), and the cache grew without bound.
        _date_undated_entries(path)
        jax.config.update("jax_compilation_cache_max_size", COMPILE_CACHE_MAX_BYTES)


def _date_undated_entries(path: str) -> None:
    """Give each entry an unbounded cache wrote (softac before the limit, or plain JAX) the access-time file
    that JAX's eviction reads: without it, every later write warns (FileNotFoundError) and is dropped."""
    import time

    import filelock

    with filelock.FileLock(os.path.join(path, ".lockfile"), timeout=10):  # JAX's own lock on the cache
        names = set(os.listdir(path))
        keys = {name.removesuffix("-cache") for name in names if name.endswith("-cache")}
        stamp = time.time_ns().to_bytes(8, "little")
        for key in keys - {name.removesuffix("-atime") for name in names}:
            with open(os.path.join(path, f"{key}-atime"), "wb") as f:
                f.write(stamp)


def select_device(device: str) -> str:
    """Returns the platform in use: 'cpu' or 'gpu'. The first call in a process decides."""
    global _chosen
    device = "gpu" if device == "cuda" else device
    import jax

    if _chosen is None:
        _enable_compile_cache(jax)
        if device == "cpu":
            jax.config.update("jax_platforms", "cpu")
        # gpu and auto: JAX's own choice (a GPU where its plugin finds one), checked below
        try:
            platform = jax.default_backend()
        except RuntimeError as exc:
            if device == "gpu":
                raise SoftacError("device=gpu but JAX finds no GPU; install jax[cuda12] "
                                  "(pip install -U 'jax[cuda12]') or use --device cpu") from None
            raise SoftacError(f"JAX could not start: {exc}".splitlines()[0]) from None
        _chosen = "cpu" if platform == "cpu" else "gpu"
    if device == "gpu" and _chosen != "gpu":
        raise SoftacError("device=gpu but JAX finds no GPU in this process; install jax[cuda12] "
                          "(pip install -U 'jax[cuda12]') or use --device cpu")
    return _chosen


DEFAULT_MAX_MAP_COUNT = 65530  # Linux's vm.max_map_count unless the machine sets another


def memory_map_count() -> int | None:
    """How many memory mappings this process holds (/proc/self/maps' lines), or None where that is not known."""
    try:
        with open("/proc/self/maps", "rb") as maps:
            return sum(1 for _ in maps)
    except OSError:
        return None


def max_map_count() -> int:
    try:
        with open("/proc/sys/vm/max_map_count") as limit:
            return int(limit.read())
    except (OSError, ValueError):
        return DEFAULT_MAX_MAP_COUNT


def release_compiled_programs_near_map_limit(fraction: float = 0.5) -> bool:
    """XLA's CPU backend maps each compiled program's code into memory regions of its own (about 500 for the
    programs of one small agent's training), and Linux grants a process vm.max_map_count of them (65,530 by
    default): past that, compiling fails ("LLVM compilation error: Cannot allocate memory") and the process
    dies of a segmentation fault. A process that builds agent after agent (a notebook's grid of settings, a test
    session) reaches it after ~130 of them. Where this process holds more than `fraction` of the limit, JAX's
    compiled programs are dropped (jax.clear_caches: later calls compile again, or load from the persistent
    compile cache), which unmaps them. Returns whether it did."""
    count = memory_map_count()
    jax = sys.modules.get("jax")
    if jax is None or count is None or count < fraction * max_map_count():
        return False
    jax.clear_caches()
    gc.collect()
    return True
