"""Where the test suite's time goes (issue 64): per test file and per marker, XLA compiling against the rest,
the processes the tests start (and their `import jax`), each local Ray's start and stop.

    python benchmarks/suite_time.py --out /tmp/suite                  # the whole suite as `make test` runs it
    python benchmarks/suite_time.py --out /tmp/suite -- -m numerics   # pytest's own arguments after --
    python benchmarks/suite_time.py --report /tmp/suite               # the tables again, from what it recorded

It runs pytest on `--workers` pytest-xdist workers (make test's 2, --dist loadgroup) with a probe
(benchmarks/suite_time/sitecustomize.py) in every Python process the session starts, test subprocesses and Ray's
workers included, and each test's seconds (benchmarks/suite_time/suite_time_plugin.py). Seconds are wall-clock seconds of each process, so
on a loaded machine a compile takes longer than alone; compare runs on one machine, side by side. The figures
per machine and commit are kept in docs/development.md.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
TRACE, LOWER, BACKEND = ("/jax/core/compile/jaxpr_trace_duration", "/jax/core/compile/jaxpr_to_mlir_module_duration",
                         "/jax/core/compile/backend_compile_duration")
SAVED, RETRIEVE = "/jax/compilation_cache/compile_time_saved_sec", "/jax/compilation_cache/cache_retrieval_time_sec"
RAY = ("ray_init", "ray_shutdown", "ray_cluster_start", "ray_cluster_shutdown")
OUTSIDE = "(outside a test: collection, session fixtures)"


def run(out: Path, workers: int, pytest_args: list[str]) -> int:
    """pytest's exit code; its wall time and command go to out/session.json."""
    events = out / "events"
    events.mkdir(parents=True, exist_ok=True)
    # a session of its own, also when started from inside another (its test): not that one's worker or test
    inherited = {k: v for k, v in os.environ.items() if not k.startswith(("PYTEST_XDIST_", "PYTEST_CURRENT_TEST"))}
    env = {**inherited, "SUITE_TIME_EVENTS": str(events),
           "PYTHONPATH": os.pathsep.join([str(HERE / "suite_time"), os.environ.get("PYTHONPATH", "")])}
    xdist = ["-n", str(workers), "--dist", "loadgroup"] if workers else ["-p", "no:xdist"]
    cmd = [sys.executable, "-m", "pytest", "-q", *xdist, "-p", "suite_time_plugin", *pytest_args]
    start = time.monotonic()
    code = subprocess.call(cmd, env=env, cwd=HERE.parent)
    wall = time.monotonic() - start
    (out / "session.json").write_text(json.dumps({"wall_s": wall, "exit_code": code, "workers": workers,
                                                  "command": cmd[1:]}))
    return code


def _test_seconds(out: Path) -> dict[str, float]:
    seconds: dict[str, float] = collections.Counter()
    for path in (out / "events").glob("durations-*.json"):
        seconds.update(json.loads(path.read_text()))
    return seconds


def _events(out: Path) -> tuple[dict[str, collections.Counter], dict[str, list[str]], dict[str, collections.Counter]]:
    """Per test, the events' seconds and counts; each test's markers; per compiled function (JAX's name for it,
    `jit(update_program)`), its XLA backend seconds and compiles."""
    per_test: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    per_function: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    markers: dict[str, list[str]] = {}
    for path in sorted((out / "events").iterdir()):
        if path.name.startswith("markers-"):
            markers.update(json.loads(path.read_text()))
            continue
        if path.suffix != ".jsonl":
            continue
        for line in path.read_text().splitlines():
            try:
                e = json.loads(line)
            except ValueError:  # a process killed mid-line (the fault tests kill -9 theirs)
                continue
            test = e["test"].split(" (", 1)[0].split("@", 1)[0] or OUTSIDE
            c = per_test[test]
            if e["event"] == "process":
                if e["test"]:  # a process started by a test; the pytest workers end outside any
                    c["processes"] += 1
                    c["process_s"] += e["secs"]
                continue
            c[e["event"]] += e["secs"]
            c["n " + e["event"]] += 1
            if e["event"] == BACKEND:
                f = per_function[e.get("fun", "(unnamed)")]
                f["compiles"] += 1
                f["backend"] += e["secs"]
                if e["secs"] >= 1.0:
                    c["n big compile"] += 1
                    c["big compile"] += e["secs"]
                    f["over 1 s"] += 1
                    f["over 1 s seconds"] += e["secs"]
    return per_test, markers, per_function


