"""What a sweep is: its spec (env, seeds, grid or search space, overrides), parsing and checking it, and
the sweep directory's spec file (DIR/sweep.json)."""

from __future__ import annotations

import dataclasses
import itertools
import json
from pathlib import Path
from typing import Any

import yaml

from softac.config.sac_config import ConfigError, SACConfig, override_key
from softac.errors import SoftacError
from softac.peers import PEERS, sweep_config


SPEC_FILE = "sweep.json"
# what a node that does not see the sweep directory is told, by the driver and by a trial (docs/cluster.md)
SHARED_DIR_HINT = "every node needs it on a shared filesystem at the same path (docs/cluster.md)"


RAY_DIR = "_ray"


LOG_DIR = "_logs"


PLOT_DIR = "plots"


FRAMEWORKS = ("softac", *PEERS)


SEARCHES = ("random", "optuna")


METRIC = "eval_mean_return"


INSTALL_RAY = "softac sweep needs Ray Tune: pip install 'softac[ray]' (from a checkout: pip install -e '.[ray]')"


# The documented SAC search space (docs/sweeps.md); `--space FILE` replaces it. Each key is a config key,
# each value one of: {loguniform: [lo, hi]}, {uniform: [lo, hi]}, {randint: [lo, hi]} (hi excluded),
# {choice: [v1, v2, ...]}.
DEFAULT_SPACE: dict[str, dict[str, list[Any]]] = {
    "actor_lr": {"loguniform": [1e-4, 3e-3]},
    "critic_lr": {"loguniform": [1e-4, 3e-3]},
    "tau": {"loguniform": [0.002, 0.1]},
    "gamma": {"choice": [0.95, 0.98, 0.99, 0.995]},
    "batch_size": {"choice": [64, 128, 256]},
    "hidden_sizes": {"choice": [[64, 64], [128, 128], [256, 256]]},
    "gradient_steps": {"choice": [1, 2]},
}


SPACE_KINDS = ("loguniform", "uniform", "randint", "choice")


@dataclasses.dataclass
class SweepSpec:
    """Everything that defines a sweep's trials (stored as DIR/sweep.json; a rerun must match it)."""

    env_id: str
    steps: int
    seeds: list[int]
    preset: str | None = None
    overrides: list[str] = dataclasses.field(default_factory=list)
    grid: dict[str, list[Any]] = dataclasses.field(default_factory=dict)
    framework: str = "softac"
    search: str | None = None
    samples: int = 0
    space: dict[str, dict[str, list[Any]]] | None = None
    asha: bool = False
    # each trial stops once its deterministic eval mean reaches this (RLlib's stop criterion; `softac train
    # --target-return`): its last evaluation is then that one
    target_return: float | None = None
    # ... or once its eval success rate reaches this (a goal env's; `softac train --target-success`)
    target_success: float | None = None

    def preset_config(self) -> SACConfig:
        """The preset (or the env's own) with the overrides, before the sweep's step budget."""
        return sweep_config(self.env_id, self.preset, self.overrides)  # checked with the preset at once

    def base_config(self) -> SACConfig:
        return self.preset_config().replace(total_steps=self.steps)

    def describe(self) -> str:
        """The configuration by framework and preset, for tables and legends: "softac, crossq preset",
        "softac, env preset + obs_norm=true", "SBX CrossQ, its defaults" (a peer's own settings are fixed);
        ", stops at R" where the trials stop at a target return (", stops at success S" at a success rate)."""
        name = self._configuration()
        if self.target_return is not None:
            name += f", stops at {self.target_return:g}"
        if self.target_success is not None:
            name += f", stops at success {self.target_success:g}"
        return name

    def _configuration(self) -> str:
        if self.framework in PEERS and PEERS[self.framework].settings != "sweep":
            # of what such a peer takes, only the env's action repeat changes what it trains
            repeat = [pair.strip() for pair in self.overrides if override_key(pair.split("=", 1)[0]) == "action_repeat"]
            return " + ".join([PEERS[self.framework].label, *repeat])
        if self.framework in PEERS:
            name = f"{PEERS[self.framework].label} as softac's {self.preset or 'env'} preset"
            return f"{name} + {' '.join(self.overrides)}" if self.overrides else name
        name = f"softac, {self.preset or 'env'} preset"
        return f"{name} + {' '.join(self.overrides)}" if self.overrides else name

    def swept_keys(self) -> list[str]:
        return list(self.space or {}) if self.search else list(self.grid)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "SweepSpec":
        known = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in known})


