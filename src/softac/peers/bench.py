"""`softac bench`: softac, Stable-Baselines3 and SBX side by side, in one run, on this machine.

Two measurements, each framework in its own fresh process, one after the other:

- throughput: training steps/s, timed between step `warmup` and `warmup + steps`, so start-up and
  compilation are excluded. `--algorithm sac` (the default): at Stable-Baselines3's SAC defaults (softac's
  `sb3` preset: 256x256 networks, batch 256, one update per env step) beside SB3's and SBX's SAC at their
  defaults; `--algorithm crossq`: softac's `crossq` preset beside SBX's CrossQ at the same settings
  (`sbx-crossq-softac`) and at its own defaults (`sbx-crossq`). Every framework learns from step 100 in
  a throughput run (learning_starts 100, whatever its setting for whole runs);
- seconds to solve: a whole training process, from its start to its exit, until the deterministic
  evaluation (10 episodes, every 1000 steps) reaches the target. softac runs its default command
  (`softac train --target-return R`); the peers run at their defaults with an EvalCallback. Both
  the whole-process wall time and the training time without evaluation are reported.

`softac-bf16` is softac with `matmul_dtype=bfloat16` (bf16 matmuls, f32 accumulation and
parameters); it is in the default list where the CPU has AVX-512 BF16 or AMX.

Peers need the `[bench]` extra (`make bench` installs it, torch 2.13.0 CPU first).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from softac import peers
from softac.base.cpus import cpu_has_bf16, machine_description
from softac.errors import SoftacError
from softac.peers import PEERS

# softac variants: the same preset with these settings added (the driver passes them as --set)
VARIANTS = {"softac": [], "softac-bf16": ["matmul_dtype=bfloat16"]}
FRAMEWORKS = (*VARIANTS, *PEERS)
MIN_WARMUP = 300
# what each --algorithm compares: softac's preset, and the peers that run the same algorithm
ALGORITHMS = {"sac": ("sb3", ["sb3", "sbx"]), "crossq": ("crossq", ["sbx-crossq-softac", "sbx-crossq"])}


def default_frameworks(algorithm: str = "sac") -> list[str]:
    ours = [fw for fw in VARIANTS if fw != "softac-bf16" or cpu_has_bf16()]
    return ours + ALGORITHMS[algorithm][1]


# ---- workers: each runs in its own process and prints one JSON line -----------------


def _throughput_softac(env_id: str, warmup: int, steps: int, seed: int, overrides: list[str],
                       preset: str = "sb3") -> dict[str, Any]:
    from softac.agent import SAC
    from softac.config.sac_config import SACConfig

    config = SACConfig.preset(preset, env_id=env_id).replace(seed=seed, eval_interval=0, buffer_size=warmup + steps,
                                                             learning_starts=peers.THROUGHPUT_LEARNING_STARTS)
    agent = SAC(config.with_overrides(overrides))
    agent.learn(warmup, progress=False)
    t0 = time.perf_counter()
    agent.learn(steps, progress=False)
    return {"steps_per_s": steps / (time.perf_counter() - t0)}


def worker(argv: list[str]) -> None:
    """A softac variant's throughput probe (`python -m softac.peers.bench throughput softac ...`); a peer's
    measurements go to its own entry point, softac.peers (also when asked here, the older form)."""
    if len(argv) > 1 and argv[1] in PEERS:
        peers.main(argv)
        return
    p = argparse.ArgumentParser(prog="python -m softac.peers.bench")
    p.add_argument("kind", choices=["throughput"])
    p.add_argument("framework", choices=list(VARIANTS))
    p.add_argument("--env", default="InvertedPendulum-v5")
    p.add_argument("--warmup", type=int, default=500)
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", dest="overrides", nargs="*", default=[])
    p.add_argument("--preset", default="sb3")
    a = p.parse_args(argv)
    print(json.dumps(_throughput_softac(a.env, a.warmup, a.steps, a.seed, a.overrides, a.preset)), flush=True)


# ---- the driver ------------------------------------------------------------------------

def _run(args: list[str], timeout: float) -> tuple[dict[str, Any] | None, float, str]:
    t0 = time.perf_counter()
    try:
        r = subprocess.run([sys.executable, *args], capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return None, time.perf_counter() - t0, f"timed out after {timeout:.0f}s"
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        lines = (r.stderr or r.stdout).strip().splitlines()
        return None, wall, lines[-1] if lines else f"exit {r.returncode}"
    for line in reversed(r.stdout.strip().splitlines()):
        if line.startswith("{"):
            return json.loads(line), wall, ""
    return {}, wall, ""


def solve_softac(env_id: str, seed: int, target: float, timeout: float,
                 extra: list[str] | tuple[str, ...] = ()) -> tuple[dict[str, Any] | None, float, str]:
    """The whole `softac train --target-return` process for one seed: (result, wall seconds, error)."""
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / "run"
        out, wall, err = _run(["-m", "softac", "train", "--env", env_id, "--seed", str(seed), "--target-return",
                               str(target), "--out", str(run), "--no-progress", *extra], timeout)
        if out is None:
            return None, wall, err
        rows = (run / "eval.csv").read_text().splitlines()[1:]
        last = rows[-1].split(",") if rows else ["0", "nan"]
        evals = [float(r.split(",")[1]) for r in rows]
        progress = (run / "progress.csv").read_text().splitlines()[1:]
        train_s = float(progress[-1].split(",")[1]) if progress else float("nan")
        return {"steps": int(last[0]), "solved": float(last[1]) >= target, "best_eval": max(evals, default=float("nan")),
                "train_s": train_s}, wall, ""


def run_bench(frameworks: list[str], env_id: str, warmup: int, steps: int, repeats: int, solve_seeds: list[int],
              target: float, max_steps: int, timeout: float, overrides: list[str], log=print,
              algorithm: str = "sac") -> dict[str, Any]:
    preset = ALGORITHMS[algorithm][0]
    result: dict[str, Any] = {"machine": machine_description(), "env": env_id, "algorithm": algorithm,
                              "softac_preset": preset, "throughput": {}, "solve": {}}
    log(f"machine: {result['machine']}")
    log(f"throughput of {algorithm} on {env_id} (softac's {preset} preset; peers: "
        f"{', '.join(PEERS[fw].about for fw in frameworks if fw in PEERS) or 'none'}): {steps} steps after "
        f"{warmup} warm-up steps, median of {repeats}")
    for round_ in range(1, repeats + 1):  # interleaved, so drift of the machine hits every framework alike
        for fw in frameworks:
            settings = VARIANTS[fw] + overrides if fw in VARIANTS else []
            extra = (["--set", *settings] if settings else []) + (["--preset", preset] if fw in VARIANTS else [])
            module = "softac.peers.bench" if fw in VARIANTS else "softac.peers"
            out, _, err = _run(["-m", module, "throughput", fw, "--env", env_id, "--warmup", str(warmup),
                                "--steps", str(steps), *extra], timeout)
            entry = result["throughput"].setdefault(fw, {"runs": []})
            if out is None:
                entry["error"] = err
                log(f"  {fw}: failed: {err}")
            else:
                entry["runs"].append(round(out["steps_per_s"], 1))
                log(f"  run {round_}/{repeats} {fw:<11} {out['steps_per_s']:8.1f} steps/s")  # minutes pass between
    for fw, entry in result["throughput"].items():
        if entry["runs"]:
            entry["median_steps_per_s"] = statistics.median(entry["runs"])
    ours = {fw: e["median_steps_per_s"] for fw, e in result["throughput"].items()
            if fw in VARIANTS and "median_steps_per_s" in e}
    for fw, entry in result["throughput"].items():
        if "median_steps_per_s" in entry:
            ratios = {f"{mine}_ratio": round(speed / entry["median_steps_per_s"], 2)
                      for mine, speed in ours.items() if fw not in VARIANTS}
            shown = "".join(f"  {k[:-6]}/{fw} = {v:.2f}x" for k, v in ratios.items())
            log(f"  {fw:<11} {entry['median_steps_per_s']:8.1f} steps/s  (runs {entry['runs']}){shown}")
            entry.update(ratios)

    if solve_seeds:
        log(f"seconds to solve {env_id} (deterministic eval mean >= {target:g}, 10 episodes every 1000 steps), "
            f"seeds {solve_seeds}")
        for fw in frameworks:
            runs = []
            for seed in solve_seeds:
                if fw in VARIANTS:
                    variant = VARIANTS[fw]
                    preset_args = ["--preset", preset] if algorithm != "sac" else []  # sac: the env's preset
                    out, wall, err = solve_softac(env_id, seed, target, timeout,
                                                  preset_args + (["--set", *variant] if variant else []))
                else:
                    out, wall, err = _run(["-m", "softac.peers", "solve", fw, "--env", env_id, "--seed", str(seed),
                                           "--target", str(target), "--max-steps", str(max_steps)], timeout)
                if out is None:
                    runs.append({"seed": seed, "error": err, "wall_s": round(wall, 1)})
                    log(f"  {fw} seed {seed}: failed: {err}")
                    continue
                out = {"seed": seed, "wall_s": round(wall, 1), **{k: (round(v, 1) if isinstance(v, float) else v)
                                                                   for k, v in out.items()}}
                runs.append(out)
                log(f"  {fw:<11} seed {seed}: {'solved' if out['solved'] else 'NOT solved'} at {out['steps']} steps, "
                    f"{out['wall_s']:.1f}s whole process, {out['train_s']:.1f}s training without eval")
            ok = [r for r in runs if "error" not in r]
            summary: dict[str, Any] = {"runs": runs, "solved": sum(r["solved"] for r in ok), "seeds": len(runs)}
            if ok:
                summary["median_wall_s"] = statistics.median(r["wall_s"] for r in ok)
                summary["median_train_s"] = statistics.median(r["train_s"] for r in ok)
                summary["median_steps"] = statistics.median(r["steps"] for r in ok)
                log(f"  {fw:<11} median {summary['median_wall_s']:.1f}s whole process, "
                    f"{summary['median_train_s']:.1f}s training, {summary['median_steps']:.0f} steps; "
                    f"solved {summary['solved']}/{summary['seeds']}")
            result["solve"][fw] = summary
    return result


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--env", default="InvertedPendulum-v5")
    p.add_argument("--algorithm", choices=list(ALGORITHMS), default="sac",
                   help="sac: softac's sb3 preset beside SB3's and SBX's SAC at their defaults; crossq: softac's "
                        "crossq preset beside SBX's CrossQ at the same settings and at its defaults")
    p.add_argument("--frameworks", default=None,
                   help=f"comma list of {','.join(FRAMEWORKS)} (default: softac, softac-bf16 where the CPU has "
                        "AVX-512 BF16 or AMX, and the algorithm's peers)")
    p.add_argument("--steps", type=int, default=2000, help="timed training steps per throughput run")
    p.add_argument("--warmup", type=int, default=500, help="untimed steps first (compile, learning_starts)")
    p.add_argument("--repeats", type=int, default=3, help="throughput runs per framework (median reported)")
    p.add_argument("--solve", action="store_true", help="also measure seconds to solve")
    p.add_argument("--solve-seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--target", type=float, default=1000.0)
    p.add_argument("--max-steps", type=int, default=50_000, help="peers' step budget when solving")
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds before one measurement is abandoned")
    p.add_argument("--set", dest="overrides", action="append", nargs="+", default=[], metavar="KEY=VALUE",
                   help="override softac's sb3-preset config for the throughput runs (e.g. matmul_dtype=bfloat16)")
    p.add_argument("--json", action="store_true", help="print the results as one JSON object on stdout")


def main_from_args(args: argparse.Namespace) -> int:
    requested = ([f.strip() for f in args.frameworks.split(",") if f.strip()] if args.frameworks is not None
                 else default_frameworks(args.algorithm))
    unknown = [f for f in requested if f not in FRAMEWORKS]
    if unknown or not requested:
        raise SoftacError(f"--frameworks takes a comma list of {', '.join(FRAMEWORKS)}; got {args.frameworks!r}")
    unlike = [f for f in requested if f in PEERS and f not in ALGORITHMS[args.algorithm][1]]
    if unlike:  # like with like: a peer runs the algorithm softac runs
        raise SoftacError(f"{', '.join(unlike)} run(s) another algorithm than --algorithm {args.algorithm} "
                          f"(its peers: {', '.join(ALGORITHMS[args.algorithm][1])})")
    for name in ("steps", "repeats"):
        if getattr(args, name) < 1:
            raise SoftacError(f"--{name} must be positive")
    if args.warmup < MIN_WARMUP:  # the timed steps must all learn, and every peer's clock starts at `warmup`
        raise SoftacError(f"--warmup must be >= {MIN_WARMUP} (every framework starts learning at step 100 in a "
                          f"throughput run), got {args.warmup}")
    missing = peers.missing_peers(requested)
    if missing:
        raise SoftacError(f"{', '.join(missing)} not installed: `make bench` installs the [bench] extra "
                          "(or: pip install torch==2.13.0 && pip install -e '.[bench]')")
    from softac.envs.make import resolve_env_id

    resolve_env_id(args.env)
    log = (lambda *a: print(*a, file=sys.stderr, flush=True)) if args.json else (lambda *a: print(*a, flush=True))
    overrides = [pair for group in args.overrides for pair in group]
    if overrides:
        from softac.config.sac_config import SACConfig

        # bad keys fail here, before minutes of benchmarking
        SACConfig.preset(ALGORITHMS[args.algorithm][0]).with_overrides(overrides)
    result = run_bench(requested, args.env, args.warmup, args.steps, args.repeats,
                       args.solve_seeds if args.solve else [], args.target, args.max_steps, args.timeout, overrides,
                       log=log, algorithm=args.algorithm)
    if args.json:
        print(json.dumps(result))
    return 0


if __name__ == "__main__":
    worker(sys.argv[1:])
