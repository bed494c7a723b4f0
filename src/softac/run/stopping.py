"""What stops a run before its step budget: an evaluation that reached a target (a mean return, a goal env's
success rate), for softac's training and a peer's run (softac.peers) alike. A callback's own stop is the
callback's (softac.run.callbacks); Ctrl-C and SIGTERM are softac.base.stop_signal's."""

from __future__ import annotations

from softac.errors import SoftacError


def check_success_rate(value: float | None, name: str) -> None:
    """A success rate to reach (--target-success, a sweep's --success-threshold): None, or in (0, 1]."""
    if value is not None and not 0.0 < value <= 1.0:
        raise SoftacError(f"{name} is a success rate in (0, 1], got {value}")


def target_reached(mean_return: float, success_rate: float | None, target_return: float | None,
                   target_success: float | None) -> str | None:
    """Which target an evaluation reached, `target_return` or `target_success` (a goal env's), else None: what stops
    softac's training and a peer's run (softac.peers) alike."""
    if target_return is not None and mean_return >= target_return:
        return "target_return"
    if target_success is not None and success_rate is not None and success_rate >= target_success:
        return "target_success"
    return None