def parse_seeds(text: str, first: int = 0) -> list[int]:
    """`N` means seeds first..first+N-1; `a,b,c` lists them."""
    try:
        if "," in text:
            seeds = [int(s) for s in text.split(",") if s.strip()]
        else:
            count = int(text)
            if count == 0:
                raise SoftacError(
                    "--seeds 0 asks for no seeds (a bare number is a count): for seed 0 alone write --seeds 0,"
                )
            if count < 0:
                raise ValueError
            seeds = list(range(first, first + count))
    except ValueError:
        raise SoftacError(f"--seeds takes a count N or a comma list of seeds, got {text!r}") from None
    if not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0:
        raise SoftacError(f"--seeds needs distinct seeds >= 0, got {text!r}")
    return seeds


def _split_top_level(text: str) -> list[str]:
    """Split on commas outside brackets: `hidden_sizes=[64,64],[256,256]` has two values."""
    parts, depth, current = [], 0, ""
    for ch in text:
        depth += ch in "[{("
        depth -= ch in "]})"
        if ch == "," and depth == 0:
            parts.append(current)
            current = ""
        else:
            current += ch
    parts.append(current)
    return [p.strip() for p in parts]


def parse_grid(items: list[str]) -> dict[str, list[Any]]:
    grid: dict[str, list[Any]] = {}
    for item in items:
        if "=" not in item:
            raise SoftacError(f"--grid expects KEY=V1,V2,..., got {item!r}")
        key, raw = item.split("=", 1)
        key = override_key(key)
        values = []
        for part in _split_top_level(raw):
            if not part:
                raise SoftacError(f"--grid {key}: empty value in {raw!r}")
            try:
                values.append(yaml.safe_load(part))
            except yaml.YAMLError:
                values.append(part)
        if key in grid:
            raise SoftacError(f"--grid {key} given twice")
        if len({json.dumps(v) for v in values}) != len(values):
            raise SoftacError(f"--grid {key} repeats a value: {raw!r}")
        grid[key] = values
    return grid


def value_text(value: Any) -> str:
    """A value as a `--set` accepts it (JSON is YAML) and as a short directory-name part."""
    return json.dumps(value, separators=(",", ":"))  # no spaces: the summary's --set line pastes into a shell


def _name_part(value: Any) -> str:
    if isinstance(value, list):
        return "x".join(str(v) for v in value)
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value).replace("/", "_").replace(" ", "")


def grid_points(grid: dict[str, list[Any]]) -> list[dict[str, Any]]:
    keys = list(grid)
    return [dict(zip(keys, combo)) for combo in itertools.product(*(grid[k] for k in keys))]


def trial_name(values: dict[str, Any], seed: int) -> str:
    return ",".join([f"{k}={_name_part(v)}" for k, v in values.items()] + [f"seed={seed}"])


def search_trial_name(trial_id: str, seed: int) -> str:
    """The run directory of a search's trial (Tune's trial id: the sampled values are in its config.yaml)."""
    return f"trial={trial_id},seed={seed}"


def grid_trials(spec: SweepSpec) -> list[dict[str, Any]]:
    return [{"name": trial_name(values, seed), "seed": seed, "values": values}
            for values in grid_points(spec.grid) for seed in spec.seeds]


def load_space(path: str | None) -> dict[str, dict[str, list[Any]]]:
    if path is None:
        return json.loads(json.dumps(DEFAULT_SPACE))
    try:
        data = yaml.safe_load(Path(path).read_text())
    except OSError as exc:
        raise SoftacError(f"cannot read search space {path}: {exc.strerror or exc}") from None
    except yaml.YAMLError as exc:
        raise SoftacError(f"search space {path} is not valid YAML: {str(exc).splitlines()[0]}") from None
    if not isinstance(data, dict) or not data:
        raise SoftacError(f"search space {path} must map config keys to {{kind: values}}")
    return data


def check_space(space: dict[str, Any], base: SACConfig) -> None:
    for key, dist in space.items():
        if not (isinstance(dist, dict) and len(dist) == 1 and next(iter(dist)) in SPACE_KINDS):
            raise SoftacError(f"search space key {key}: expected one of {', '.join(SPACE_KINDS)} "
                              f"with a list, got {dist!r}")
        kind, values = next(iter(dist.items()))
        if not isinstance(values, list) or not values:
            raise SoftacError(f"search space key {key}: {kind} needs a list")
        if kind != "choice":
            if len(values) != 2 or not all(isinstance(v, (int, float)) for v in values) or values[0] >= values[1]:
                raise SoftacError(f"search space key {key}: {kind} needs [low, high] with low < high")
            if kind == "loguniform" and values[0] <= 0:
                raise SoftacError(f"search space key {key}: loguniform needs low > 0")
        probes = values if kind == "choice" else [values[0]]
        for value in probes:  # unknown keys and impossible values fail here, before Ray starts
            base.with_overrides([f"{key}={value_text(value)}"])


