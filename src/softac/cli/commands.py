"""What each `softac` command does (softac.cli.main parses the command line and maps errors to exit codes): train,
eval, video, plot, report, export, baselines, presets, sweep and bench, each a function of the parsed arguments
that returns the exit code."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

from softac.errors import SoftacError, TrainingInterrupted

EXIT_OK, EXIT_INTERNAL, EXIT_BAD_INPUT, EXIT_RUN_FAILED, EXIT_INTERRUPTED = 0, 1, 2, 3, 130
EXIT_BROKEN_PIPE = 141  # 128 + SIGPIPE, what a shell reports for a Unix tool whose reader went away


# train's flags that set a config key, by key, each read from its argparse destination (--env is not one: it picks
# the preset, which `--set env_id=` may move to another env, as a sweep's grid over env_id does)
FLAG_OF_KEY = {"total_steps": "--steps", "seed": "--seed", "n_envs": "--n-envs", "env_workers": "--env-workers",
               "device": "--device", "loggers": "--logger", "offline_data": "--offline-data"}


def _resolve_train_config(args: argparse.Namespace):
    from softac.config.sac_config import SACConfig, parse_overrides

    overrides = parse_overrides([pair for group in args.overrides for pair in group])
    direct = {key: getattr(args, flag.removeprefix("--").replace("-", "_")) for key, flag in FLAG_OF_KEY.items()}
    _refuse_flags_that_disagree_with_set(overrides, direct)
    # one replace, checked once: `--set env_workers=4 --n-envs 4` is valid though neither half is alone, and so is
    # `--preset fastsac --env Pendulum-v1 --n-envs 2` though the preset's 4096 envs are not on a host env
    changes = {**overrides, **{k: v for k, v in direct.items() if v is not None}}
    if args.config:
        config = SACConfig.from_yaml(args.config)
        return config.replace(**{**({"env_id": args.env} if args.env else {}), **changes})
    if args.preset:
        return SACConfig.preset(args.preset, env_id=args.env, overrides=changes)
    return SACConfig.for_env(args.env, overrides=changes)


def _refuse_flags_that_disagree_with_set(overrides: dict, flags: dict) -> None:
    """A flag and a `--set` of its key that say different things: one line naming both (the flag used to win
    silently, and `--steps 600 --set total_steps=1200` recorded 600, so a later --resume trained nothing; issue
    65). The same value twice is allowed."""
    for key, flag_value in flags.items():
        if flag_value is None or key not in overrides:
            continue
        value = overrides[key]
        same = (str(value).replace(" ", "") == str(flag_value).replace(" ", "") if key == "loggers"
                else value == flag_value)
        if not same:
            raise SoftacError(f"{FLAG_OF_KEY[key]} {flag_value} and --set {key}={value} disagree; give one")


def _default_run_dir(config) -> Path:
    name = config.env_id.replace(":", "_").replace("/", "_")
    return Path("runs") / name / f"{time.strftime('%Y%m%d-%H%M%S')}-seed{config.seed}"


def _pin_cpus(n: int | None) -> str | None:
    """--cpus, once the inputs are checked and before JAX starts (XLA sizes its thread pool from the CPUs
    this process may use); the line to print when training starts."""
    from softac.base.cpus import pin_this_process, usable_cpus

    if n is None:
        return None
    if n < 1:
        raise SoftacError(f"--cpus must be >= 1, got {n}")
    usable = usable_cpus()
    if not usable:
        return "softac: note: --cpus is ignored here (this OS cannot pin a process to CPUs)"
    if n > len(usable):
        raise SoftacError(f"--cpus {n}: this process may use {len(usable)} CPU(s) ({usable})")
    cpus, shared = pin_this_process(n)
    return f"pinned to CPUs {cpus}" + (" (shared: no free CPUs)" if shared else "")


def cmd_train(args: argparse.Namespace) -> int:
    from softac.run.stopping import check_success_rate
    from softac.run.run_dir import run_lock

    check_success_rate(args.target_success, "--target-success")

    if args.resume:
        clash = [flag for flag, value in (("--env", args.env), ("--preset", args.preset), ("--config", args.config),
                                          ("--seed", args.seed), ("--n-envs", args.n_envs), ("--out", args.out),
                                          ("--offline-data", args.offline_data))
                 if value is not None] + (["--set"] if args.overrides else [])
        if clash:
            raise SoftacError(f"--resume continues a run with its own config; drop {', '.join(clash)}")
        run = Path(args.resume)
        if not run.exists():  # before the lock, which would make the directory
            raise SoftacError(f"no such run or checkpoint: {run}")
        if args.steps is not None and args.total_steps is not None:
            raise SoftacError("--steps (steps to add) and --total-steps (steps to reach) say the same; give one")
    else:
        if args.allow_new_bounds:
            raise SoftacError("--allow-new-bounds goes with --resume (a new run takes its env's bounds)")
        if args.total_steps is not None:
            raise SoftacError("--total-steps goes with --resume (a new run trains --steps steps)")
        config = _resolve_train_config(args)
        run = Path(args.out) if args.out else _default_run_dir(config)
    # one writer per run, from before the checks that read it until the last file is written: a second
    # `softac train` into it (or `--resume` of it) exits 2 naming this process
    with run_lock(run):
        if args.resume:
            agent, steps, start, pinned = _resume_agent(run, args)
        else:
            agent, steps, start, pinned = _new_agent(config, run, args)
        for line in (pinned, start):  # printed once every input is accepted: a refused one gets one line only
            if line:
                print(line, file=sys.stderr)
        try:
            summary = agent.learn(steps, run_dir=run, target_return=args.target_return, progress=args.progress,
                                  target_success=args.target_success)
        except TrainingInterrupted as exc:
            # said before the lock goes: a stopped sweep waits for the lock, then its user reads the trial's log
            print(f"softac: {exc}", file=sys.stderr, flush=True)
            return EXIT_INTERRUPTED
        if args.video:
            _record_video(run, which=None, out=None, episodes=1, deterministic=True,
                          allow_new_bounds=args.allow_new_bounds)
    last = summary["last_eval"]
    solved = " (target reached)" if summary["stop_reason"] in ("target_return", "target_success") else ""
    eval_text = f"; last eval mean return {last:.1f}" if last is not None else ""
    if summary.get("last_success") is not None:
        eval_text += f", success rate {summary['last_success']:.2f}"
    print(f"done: {summary['steps']} steps in {summary['wall_s']:.1f}s{eval_text}{solved}; run in {run}",
          file=sys.stderr)
    return EXIT_OK


def _resume_agent(run: Path, args: argparse.Namespace):
    from softac.run import checkpoint as ckpt
    from softac.agent import SAC

    directory = ckpt.resolve(run, "last")
    if directory.parent.parent != run:
        raise SoftacError(f"--resume needs a run directory (with checkpoints/last), got {run}")
    _choose_gl_backend_if(args.video)
    pinned = _pin_cpus(args.cpus)
    # where metrics go is not part of the experiment: --logger may change it on resume
    agent = SAC.load(run, which="last", device=args.device, env_workers=args.env_workers,
                     allow_new_bounds=args.allow_new_bounds, loggers=args.logger)
    if args.total_steps is not None:
        if args.total_steps < agent.num_steps:
            raise SoftacError(f"{run} is at step {agent.num_steps}, past --total-steps {args.total_steps}")
        steps = args.total_steps - agent.num_steps
    else:
        steps = args.steps if args.steps is not None else max(agent.config.total_steps - agent.num_steps, 0)
    # (training raises the run's total_steps where this goes past it: TrainingLoop)
    return agent, steps, f"resuming {run} at step {agent.num_steps}; training {steps} more steps", pinned


def _new_agent(config, run: Path, args: argparse.Namespace):
    from softac.agent import SAC
    from softac.replay.buffer import check_buffer_memory
    from softac.config.names import parse_backends
    from softac.run.loggers import check_backends_installed
    from softac.run.run_dir import check_new_run_dir

    check_new_run_dir(run)  # before JAX starts: a clash should fail fast
    check_backends_installed(parse_backends(config.loggers))
    _choose_gl_backend_if(args.video)
    pinned = _pin_cpus(args.cpus)
    agent = SAC(config)
    per = agent.buffer_bytes_per_transition
    check_buffer_memory(config.buffer_size, per)
    start = (f"training {config.env_id} for {config.total_steps} steps (seed {config.seed}) -> {run}; replay buffer "
             f"{per:.0f} B per transition, {per * config.buffer_size / 2**20:.1f} MiB at buffer_size "
             f"{config.buffer_size:,}")
    offline = agent.collector.load_offline() if config.offline_data else None  # read now: a bad one fails first
    if offline is not None:
        start += f"; {offline.describe()}, {config.offline_mode}" + (
            f" ({config.offline_fraction:g} of each batch)" if config.mixes_offline_data else " into the replay")
    if config.learning_starts >= config.total_steps:  # a preset's warm-up past a short --steps (fastsac's 40,960)
        start += (f"\nsoftac: note: learning_starts={config.learning_starts:,} is not below the run's "
                  f"{config.total_steps:,} steps: it acts at random throughout and never updates (--set "
                  "learning_starts=N for fewer)")
    return agent, config.total_steps, start, pinned


def _choose_gl_backend_if(video: bool) -> None:
    if video:  # MuJoCo picks its GL backend when first imported: choose it now, fail early
        from softac.base.opengl import choose_gl_backend

        choose_gl_backend()


def cmd_eval(args: argparse.Namespace) -> int:
    from softac.agent import SAC
    from softac.run.evaluation import evaluate

    if args.episodes < 1:
        raise SoftacError("--episodes must be >= 1")
    agent = SAC.load(args.path, which=args.checkpoint, device=args.device, allow_new_bounds=args.allow_new_bounds)
    stats = evaluate(agent, episodes=args.episodes, deterministic=not args.stochastic, seed=args.seed,
                     policy=args.policy)
    stats["checkpoint_step"] = agent.num_steps
    stats["path"] = str(args.path)
    if args.json:
        print(json.dumps(stats))
    else:
        mode = "stochastic" if args.stochastic else "deterministic"
        if args.policy != "deployed":
            mode += f" ({args.policy})"
        success = f", success rate {stats['success_rate']:.2f}" if stats["success_rate"] is not None else ""
        print(f"{stats['env_id']}: mean return {stats['mean_return']:.2f} +- {stats['std_return']:.2f}{success} over "
              f"{stats['episodes']} {mode} episodes (mean length {stats['mean_length']:.0f}; "
              f"checkpoint at step {agent.num_steps})")
        if stats["reward_terms"]:
            print("reward terms, mean per episode: " + ", ".join(
                f"{name[len('reward_'):]} {value:.2f}" for name, value in stats["reward_terms"].items()))
    return EXIT_OK


def cmd_dataset(args: argparse.Namespace) -> int:
    from softac.agent import SAC
    from softac.outputs.dataset import write_agent_dataset
    from softac.run import checkpoint as ckpt

    run = Path(args.run)
    fresh = args.episodes is not None or args.steps is not None
    if not fresh and (args.noise or args.policy != "deployed" or args.seed):
        raise SoftacError("--noise, --policy and --seed choose how fresh episodes act: give --episodes N or --steps N")
    # the buffer: the last checkpoint's (the loaded agent's collector holds it); fresh episodes: its best policy
    agent = SAC.load(run if fresh else ckpt.resolve(run, "last"))
    written = write_agent_dataset(agent, f"softac run {run}", args.out, args.id, args.episodes, args.policy,
                                  args.noise, args.seed, args.steps)
    if not fresh:
        print(f"wrote {written.path}: the replay buffer of {run}, {written.transitions:,} transitions in "
              f"{written.episodes:,} episodes (Minari {_minari_version()}; --offline-data {written.path})")
        return EXIT_OK
    print(f"wrote {written.path}: {written.episodes} episodes of {run}'s {args.policy} policy"
          + (f" with noise {args.noise:g}" if args.noise else "")
          + f", {written.transitions:,} transitions, mean return {written.mean_return:.2f} (Minari "
          f"{_minari_version()}; --offline-data {written.path})")
    return EXIT_OK


def _minari_version() -> str:
    import minari

    return minari.__version__


def _record_video(path: Path, which: str | None, out: str | None, episodes: int, deterministic: bool,
                  max_steps: int | None = None, allow_new_bounds: bool = False,
                  policy: str = "deployed") -> dict[str, Any]:
    _choose_gl_backend_if(True)  # first: it probes backends in subprocesses, before JAX starts its threads

    from softac.run import checkpoint as ckpt
    from softac.agent import SAC
    from softac.outputs.video import default_video_path, record

    directory = ckpt.resolve(path, which)
    agent = SAC.load(directory, allow_new_bounds=allow_new_bounds)
    target = Path(out) if out else default_video_path(Path(path), agent.num_steps, policy=policy)
    if target.suffix.lower() != ".mp4":
        raise SoftacError(f"--out must name an .mp4 file, got {target}")
    result = record(agent, target, episodes=episodes, deterministic=deterministic, max_steps=max_steps,
                    policy=policy)
    if out is None:  # put the return in the file name
        named = default_video_path(Path(path), agent.num_steps, result["mean_return"], policy)
        Path(result["path"]).replace(named)
        result["path"] = str(named)
    print(f"video: {result['path']} ({len(result['returns'])} episode(s), return "
          f"{', '.join(f'{r:.1f}' for r in result['returns'])})", file=sys.stderr)
    return result


def cmd_video(args: argparse.Namespace) -> int:
    if args.episodes < 1:
        raise SoftacError("--episodes must be >= 1")
    _record_video(Path(args.path), args.checkpoint, args.out, args.episodes, not args.stochastic, args.max_steps,
                  args.allow_new_bounds, args.policy)
    return EXIT_OK


def cmd_plot(args: argparse.Namespace) -> int:
    from softac.outputs.plots import plot_runs
    from softac.sweep import SPEC_FILE, load_spec, trial_dirs

    runs, named = [], {}
    for given in map(Path, args.runs):  # a sweep directory stands for all its trials
        if (given / SPEC_FILE).exists():
            trials, sweep = trial_dirs(given), load_spec(given).describe()
            runs.extend(trials)
            named.update({trial: _trial_configuration(sweep, trial) for trial in trials})
        else:
            runs.append(given)
    # several sweeps: configurations named by framework and preset (and grid values), not by differing keys
    several = len({name.parent for name in named}) > 1 and len(named) == len(runs)
    written = plot_runs(runs, Path(args.out) if args.out else None, names=named if several else None)
    for path in written:
        print(path)
    return EXIT_OK


def _trial_configuration(sweep: str, trial: Path) -> str:
    """A trial's configuration in a comparison of sweeps: its sweep's (framework and preset), then the
    trial's grid values (its name without the seed)."""
    grid = ",".join(part for part in trial.name.split(",") if not part.startswith("seed="))
    return sweep + (f", {grid}" if grid else "")


