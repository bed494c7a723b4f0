"""softac: Soft Actor-Critic for continuous-control Gymnasium environments, on JAX.

The package's sub-packages, ranked by the data flow (each imports only its own and lower ranks:
tests/test_package_ranks.py): base, config, envs, replay, learner, run, outputs, then agent.py, peers,
sweep, cli. docs/development.md is the map.
"""

import importlib
import importlib.abc
import importlib.util
import sys

from softac.config.sac_config import ConfigError, SACConfig
from softac.errors import SoftacError, TrainingInterrupted
from softac.version import __version__

__all__ = ["SAC", "SACConfig", "evaluate", "show", "ConfigError", "SoftacError", "TrainingInterrupted", "__version__"]


# Modules that lived at the package's top level before issue 65 moved them into sub-packages: importable at
# their old paths too (`from softac.callbacks import Callback`, `python -m softac.bench`), as the very module
# of the new path, so that a name patched through either path is the same name.
MOVED = {
    "baselines": "outputs.reference", "bench": "peers.bench", "buffer": "replay.buffer",
    "callbacks": "run.callbacks", "checkpoint": "run.checkpoint", "collector": "replay.collector",
    "commands": "cli.commands", "cpus": "base.cpus", "device": "base.device", "dmc": "envs.dmc",
    "encoder": "learner.encoder", "env_workers": "envs.workers", "evaluation": "run.evaluation",
    "exploration": "replay.exploration", "export": "outputs.export", "export_numpy": "learner.numpy_forward",
    "gl": "base.opengl", "image_buffer": "replay.image_buffer", "loggers": "run.loggers", "logs": "run.csv_logs",
    "loop": "run.loop", "losses": "learner.losses", "memory": "base.memory", "networks": "learner.networks",
    "normalization": "learner.normalization", "notebook": "outputs.notebook", "peer_settings": "peers.settings",
    "pixels": "envs.pixels", "plots": "outputs.plots", "policy": "learner.policy", "report": "outputs.report",
    "rundir": "run.run_dir", "runstate": "run.run_state", "sac": "learner.sac",
    "snapshot": "run.checkpoint_contents", "stats": "outputs.seed_stats", "stopsignal": "base.stop_signal",
    "video": "outputs.video",
}


class _OldPaths(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds `softac.OLD` for the modules in MOVED and loads it as the module at its new path."""

    def find_spec(self, fullname, path=None, target=None):
        old = fullname.removeprefix(f"{__name__}.")
        if old == fullname or old not in MOVED:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec):
        module = importlib.import_module(self._new(spec.name))
        spec.loader_state = module.__spec__  # the import system sets __spec__ to the old path's: put back below
        return module

    def exec_module(self, module):
        module.__spec__ = module.__spec__.loader_state

    def get_code(self, fullname):  # `python -m softac.OLD` runs the new module's code
        new = self._new(fullname)
        return importlib.util.find_spec(new).loader.get_code(new)

    @staticmethod
    def _new(fullname: str) -> str:
        return f"{__name__}.{MOVED[fullname.removeprefix(f'{__name__}.')]}"


if not any(isinstance(finder, _OldPaths) for finder in sys.meta_path):
    sys.meta_path.append(_OldPaths())


def __getattr__(name: str):
    # JAX is imported only when an agent is needed, so `softac presets` and `--help` start fast
    if name == "SAC":
        from softac.agent import SAC

        return SAC
    if name == "evaluate":
        from softac.run.evaluation import evaluate

        return evaluate
    if name == "show":
        from softac.outputs.notebook import show

        return show
    raise AttributeError(name)