def default_threshold(env_id: str) -> float | None:
    """The env's registered reward_threshold (InvertedPendulum: 950), if it has one."""
    import gymnasium as gym

    try:
        threshold = gym.spec(env_id).reward_threshold
    except Exception:  # unknown ids are reported by validate()
        return None
    return None if threshold is None else float(threshold)


def check_peer_spec(spec: SweepSpec, base: SACConfig) -> None:
    """A peer's sweep: softac's settings only where the peer runs at them (a "sweep" peer: --preset and --set,
    each one it cannot take refused here), the goal env a HER peer needs, its package installed."""
    from softac.envs.make import make_env
    from softac.peers import check_her_env, missing_peers, peer_settings

    peer = PEERS[spec.framework]
    if peer.package == "brax":
        from softac.peers.brax_sac import check_playground_env

        check_playground_env(spec.env_id, named=f"--framework {spec.framework}")
    if peer.settings == "sweep":
        if spec.grid or spec.search:
            raise SoftacError(f"--framework {spec.framework} runs at one config (--preset and --set): --grid and "
                              "--search are for softac")
    else:
        # how the run is measured, and the env's action repeat, which a peer takes as softac does
        allowed = {"eval_interval", "eval_episodes", "log_interval", "action_repeat"}
        own = [pair for pair in spec.overrides if override_key(pair.split("=", 1)[0]) not in allowed]
        if spec.grid or spec.search or spec.preset or own:
            raise SoftacError(f"--framework {spec.framework} runs {peer.about}, not softac's "
                              "settings: --grid, --search, --preset and --set (other than eval_interval/"
                              "eval_episodes/log_interval/action_repeat) are for softac")
    if peer.settings == "zoo":  # RL Zoo's settings for the env, or a refusal: no env needs making
        try:
            peer_settings(spec.framework, base, 0, spec.env_id)
        except ValueError as exc:
            raise SoftacError(f"--framework {spec.framework}: {exc}") from None
    if peer.her or peer.settings == "sweep":  # checked now, not in every trial after Ray starts
        env = make_env(spec.env_id)
        try:
            check_her_env(spec.framework, env, spec.env_id, named=f"--framework {spec.framework}")
            peer_settings(spec.framework, base, int(env.action_space.shape[0]))
        except ValueError as exc:
            raise SoftacError(f"--framework {spec.framework}: {exc}") from None
        finally:
            env.close()
    if missing_peers([spec.framework]):
        if peer.extra != "bench":
            raise SoftacError(f"--framework {spec.framework} needs the [{peer.extra}] extra: "
                              f"pip install -e '.[{peer.extra}]'")
        raise SoftacError(f"--framework {spec.framework} needs the [bench] extra: `make bench` "
                          "(or: pip install torch==2.13.0 && pip install -e '.[bench]')")


# the keys a sweep sets in each trial's command itself, by the sweep's option that sets them
SWEEP_SETS = {"seed": "--seeds", "total_steps": "--steps"}


def _refuse_keys_the_sweep_sets(spec: SweepSpec) -> None:
    """`--set seed=3` (or a grid or space over it) beside the sweep's own --seeds would disagree with each trial's
    --seed flag (a trial's `softac train` refuses that; issue 65): one line now, before Ray starts."""
    for where, keys in (("--set", [override_key(pair.split("=", 1)[0]) for pair in spec.overrides]),
                        ("--grid", list(spec.grid)), ("--space", list(spec.space or {}) if spec.search else [])):
        for key in keys:
            if key in SWEEP_SETS:
                raise SoftacError(f"{where} {key}: a sweep sets {key} from its {SWEEP_SETS[key]}; drop it from {where}")