def cmd_report(args: argparse.Namespace) -> int:
    from softac.outputs.report import build_report

    run = Path(args.run)
    if not run.is_dir():
        raise SoftacError(f"no such run directory: {run}")
    print(build_report(run, Path(args.out) if args.out else None))
    return EXIT_OK


def cmd_export(args: argparse.Namespace) -> int:
    from softac.outputs.export import export_policy

    print(export_policy(args.path, args.out, args.format, which=args.checkpoint,
                        allow_new_bounds=args.allow_new_bounds))
    return EXIT_OK


def cmd_baselines(args: argparse.Namespace) -> int:
    from softac.outputs.reference import run_baselines

    if args.episodes < 1:
        raise SoftacError("--episodes must be >= 1")
    if args.out and not Path(args.out).is_dir():
        raise SoftacError(f"--out {args.out} is not a run directory")
    result = run_baselines(args.env, episodes=args.episodes, seed=args.seed)
    if args.out:
        from softac.run.run_dir import write_atomic

        write_atomic(Path(args.out) / "baselines.json", json.dumps(result, indent=1).encode())
    if args.json:
        print(json.dumps(result))
    else:
        for name, stats in result["baselines"].items():
            print(f"{result['env_id']} {name:<9} mean return {stats['mean_return']:9.2f} +- "
                  f"{stats['std_return']:.2f} over {stats['episodes']} episodes")
    return EXIT_OK


