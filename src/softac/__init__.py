"""softac: Soft Actor-Critic for continuous-control Gymnasium environments, on JAX."""

from softac.config import ConfigError, SACConfig
from softac.errors import SoftacError, TrainingInterrupted
from softac.version import __version__

__all__ = ["SAC", "SACConfig", "evaluate", "show", "ConfigError", "SoftacError", "TrainingInterrupted", "__version__"]


def __getattr__(name: str):
    # JAX is imported only when an agent is needed, so `softac presets` and `--help` start fast
    if name == "SAC":
        from softac.agent import SAC

        return SAC
    if name == "evaluate":
        from softac.evaluation import evaluate

        return evaluate
    if name == "show":
        from softac.notebook import show

        return show
    raise AttributeError(name)