def _row(c: collections.Counter) -> dict[str, float]:
    return {"tests": c["tests"], "seconds": c["seconds"], "compile": c[TRACE] + c[LOWER] + c[BACKEND],
            "backend": c[BACKEND], "compiles": c["n " + BACKEND], "over 1 s": c["n big compile"],
            "cache saved": c[SAVED], "processes": c["processes"], "jax import": c["jax_import"],
            "Ray starts": c["n ray_init"] + c["n ray_cluster_start"],
            "Ray start+stop": sum(c[k] for k in RAY)}


COLUMNS = ["tests", "seconds", "compile", "backend", "compiles", "over 1 s", "cache saved", "processes",
           "jax import", "Ray starts", "Ray start+stop"]


def _table(title: str, groups: dict[str, collections.Counter], top: int | None = None) -> list[str]:
    rows = sorted(groups.items(), key=lambda kv: -kv[1]["seconds"])
    lines = [f"| {title} | " + " | ".join(COLUMNS) + " |", "| --- " * (len(COLUMNS) + 1) + "|"]
    for name, c in rows[:top]:
        r = _row(c)
        lines.append(f"| {name} | " + " | ".join(f"{round(r[k]):,}" for k in COLUMNS) + " |")
    return lines


def _function_table(per_function: dict[str, collections.Counter], top: int = 12) -> list[str]:
    """The compiled functions that took XLA's backend the longest (a cache hit counts too, at its reading's
    seconds): one program per distinct config and shapes, so `jit(update_program)` (`jit(update)` before
    9b7a060) leads."""
    columns = ["backend", "compiles", "over 1 s", "over 1 s seconds"]
    lines = ["| compiled function | " + " | ".join(columns) + " |", "| --- " * (len(columns) + 1) + "|"]
    for name, f in sorted(per_function.items(), key=lambda kv: -kv[1]["backend"])[:top]:
        lines.append(f"| {name} | " + " | ".join(f"{round(f[k]):,}" for k in columns) + " |")
    return lines


def report(out: Path) -> str:
    seconds = _test_seconds(out)
    per_test, markers, per_function = _events(out)
    files: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    by_marker: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    total: collections.Counter = collections.Counter()
    for test in set(seconds) | set(per_test):
        c = collections.Counter(per_test.get(test, {}))
        if test in seconds:
            c["tests"], c["seconds"] = 1, seconds[test]
        files[test.split("::", 1)[0]].update(c)
        for m in (markers.get(test) or ["(no marker)"]) if test != OUTSIDE else [OUTSIDE]:
            by_marker[m].update(c)
        total.update(c)
    session = json.loads((out / "session.json").read_text()) if (out / "session.json").exists() else {}
    t = _row(total)
    lines = [f"session: {session.get('wall_s', 0):,.0f} s wall on {session.get('workers', '?')} workers "
             f"(exit {session.get('exit_code', '?')}); tests: {t['tests']:,.0f}, their seconds summed "
             f"{t['seconds']:,.0f}",
             f"compiling: {t['compile']:,.0f} s ({total[TRACE]:,.0f} tracing, {total[LOWER]:,.0f} lowering, "
             f"{total[BACKEND]:,.0f} XLA) in {t['compiles']:,.0f} compiles, {t['over 1 s']:,.0f} of them over 1 s "
             f"({total['big compile']:,.0f} s); compile-cache hits: {total['n ' + SAVED]:,.0f}, saving "
             f"{total[SAVED]:,.0f} s for {total[RETRIEVE]:,.0f} s of reading",
             f"processes the tests started (with JAX): {t['processes']:,.0f}, {total['process_s']:,.0f} s, "
             f"{t['jax import']:,.0f} s of it to the end of `import jax`",
             f"Ray: {total['n ray_init']:,.0f} ray.init ({total['ray_init']:,.0f} s), {total['n ray_shutdown']:,.0f} "
             f"ray.shutdown ({total['ray_shutdown']:,.0f} s), {total['n ray_cluster_start']:,.0f} test clusters "
             f"({total['ray_cluster_start'] + total['ray_cluster_shutdown']:,.0f} s to start and stop)",
             "", *_table("file", files), "", *_table("marker", by_marker), "", *_function_table(per_function)]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, help="where to keep what it records (a new or empty folder)")
    p.add_argument("--workers", type=int, default=2, help="pytest-xdist workers (0: one process)")
    p.add_argument("--report", type=Path, metavar="DIR", help="only print the tables of an earlier run in DIR")
    p.add_argument("pytest_args", nargs="*", help="pytest's arguments (after --)")
    a = p.parse_args(argv)
    if a.report:
        print(report(a.report))
        return 0
    if a.out is None:
        p.error("--out DIR is required to run the suite")
    if a.out.exists() and any(a.out.iterdir()):
        p.error(f"{a.out} is not empty")
    code = run(a.out, a.workers, a.pytest_args)
    print(report(a.out))
    return code


if __name__ == "__main__":
    sys.exit(main())