def cmd_presets(args: argparse.Namespace) -> int:
    """A line per preset; with a name, that preset whole: its description and its settings."""
    from softac.config.presets import preset_names, preset_summary

    if args.name:
        print(_preset_page(args.name))
        return EXIT_OK
    names = preset_names()
    width = max(len(n) for n in names)
    for name in names:
        print(f"{name:<{width}}  {_preset_family(name):<9}  {preset_summary(name)}")
    print("\nsoftac presets NAME shows one whole; softac train --preset NAME trains with it", file=sys.stderr)
    return EXIT_OK


def _preset_family(name: str) -> str:
    from softac.config.presets import DMC_PRESET, GENERIC_PRESETS

    return "[any env]" if name in GENERIC_PRESETS else "[dmc]" if name == DMC_PRESET else "[env]"


def _preset_page(name: str) -> str:
    import textwrap

    import yaml

    from softac.config.presets import load_preset, preset_description, preset_extends, preset_summary

    values = load_preset(name)  # an unknown name: one line naming the closest
    text = [f"{name}  {_preset_family(name)}", preset_summary(name), ""]
    text += [textwrap.fill(paragraph, 100) for paragraph in preset_description(name).splitlines()]
    extends = preset_extends(name)
    text += ["", f"settings{f' (with those of {extends}, which it extends)' if extends else ''}; any other key is "
                 "SACConfig's default:"]
    text += [f"  {key}: {yaml.safe_dump(value, default_flow_style=True).strip().removesuffix('...').strip()}"
             for key, value in values.items()]
    return "\n".join(text)


