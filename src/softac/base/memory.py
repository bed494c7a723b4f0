"""What memory the machine has, and what a transition row takes: the numbers the replay buffers and the
learner check before they allocate anything (a run the machine cannot hold is refused in one line)."""

from __future__ import annotations

import os


def available_memory_bytes() -> int:
    """MemAvailable from /proc/meminfo, else physical memory, else a large number."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return 1 << 62


def memory_shortfall(need: float, fraction: float = 0.8, available: int | None = None, where: str = "") -> str | None:
    """None where `need` bytes fit in `fraction` of the memory available now (the host's, else `available`, a
    device's), else what a refusal says of it: "<need><where> but only <available> is available"."""
    have = available_memory_bytes() if available is None else available
    return None if need <= fraction * have else f"{human_bytes(need)}{where} but only {human_bytes(have)} is available"


def human_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"


def transition_bytes(obs_dim: int, act_dim: int) -> int:
    """A float32 transition row: obs, next_obs, action, reward and terminated, and a done flag (one byte)."""
    return 4 * (2 * obs_dim + act_dim + 2) + 1
