"""benchmarks/suite_time.py's probe (issue 64): imported by every Python process the measured test session starts
(this folder is put first on PYTHONPATH), it records, per process and under the test that was running
(PYTEST_CURRENT_TEST, which child processes inherit): the seconds to the end of `import jax`, JAX's compile events
(tracing, lowering, XLA's backend compile, compile-cache hits and the time they saved), each `ray.init` and
`ray.shutdown` and each Ray test cluster's start and stop, and the process's own wall time. One JSON line an event,
in SUITE_TIME_EVENTS/<pid>.jsonl. Without SUITE_TIME_EVENTS it does nothing."""

import atexit
import functools
import importlib.abc
import importlib.util
import json
import os
import sys
import time

_START = time.time()
_EVENTS = os.environ.get("SUITE_TIME_EVENTS")
_file = None


def _write(event: str, secs: float, **extra) -> None:
    global _file
    if _file is None:
        _file = open(os.path.join(_EVENTS, f"{os.getpid()}.jsonl"), "a", buffering=1)
    test = os.environ.get("PYTEST_CURRENT_TEST", "").rsplit(" (", 1)[0]
    _file.write(json.dumps({"event": event, "secs": secs, "test": test, "pid": os.getpid(), **extra}) + "\n")


def _timed(event: str, fn):
    @functools.wraps(fn)
    def timed(*args, **kwargs):
        start = time.time()
        try:
            return fn(*args, **kwargs)
        finally:
            _write(event, time.time() - start)
    return timed


def _after_jax(module) -> None:
    _write("jax_import", time.time() - _START)
    from jax import monitoring

    # JAX names the compiled function (fun_name) with its tracing, lowering and backend events
    monitoring.register_event_duration_secs_listener(
        lambda event, secs, **kw: _write(event, secs, **({"fun": kw["fun_name"]} if "fun_name" in kw else {})))


def _after_ray(module) -> None:
    module.init = _timed("ray_init", module.init)
    module.shutdown = _timed("ray_shutdown", module.shutdown)


def _after_cluster_utils(module) -> None:
    cluster = module.Cluster
    cluster.__init__ = _timed("ray_cluster_start", cluster.__init__)
    cluster.shutdown = _timed("ray_cluster_shutdown", cluster.shutdown)


_HOOKS = {"jax": _after_jax, "ray": _after_ray, "ray.cluster_utils": _after_cluster_utils}


class _AfterImport(importlib.abc.MetaPathFinder):
    """Runs a hook once a watched module has been executed (the module itself is found as usual)."""

    def __init__(self) -> None:
        self.finding: set[str] = set()

    def find_spec(self, name, path, target=None):
        if name not in _HOOKS or name in self.finding:
            return None
        self.finding.add(name)
        try:
            spec = importlib.util.find_spec(name)
        finally:
            self.finding.discard(name)
        if spec is None or spec.loader is None:
            return None
        execute = spec.loader.exec_module

        def exec_module(module):
            execute(module)
            try:
                _HOOKS[name](module)
            except Exception as exc:  # a probe must never break the process it measures
                _write(f"probe_failed:{name}:{exc!r}", 0.0)

        spec.loader.exec_module = exec_module
        return spec


if _EVENTS:
    sys.meta_path.insert(0, _AfterImport())

    @atexit.register
    def _process_end() -> None:
        if _file is not None or "jax" in sys.modules:
            _write("process", time.time() - _START, argv=" ".join(sys.orig_argv[:6]))
