"""The YAML presets (softac/config/presets/*.yaml): their names, their values (`extends: OTHER` starts from
another's), and the comment lines that describe them (`softac presets`, `softac presets NAME`)."""

from __future__ import annotations

import difflib
from importlib import resources
from typing import Any

import yaml

from softac.errors import ConfigError

FALLBACK_PRESET = "default"
GENERIC_PRESETS = ("default", "sb3", "cleanrl", "crossq", "crossq-avg", "crossq-wn", "sac-100k", "tqc", "simba", "droq",
                   "drq", "xqc", "flashsac", "brax-sac", "fastsac", "rlpd")

DMC_PRESET = "dmc"  # every DeepMind Control task without a preset of its own (issue 43); names no env itself


def _preset_dir():
    return resources.files("softac.config") / "presets"


def preset_names() -> list[str]:
    return sorted(p.name[: -len(".yaml")] for p in _preset_dir().iterdir() if p.name.endswith(".yaml"))


def load_preset(name: str, _seen: tuple[str, ...] = ()) -> dict[str, Any]:
    """A preset's values; `extends: OTHER` in a preset file starts from OTHER's values (the MuJoCo env
    presets extend `crossq`, so its settings are written once)."""
    names = preset_names()
    if name not in names:
        close = difflib.get_close_matches(name, names, n=1)
        hint = f" (did you mean {close[0]}?)" if close else ""
        raise ConfigError(f"unknown preset '{name}'{hint}; `softac presets` lists them")
    if name in _seen:
        raise ConfigError(f"preset '{name}' extends itself ({' -> '.join((*_seen, name))})")
    data = _preset_file_values(name)
    base = data.pop("extends", None)
    return {**load_preset(str(base), (*_seen, name)), **data} if base else data


def _preset_text(name: str) -> str:
    return (_preset_dir() / f"{name}.yaml").read_text()


def _preset_file_values(name: str) -> dict[str, Any]:
    """What the preset's own file sets, `extends` included."""
    return dict(yaml.safe_load(_preset_text(name)) or {})


def preset_extends(name: str) -> str | None:
    """The preset a preset's file starts from (`extends:`), or None."""
    base = _preset_file_values(name).get("extends")
    return str(base) if base else None


def _preset_comments(name: str) -> list[str]:
    return [line.lstrip("#").strip() for line in _preset_text(name).splitlines() if line.startswith("#")]


def preset_summary(name: str) -> str:
    """The first comment line of a preset file: what it is for, in one sentence (`softac presets` lists it)."""
    comments = _preset_comments(name)
    return comments[0] if comments else ""


def preset_description(name: str) -> str:
    """The comment lines after the summary: settings, sources, departures and figures (`softac presets NAME`)."""
    return "\n".join(_preset_comments(name)[1:])