def validate(spec: SweepSpec) -> SACConfig:
    """Every trial's config, checked before Ray starts (bad input fails in a second, with one line)."""
    from softac.envs.make import resolve_env_id

    if spec.framework not in FRAMEWORKS:
        raise SoftacError(f"--framework must be one of {', '.join(FRAMEWORKS)}")
    resolve_env_id(spec.env_id)
    if spec.target_success is not None:
        from softac.run.stopping import check_success_rate

        check_success_rate(spec.target_success, "--target-success")
    _refuse_keys_the_sweep_sets(spec)
    base = spec.base_config()
    if spec.framework != "softac":
        check_peer_spec(spec, base)
    if spec.search:
        if spec.grid:
            raise SoftacError("--grid and --search are alternatives: a grid sweeps listed values, a search samples")
        if spec.samples < 1:
            raise SoftacError("--samples must be >= 1")
        if len(spec.seeds) != 1:
            raise SoftacError("a search runs each sampled configuration on one seed (--seeds 1); run the best "
                              "configurations again with --grid and several seeds")
        check_space(spec.space or {}, base)
    elif spec.asha:
        raise SoftacError("--asha stops trials early and needs --search (random or optuna)")
    for values in grid_points(spec.grid):
        try:
            base.with_overrides([f"{k}={value_text(v)}" for k, v in values.items()])
        except ConfigError as exc:
            raise SoftacError(f"--grid: {exc}") from None
    return base


def prepare_out_dir(out: Path, spec: SweepSpec) -> None:
    """A new sweep takes an empty or missing DIR; an existing sweep continues only with the same spec, or,
    for a grid, with more seeds (the finished trials are kept: `--seeds 5` after `--seeds 3` runs seeds 3
    and 4) or, for softac's grid, more steps (finished trials continue from their last checkpoint)."""
    from softac.run.run_dir import LOCK, write_atomic

    spec_path = out / SPEC_FILE
    if spec_path.exists():
        try:
            stored = json.loads(spec_path.read_text())
        except (OSError, ValueError) as exc:
            raise SoftacError(f"cannot read {spec_path}: {exc}") from None
        mine = spec.to_dict()
        differs = sorted(k for k in set(stored) | set(mine) if stored.get(k) != mine.get(k))
        growable = bool(differs) and set(differs) <= {"seeds", "steps"}
        if growable and "steps" in differs:
            _check_budget_raise(out, stored, spec)  # a shorter budget, a search's or a peer's is refused here
        more_seeds = "seeds" not in differs or set(stored.get("seeds") or []) < set(mine["seeds"])
        if growable and more_seeds and not spec.search:
            try:  # the sweep grows: its spec now names every seed and its budget, for --resume and the summaries
                write_atomic(spec_path, (json.dumps(mine, indent=1) + "\n").encode())
            except OSError as exc:
                raise SoftacError(f"cannot update {spec_path}: {exc.strerror or exc}") from None
        elif differs:
            grow = " (a grid may only gain seeds)" if differs == ["seeds"] and not spec.search else ""
            raise SoftacError(f"{out} holds a different sweep (differs in {', '.join(differs)}{grow}); continue it "
                              f"with `softac sweep --resume {out}` or pick another --out")
        return

    if out.exists() and (not out.is_dir() or any(p.name != LOCK for p in out.iterdir())):
        raise SoftacError(f"{out} exists and is not a sweep directory; pick another --out")

    try:
        out.mkdir(parents=True, exist_ok=True)
        write_atomic(spec_path, (json.dumps(spec.to_dict(), indent=1) + "\n").encode())
    except OSError as exc:
        raise SoftacError(f"cannot create sweep directory {out}: {exc.strerror or exc}") from None


def _check_budget_raise(out: Path, stored: dict[str, Any], spec: SweepSpec) -> None:
    """More steps per trial: softac's grid trials continue from their checkpoints (resume is exact). A peer's
    checkpoint is tied to the budget it was started with, and a search's schedule (ASHA) to its own."""
    old = stored.get("steps")
    if not isinstance(old, int) or spec.steps < old:
        raise SoftacError(f"{out} is a sweep of {old} steps per trial; --steps {spec.steps} cannot shorten it (its "
                          "trials may have trained past that)")
    if spec.search:
        raise SoftacError(f"{out} is a {spec.search} search of {old} steps per trial; its budget cannot be raised "
                          "(check the best configuration on more steps with the command in its summary.md)")
    if spec.framework != "softac":
        raise SoftacError(f"{out} is a sweep of {spec.framework} for {old} steps per trial; a peer's checkpoint is "
                          f"tied to its budget, so --steps {spec.steps} needs a new sweep (another --out)")


def load_spec(out: Path) -> SweepSpec:
    path = out / SPEC_FILE
    if not path.exists():
        raise SoftacError(f"{out} is not a sweep directory (no {SPEC_FILE})")
    try:
        return SweepSpec.from_dict(json.loads(path.read_text()))
    except (OSError, ValueError, TypeError) as exc:
        raise SoftacError(f"cannot read {path}: {exc}") from None


def planned_trials(spec: SweepSpec) -> int:
    return spec.samples if spec.search else len(spec.seeds) * len(grid_points(spec.grid))