def sweep_spec_from_args(args: argparse.Namespace):
    """The SweepSpec a new `softac sweep` command line describes."""
    from softac import sweep
    from softac.config.sac_config import DEFAULT_ENV

    spec = sweep.SweepSpec(
        env_id=args.env or DEFAULT_ENV, steps=args.steps or 0, seeds=sweep.parse_seeds(args.seeds, args.first_seed),
        preset=args.preset, overrides=[pair for group in args.overrides for pair in group],
        grid=sweep.parse_grid([g for group in args.grid for g in group]),
        framework=args.framework, search=args.search, samples=args.samples if args.search else 0,
        space=sweep.load_space(args.space) if args.search else None, asha=args.asha, target_return=args.target_return,
        target_success=args.target_success)
    spec.steps = spec.steps or spec.preset_config().total_steps  # default: the preset's budget
    return spec


def cmd_sweep(args: argparse.Namespace) -> int:
    from softac import sweep

    if args.resume:
        given = [flag for flag, value in (("--env", args.env), ("--preset", args.preset), ("--out", args.out),
                                          ("--space", args.space), ("--search", args.search),
                                          ("--target-return", args.target_return),
                                          ("--target-success", args.target_success))
                 if value is not None] + (["--grid"] if args.grid else []) + (["--set"] if args.overrides else [])
        if given:
            raise SoftacError(f"--resume continues a sweep with its own settings; drop {', '.join(given)}")
        out = Path(args.resume)
        spec = sweep.load_spec(out)
        spec.steps = args.steps or spec.steps  # a raised budget: checked in run_sweep (prepare_out_dir)
    else:
        if not args.out:
            raise SoftacError("softac sweep needs --out DIR (or --resume DIR)")
        out = Path(args.out)
        spec = sweep_spec_from_args(args)
    from softac.run.stopping import check_success_rate

    check_success_rate(args.success_threshold, "--success-threshold")  # (--target-success: sweep.validate)
    threshold = args.threshold
    if threshold is None:
        threshold = spec.target_return if spec.target_return is not None else sweep.default_threshold(spec.env_id)
    success_threshold = args.success_threshold
    if success_threshold is None:
        success_threshold = spec.target_success if spec.target_success is not None else sweep.SUCCESS_THRESHOLD
    result = sweep.run_sweep(spec, out, address=args.address, cpus_per_trial=args.cpus_per_trial,
                             max_concurrent=args.max_concurrent, threshold=threshold,
                             success_threshold=success_threshold, max_retries=args.max_retries,
                             gpus_per_trial=args.gpus_per_trial)
    if result["failed"]:
        print(f"softac: {len(result['failed'])} trial(s) failed, first: {result['failed'][0]}", file=sys.stderr)
    if result["unfinished"]:
        print(f"softac: {len(result['unfinished'])} of {result['trials']} trials unfinished; continue with "
              f"`softac sweep --resume {out}`", file=sys.stderr)
        return EXIT_RUN_FAILED if result["failed"] else EXIT_INTERRUPTED
    return EXIT_RUN_FAILED if result["failed"] else EXIT_OK


def cmd_bench(args: argparse.Namespace) -> int:
    from softac.peers.bench import main_from_args

    return main_from_args(args)
