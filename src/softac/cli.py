"""The `softac` command: parse, call the library, map errors to exit codes.

Exit codes: 0 success; 1 a bug of ours (one line; SOFTAC_DEBUG=1 shows the traceback); 2 bad input
(one line on stderr, no traceback); 3 a run that started and then failed (divergence, an env that raised
or returned NaN, a full disk; one line, the last good checkpoint kept); 130 interrupted (Ctrl-C or
SIGTERM) after a checkpoint was written.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from softac.errors import RunFailed, SoftacError, TrainingInterrupted
from softac.peers import PEERS

EXIT_OK, EXIT_INTERNAL, EXIT_BAD_INPUT, EXIT_RUN_FAILED, EXIT_INTERRUPTED = 0, 1, 2, 3, 130


class _Parser(argparse.ArgumentParser):
    commands: dict[str, argparse.ArgumentParser] = {}  # the root's subcommand parsers, by name

    def error(self, message: str) -> None:  # one line, not usage + message
        where = f"{self.prog}: " if " " in self.prog else ""  # main() already says "softac: error:"
        raise SoftacError(f"{where}{message} (see {self.prog} --help)")

    def parse_args(self, args=None, namespace=None):  # type: ignore[override]
        # argparse reports a subcommand's unknown arguments from the root; blame the command they followed
        parsed, unknown = self.parse_known_args(args, namespace)
        if unknown:
            self.commands.get(getattr(parsed, "command", None), self).error(
                f"unrecognized arguments: {' '.join(unknown)}")
        return parsed


def _positive_int(text: str) -> int:
    try:
        value = int(text.replace("_", ""))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got '{text}'") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {value}")
    return value


def _finite_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got '{text}'") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number, got '{text}'")
    return value


def _add_allow_new_bounds(p: argparse.ArgumentParser) -> None:
    p.add_argument("--allow-new-bounds", action="store_true",
                   help="load a checkpoint into an env whose action bounds differ from the ones it was trained with "
                        "(its actions are scaled to the new bounds); refused otherwise")


def _train_arguments(t: argparse.ArgumentParser) -> None:
    t.add_argument("--env", help="Gymnasium env id, module:EnvId, or dmc:DOMAIN-TASK (the DeepMind Control Suite, [dmc] extra)")
    src = t.add_mutually_exclusive_group()
    src.add_argument("--preset", help="preset name (see `softac presets`)")
    src.add_argument("--config", help="YAML file of config keys")
    t.add_argument("--set", dest="overrides", action="append", nargs="+", default=[], metavar="KEY=VALUE",
                   help="override a config key (repeatable)")
    t.add_argument("--steps", type=_positive_int, help="env steps to train (with --resume: steps to add)")
    t.add_argument("--total-steps", type=_positive_int, metavar="N",
                   help="with --resume: train until the run has N steps (its budget becomes N)")
    t.add_argument("--seed", type=int)
    t.add_argument("--n-envs", type=_positive_int)
    t.add_argument("--env-workers", type=_positive_int, metavar="K",
                   help="step the n_envs envs in K worker processes (for slow simulators; the same results; "
                        "with --resume too)")
    t.add_argument("--out", help="run directory (default runs/ENV/DATE-seedS)")
    t.add_argument("--device", choices=["cpu", "gpu", "cuda", "auto"])
    t.add_argument("--resume", metavar="DIR", help="continue the run in DIR exactly where it stopped")
    t.add_argument("--cpus", type=_positive_int, metavar="N",
                   help="pin the run to N CPUs that no other pinned softac run or sweep trial holds (side-by-side "
                        "runs stop competing for cores; results match a sweep trial with N CPUs)")
    t.add_argument("--target-return", type=_finite_float, metavar="R",
                   help="stop once the deterministic eval mean reaches R")
    t.add_argument("--target-success", type=_finite_float, metavar="S",
                   help="stop once the deterministic eval's success rate reaches S (in (0, 1]; goal envs, and "
                        "any env that reports info['is_success'])")
    t.add_argument("--video", action="store_true", help="record the final policy to RUN/videos at the end")
    _add_allow_new_bounds(t)
    t.add_argument("--logger", metavar="NAMES",
                   help="where metrics go besides the CSV files: tensorboard (default), wandb, mlflow, comma-separated, "
                        "or none (sets the loggers key; allowed with --resume)")
    bar = t.add_mutually_exclusive_group()
    bar.add_argument("--progress", dest="progress", action="store_true", default=None, help="force the progress bar")
    bar.add_argument("--no-progress", dest="progress", action="store_false", help="plain log lines instead")


def _sweep_arguments(sw: argparse.ArgumentParser) -> None:
    sw.add_argument("--env", help="Gymnasium env id, module:EnvId or dmc:DOMAIN-TASK (default InvertedPendulum-v5)")
    sw.add_argument("--seeds", default="1", help="a count N (seeds 0..N-1, or from --first-seed) or a comma list")
    sw.add_argument("--first-seed", type=int, default=0, help="first seed when --seeds is a count")
    sw.add_argument("--grid", action="append", nargs="+", default=[], metavar="KEY=V1,V2",
                    help="sweep a config key over values (repeatable; the grid is their product)")
    sw.add_argument("--preset", help="preset name (default: the env's preset)")
    sw.add_argument("--set", dest="overrides", action="append", nargs="+", default=[], metavar="KEY=VALUE",
                    help="override a config key in every trial")
    sw.add_argument("--steps", type=_positive_int, help="env steps per trial (default: the preset's total_steps; with --resume, or "
                    "the same command again: a larger budget, which finished trials continue to)")
    sw.add_argument("--out", help="sweep directory: one run directory per trial, summary.csv, summary.md, plots/")
    sw.add_argument("--resume", metavar="DIR", help="continue the sweep in DIR (finished trials are not redone)")
    sw.add_argument("--address", help="an existing Ray cluster (e.g. auto or ray://HEAD:10001); default: local Ray")
    sw.add_argument("--cpus-per-trial", type=float, default=1.0, help="CPUs Ray reserves for each trial (default 1)")
    sw.add_argument("--gpus-per-trial", type=float, default=0.0,
                    help="GPUs Ray reserves for each trial (with --set device=gpu; fractions share a GPU)")
    sw.add_argument("--max-concurrent", type=_positive_int, help="at most this many trials at once")
    sw.add_argument("--max-retries", type=_positive_int, default=3, metavar="N",
                    help="a trial whose process is lost (its node died, a signal killed it) is started again from "
                         "its last checkpoint, at most N times (default 3); then the sweep exits 3 naming it")
    sw.add_argument("--framework", choices=["softac", *PEERS], default="softac",
                    help="a peer instead of softac, evaluated like softac (needs the [bench] extra): "
                         + "; ".join(f"{name}: {peer.about}" for name, peer in PEERS.items()))
    sw.add_argument("--search", choices=["random", "optuna"], help="sample configurations instead of a grid")
    sw.add_argument("--samples", type=_positive_int, default=8, help="configurations a search tries (default 8)")
    sw.add_argument("--space", metavar="FILE", help="YAML search space (default: the documented SAC space)")
    sw.add_argument("--asha", action="store_true", help="with --search: stop poor trials early (ASHA)")
    sw.add_argument("--threshold", type=_finite_float, metavar="R",
                    help="also report steps and seconds until the eval mean first reaches R")
    sw.add_argument("--target-return", type=_finite_float, metavar="R",
                    help="stop each trial once its deterministic eval mean reaches R (softac's trials and the "
                         "peers'); the summary's steps and seconds to it are reported as with --threshold R")
    sw.add_argument("--success-threshold", type=_finite_float, metavar="S", default=0.9,
                    help="for envs that report success (goal envs): the summary's steps until the eval success "
                         "rate first reaches S (default 0.9)")


def build_parser() -> _Parser:
    parser = _Parser(prog="softac", description="Soft Actor-Critic for continuous-control Gymnasium envs.")
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    sub = parser.add_subparsers(dest="command", parser_class=_Parser)
    parser.commands = sub.choices  # to name the command whose arguments were not understood

    _train_arguments(sub.add_parser("train", help="train an agent (InvertedPendulum-v5 by default)"))

    e = sub.add_parser("eval", help="evaluate a run or checkpoint")
    e.add_argument("path", metavar="RUN_OR_CKPT")
    e.add_argument("--episodes", type=_positive_int, default=10)
    e.add_argument("--stochastic", action="store_true", help="sample actions instead of the mean action")
    e.add_argument("--checkpoint", choices=["best", "last"], help="which checkpoint of a run (default best, else last)")
    e.add_argument("--seed", type=int, help="seed of the first eval episode (default: the run's eval seed)")
    e.add_argument("--device", choices=["cpu", "gpu", "cuda", "auto"])
    e.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    _add_allow_new_bounds(e)

    sub.add_parser("presets", help="list presets")

    pl = sub.add_parser("plot", help="learning curve and metric grid; several runs: mean and 95%% CI across seeds")
    pl.add_argument("runs", nargs="+", metavar="RUN")
    pl.add_argument("--out", help="output folder (default RUN/plots; required for several runs)")

    v = sub.add_parser("video", help="render the agent to an MP4 (headless: EGL or OSMesa)")
    v.add_argument("path", metavar="RUN_OR_CKPT")
    v.add_argument("--out", help="MP4 file (default RUN/videos/stepN-returnR.mp4)")
    v.add_argument("--episodes", type=_positive_int, default=1)
    v.add_argument("--stochastic", action="store_true")
    v.add_argument("--checkpoint", choices=["best", "last"])
    v.add_argument("--max-steps", type=_positive_int, help="stop each episode after this many steps")
    _add_allow_new_bounds(v)

    rp = sub.add_parser("report", help="one self-contained HTML page for a run")
    rp.add_argument("run", metavar="RUN")
    rp.add_argument("--out", help="HTML file (default RUN/report.html)")

    x = sub.add_parser("export", help="the deterministic policy as ONNX or NumPy, to act without JAX")
    x.add_argument("path", metavar="RUN_OR_CKPT")
    x.add_argument("--format", choices=["onnx", "numpy"], default="onnx",
                   help="onnx: policy.onnx (needs the [export] extra); numpy: policy.npz (default onnx)")
    x.add_argument("--out", help="file to write (default RUN/export/policy.onnx or RUN/export/policy.npz)")
    x.add_argument("--checkpoint", choices=["best", "last"], help="which checkpoint of a run (default best, else last)")
    _add_allow_new_bounds(x)

    b = sub.add_parser("baselines", help="random, zero and heuristic policies' returns")
    b.add_argument("--env", default="InvertedPendulum-v5")
    b.add_argument("--episodes", type=_positive_int, default=10)
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--out", metavar="RUN", help="also write RUN/baselines.json (plots and reports draw it)")
    b.add_argument("--json", action="store_true")

    _sweep_arguments(sub.add_parser("sweep", help="many runs on Ray Tune (seeds x a grid, or a search): summary, CI "
                                                  "table, plots"))

    from softac.bench import add_arguments

    add_arguments(sub.add_parser("bench", help="throughput and seconds-to-solve, side by side with SB3 and SBX"))
    return parser


# ---- commands -----------------------------------------------------------------

def _resolve_train_config(args: argparse.Namespace):
    from softac.config import SACConfig, parse_overrides

    if args.config:
        config = SACConfig.from_yaml(args.config)
        if args.env:
            config = config.replace(env_id=args.env)
    elif args.preset:
        config = SACConfig.preset(args.preset, env_id=args.env)
    else:
        config = SACConfig.for_env(args.env)
    overrides = parse_overrides([pair for group in args.overrides for pair in group])
    direct = {"total_steps": args.steps, "seed": args.seed, "n_envs": args.n_envs, "env_workers": args.env_workers,
              "device": args.device, "loggers": args.logger}
    # one replace, checked once: `--set env_workers=4 --n-envs 4` is valid though neither half is alone
    return config.replace(**{**overrides, **{k: v for k, v in direct.items() if v is not None}})


def _default_run_dir(config) -> Path:
    name = config.env_id.replace(":", "_").replace("/", "_")
    return Path("runs") / name / f"{time.strftime('%Y%m%d-%H%M%S')}-seed{config.seed}"


def _pin_cpus(n: int | None) -> str | None:
    """--cpus, once the inputs are checked and before JAX starts (XLA sizes its thread pool from the CPUs
    this process may use); the line to print when training starts."""
    from softac.cpus import pin_this_process, usable_cpus

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
    from softac.loop import check_success_rate
    from softac.rundir import run_lock

    check_success_rate(args.target_success, "--target-success")

    if args.resume:
        clash = [flag for flag, value in (("--env", args.env), ("--preset", args.preset), ("--config", args.config),
                                          ("--seed", args.seed), ("--n-envs", args.n_envs), ("--out", args.out))
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
    from softac import checkpoint as ckpt
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
    from softac.buffer import check_buffer_memory
    from softac.loggers import check_backends_installed, parse_backends
    from softac.rundir import check_new_run_dir

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
    return agent, config.total_steps, start, pinned


def _choose_gl_backend_if(video: bool) -> None:
    if video:  # MuJoCo picks its GL backend when first imported: choose it now, fail early
        from softac.gl import choose_gl_backend

        choose_gl_backend()


def cmd_eval(args: argparse.Namespace) -> int:
    from softac.agent import SAC
    from softac.evaluation import evaluate

    if args.episodes < 1:
        raise SoftacError("--episodes must be >= 1")
    agent = SAC.load(args.path, which=args.checkpoint, device=args.device, allow_new_bounds=args.allow_new_bounds)
    stats = evaluate(agent, episodes=args.episodes, deterministic=not args.stochastic, seed=args.seed)
    stats["checkpoint_step"] = agent.num_steps
    stats["path"] = str(args.path)
    if args.json:
        print(json.dumps(stats))
    else:
        mode = "stochastic" if args.stochastic else "deterministic"
        success = f", success rate {stats['success_rate']:.2f}" if stats["success_rate"] is not None else ""
        print(f"{stats['env_id']}: mean return {stats['mean_return']:.2f} +- {stats['std_return']:.2f}{success} over "
              f"{stats['episodes']} {mode} episodes (mean length {stats['mean_length']:.0f}; "
              f"checkpoint at step {agent.num_steps})")
        if stats["reward_terms"]:
            print("reward terms, mean per episode: " + ", ".join(
                f"{name[len('reward_'):]} {value:.2f}" for name, value in stats["reward_terms"].items()))
    return EXIT_OK


def _record_video(path: Path, which: str | None, out: str | None, episodes: int, deterministic: bool,
                  max_steps: int | None = None, allow_new_bounds: bool = False) -> dict[str, Any]:
    _choose_gl_backend_if(True)  # first: it probes backends in subprocesses, before JAX starts its threads

    from softac import checkpoint as ckpt
    from softac.agent import SAC
    from softac.video import default_video_path, record

    directory = ckpt.resolve(path, which)
    agent = SAC.load(directory, allow_new_bounds=allow_new_bounds)
    target = Path(out) if out else default_video_path(Path(path), agent.num_steps)
    if target.suffix.lower() != ".mp4":
        raise SoftacError(f"--out must name an .mp4 file, got {target}")
    result = record(agent, target, episodes=episodes, deterministic=deterministic, max_steps=max_steps)
    if out is None:  # put the return in the file name
        named = default_video_path(Path(path), agent.num_steps, result["mean_return"])
        Path(result["path"]).replace(named)
        result["path"] = str(named)
    print(f"video: {result['path']} ({len(result['returns'])} episode(s), return "
          f"{', '.join(f'{r:.1f}' for r in result['returns'])})", file=sys.stderr)
    return result


def cmd_video(args: argparse.Namespace) -> int:
    if args.episodes < 1:
        raise SoftacError("--episodes must be >= 1")
    _record_video(Path(args.path), args.checkpoint, args.out, args.episodes, not args.stochastic, args.max_steps,
                  args.allow_new_bounds)
    return EXIT_OK


def cmd_plot(args: argparse.Namespace) -> int:
    from softac.plots import plot_runs
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
    from softac.report import build_report

    run = Path(args.run)
    if not run.is_dir():
        raise SoftacError(f"no such run directory: {run}")
    print(build_report(run, Path(args.out) if args.out else None))
    return EXIT_OK


def cmd_export(args: argparse.Namespace) -> int:
    from softac.export import export_policy

    print(export_policy(args.path, args.out, args.format, which=args.checkpoint,
                        allow_new_bounds=args.allow_new_bounds))
    return EXIT_OK


def cmd_baselines(args: argparse.Namespace) -> int:
    from softac.baselines import run_baselines

    if args.episodes < 1:
        raise SoftacError("--episodes must be >= 1")
    if args.out and not Path(args.out).is_dir():
        raise SoftacError(f"--out {args.out} is not a run directory")
    result = run_baselines(args.env, episodes=args.episodes, seed=args.seed)
    if args.out:
        from softac.rundir import write_atomic

        write_atomic(Path(args.out) / "baselines.json", json.dumps(result, indent=1).encode())
    if args.json:
        print(json.dumps(result))
    else:
        for name, stats in result["baselines"].items():
            print(f"{result['env_id']} {name:<9} mean return {stats['mean_return']:9.2f} +- "
                  f"{stats['std_return']:.2f} over {stats['episodes']} episodes")
    return EXIT_OK


def cmd_presets(args: argparse.Namespace) -> int:
    from softac.config import DMC_PRESET, GENERIC_PRESETS, preset_names, preset_summary

    names = preset_names()
    width = max(len(n) for n in names)
    for name in names:
        kind = "[any env]" if name in GENERIC_PRESETS else "[dmc]" if name == DMC_PRESET else "[env]"
        print(f"{name:<{width}}  {kind:<9}  {preset_summary(name)}")
    return EXIT_OK


def sweep_spec_from_args(args: argparse.Namespace):
    """The SweepSpec a new `softac sweep` command line describes."""
    from softac import sweep
    from softac.config import DEFAULT_ENV

    spec = sweep.SweepSpec(
        env_id=args.env or DEFAULT_ENV, steps=args.steps or 0, seeds=sweep.parse_seeds(args.seeds, args.first_seed),
        preset=args.preset, overrides=[pair for group in args.overrides for pair in group],
        grid=sweep.parse_grid([g for group in args.grid for g in group]),
        framework=args.framework, search=args.search, samples=args.samples if args.search else 0,
        space=sweep.load_space(args.space) if args.search else None, asha=args.asha, target_return=args.target_return)
    spec.steps = spec.steps or spec.preset_config().total_steps  # default: the preset's budget
    return spec


def cmd_sweep(args: argparse.Namespace) -> int:
    from softac import sweep

    if args.resume:
        given = [flag for flag, value in (("--env", args.env), ("--preset", args.preset), ("--out", args.out),
                                          ("--space", args.space), ("--search", args.search),
                                          ("--target-return", args.target_return))
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
    from softac.loop import check_success_rate

    check_success_rate(args.success_threshold, "--success-threshold")
    threshold = args.threshold
    if threshold is None:
        threshold = spec.target_return if spec.target_return is not None else sweep.default_threshold(spec.env_id)
    result = sweep.run_sweep(spec, out, address=args.address, cpus_per_trial=args.cpus_per_trial,
                             max_concurrent=args.max_concurrent, threshold=threshold,
                             success_threshold=args.success_threshold, max_retries=args.max_retries,
                             gpus_per_trial=args.gpus_per_trial)
    if result["failed"]:
        print(f"softac: {len(result['failed'])} trial(s) failed, first: {result['failed'][0]}", file=sys.stderr)
    if result["unfinished"]:
        print(f"softac: {len(result['unfinished'])} of {result['trials']} trials unfinished; continue with "
              f"`softac sweep --resume {out}`", file=sys.stderr)
        return EXIT_RUN_FAILED if result["failed"] else EXIT_INTERRUPTED
    return EXIT_RUN_FAILED if result["failed"] else EXIT_OK


def cmd_bench(args: argparse.Namespace) -> int:
    from softac.bench import main_from_args

    return main_from_args(args)


COMMANDS = {"train": cmd_train, "eval": cmd_eval, "presets": cmd_presets, "bench": cmd_bench, "plot": cmd_plot,
            "video": cmd_video, "report": cmd_report, "export": cmd_export, "baselines": cmd_baselines,
            "sweep": cmd_sweep}


def entry_point() -> int:
    """The `softac` command and `python -m softac`: main() in a process of its own."""
    from softac.stopsignal import finish_after_stop

    finish_after_stop()
    return main()


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        if args.version:
            from softac import __version__

            print(__version__)
            return EXIT_OK
        if args.command is None:
            parser.print_help(sys.stderr)
            return EXIT_BAD_INPUT
        return COMMANDS[args.command](args)
    except RunFailed as exc:
        print(f"softac: error: {exc}", file=sys.stderr)
        return EXIT_RUN_FAILED
    except SoftacError as exc:
        print(f"softac: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except TrainingInterrupted as exc:
        print(f"softac: {exc}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except KeyboardInterrupt:
        print("softac: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as exc:  # a bug of ours: say so in one line, keep the traceback for SOFTAC_DEBUG
        if os.environ.get("SOFTAC_DEBUG"):
            raise
        print(f"softac: internal error: {type(exc).__name__}: {exc} (rerun with SOFTAC_DEBUG=1 for the traceback)"
              .splitlines()[0], file=sys.stderr)
        return EXIT_INTERNAL


if __name__ == "__main__":
    sys.exit(entry_point())
