"""Names the config refers to outside itself, as data: the id forms of the env families that choose presets
(issue 43), the network kinds and the logger backends. The config checks them without importing the envs or the loggers, which
import them from here (the config is a leaf: issue 65)."""

from __future__ import annotations

from softac.errors import SoftacError

DMC_PREFIX = "dm_control/"
SHORT_PREFIX = "dmc:"
PLAYGROUND_PREFIXES = ("playground/", "playground:")  # MuJoCo Playground's envs: collected on the device (issue 67)
BACKENDS = ("tensorboard", "wandb", "mlflow")
# the network kinds a config may name (softac.learner.networks.NETWORKS holds each; `crossq` picks the
# batch-renormalised MLP itself): named here so that a bad name is refused before anything is built
NETWORK_NAMES = ("mlp", "simba", "bn_mlp", "flashsac")


def long_id(env_id: str) -> str:
    """`dmc:cheetah-run` -> `dm_control/cheetah-run-v0`; other ids unchanged."""
    if env_id.startswith(SHORT_PREFIX):
        return f"{DMC_PREFIX}{env_id[len(SHORT_PREFIX):]}-v0"
    return env_id


def is_dmc_id(env_id: str) -> bool:
    return env_id.startswith((DMC_PREFIX, SHORT_PREFIX))


def is_playground_id(env_id: str) -> bool:
    return env_id.startswith(PLAYGROUND_PREFIXES)


def task_preset_name(env_id: str) -> str:
    """The name a preset of one DeepMind Control task has: `dmc:cheetah-run` and `dm_control/cheetah-run-v0` ->
    `dmc-cheetah-run` (a file name on every system, where `dmc:` is not)."""
    task = long_id(env_id)[len(DMC_PREFIX):]
    return f"dmc-{task.removesuffix('-v0')}"


def parse_backends(text: str) -> list[str]:
    """`tensorboard,wandb` -> the backend names; `none` or empty -> [] (CSV only). Unknown names refused."""
    names = [n.strip().lower() for n in str(text).split(",") if n.strip()]
    if names in ([], ["none"]) or names == ["csv"]:
        return []
    names = [n for n in names if n != "csv"]  # CSV is always on; naming it is harmless
    unknown = [n for n in names if n not in BACKENDS]
    if unknown:
        raise SoftacError(f"unknown logger '{unknown[0]}': choose from {', '.join(BACKENDS)} (comma-separated), "
                          "or none for the CSV files only")
    return list(dict.fromkeys(names))
