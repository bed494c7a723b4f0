"""The run's settings: `SACConfig` (one typed dataclass, every hyperparameter once), its checks, presets and overrides.

`softac.config.SACConfig` and `softac.config.ConfigError` are the public names (as `softac.SACConfig`)."""

from softac.config.sac_config import ConfigError, SACConfig

__all__ = ["ConfigError", "SACConfig"]
