"""The `softac` command: parse, call the library, map errors to exit codes.

Exit codes: 0 success; 1 a bug of ours (one line; SOFTAC_DEBUG=1 shows the traceback); 2 bad input
(one line on stderr, no traceback); 3 a run that started and then failed (divergence, an env that raised
or returned NaN, a full disk; one line, the last good checkpoint kept); 130 interrupted (Ctrl-C or
SIGTERM) after a checkpoint was written.
"""

from __future__ import annotations

import argparse
import os
import sys

from softac.errors import RunFailed, SoftacError, TrainingInterrupted
from softac.peers import PEERS

from softac.cli.commands import (EXIT_BAD_INPUT, EXIT_BROKEN_PIPE, EXIT_INTERNAL, EXIT_INTERRUPTED, EXIT_OK, EXIT_RUN_FAILED,
                             cmd_baselines, cmd_bench, cmd_eval, cmd_export, cmd_plot, cmd_presets, cmd_report,
                             cmd_dataset, cmd_sweep, cmd_train, cmd_video)


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


def _add_policy(p: argparse.ArgumentParser) -> None:
    # learner.POLICIES spelled here (a test keeps them equal): cli imports nothing heavy, so `softac --help` starts fast
    p.add_argument("--policy", choices=["deployed", "actor", "average"], default="deployed",
                   help="which policy: deployed (default: the weight average with policy_average_tau, else the "
                        "actor), actor (the actor that explores), average (the weight average)")


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
    t.add_argument("--offline-data", metavar="SOURCE",
                   help="learn from a dataset beside the env's transitions: a Minari dataset id or directory, a softac "
                        "run directory (its replay buffer) or a `softac dataset` output (config key offline_data; "
                        "offline_mode, offline_fraction)")
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
    sw.add_argument("--target-success", type=_finite_float, metavar="S",
                    help="goal envs: stop each trial once its eval success rate reaches S (softac's trials and the "
                         "peers'); the summary's steps to it are reported as with --success-threshold S")
    sw.add_argument("--success-threshold", type=_finite_float, metavar="S",
                    help="for envs that report success (goal envs): the summary's steps until the eval success "
                         "rate first reaches S (default: --target-success, else 0.9)")


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
    _add_policy(e)
    e.add_argument("--device", choices=["cpu", "gpu", "cuda", "auto"])
    e.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    _add_allow_new_bounds(e)

    pr = sub.add_parser("presets", help="list presets, a line each; with NAME, that one's description and settings")
    pr.add_argument("name", nargs="?", metavar="NAME", help="a preset to show whole")

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
    _add_policy(v)
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

    d = sub.add_parser("dataset", help="a Minari dataset from a run: its replay buffer, or fresh episodes of its policy")
    d.add_argument("run", metavar="RUN")
    d.add_argument("--out", required=True, metavar="DIR", help="the dataset's directory (new); NAMESPACE/NAME-vN at its "
                                                            "end names its Minari id")
    d.add_argument("--episodes", type=_positive_int, metavar="N",
                   help="N fresh episodes of the run's policy (default: the replay buffer of its last checkpoint)")
    d.add_argument("--steps", type=_positive_int, metavar="N",
                   help="fresh episodes of the run's policy until N transitions (the last episode cut there)")
    _add_policy(d)
    d.add_argument("--noise", type=_finite_float, default=0.0, metavar="S",
                   help="with --episodes: Gaussian noise of std S on each action, in [-1, 1] units (default 0)")
    d.add_argument("--seed", type=int, default=0, help="with --episodes: episode i starts from reset(seed=SEED+i)")
    d.add_argument("--id", metavar="NAMESPACE/NAME-vN", help="the dataset's Minari id (default from --out, else "
                                                             "softac/ENV-replay-v0 or softac/ENV-policy-v0)")

    b = sub.add_parser("baselines", help="random, zero and heuristic policies' returns")
    b.add_argument("--env", default="InvertedPendulum-v5")
    b.add_argument("--episodes", type=_positive_int, default=10)
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--out", metavar="RUN", help="also write RUN/baselines.json (plots and reports draw it)")
    b.add_argument("--json", action="store_true")

    _sweep_arguments(sub.add_parser("sweep", help="many runs on Ray Tune (seeds x a grid, or a search): summary, CI "
                                                  "table, plots"))

    from softac.peers.bench import add_arguments

    add_arguments(sub.add_parser("bench", help="throughput and seconds-to-solve, side by side with SB3 and SBX"))
    return parser


# ---- commands -----------------------------------------------------------------

COMMANDS = {"train": cmd_train, "eval": cmd_eval, "presets": cmd_presets, "bench": cmd_bench, "plot": cmd_plot,
            "video": cmd_video, "report": cmd_report, "export": cmd_export, "baselines": cmd_baselines,
            "sweep": cmd_sweep, "dataset": cmd_dataset}


def entry_point() -> int:
    """The `softac` command and `python -m softac`: main() in a process of its own."""
    from softac.base.stop_signal import finish_after_stop

    finish_after_stop()
    return main()


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        if args.version:
            from softac.version import __version__

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
    except BrokenPipeError:  # the reader stopped early (`softac presets | head`): quiet, as Unix tools are
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # so that the exit's flush cannot fail too
        return EXIT_BROKEN_PIPE
    except Exception as exc:  # a bug of ours: say so in one line, keep the traceback for SOFTAC_DEBUG
        if os.environ.get("SOFTAC_DEBUG"):
            raise
        print(f"softac: internal error: {type(exc).__name__}: {exc} (rerun with SOFTAC_DEBUG=1 for the traceback)"
              .splitlines()[0], file=sys.stderr)
        return EXIT_INTERNAL


if __name__ == "__main__":
    sys.exit(entry_point())
