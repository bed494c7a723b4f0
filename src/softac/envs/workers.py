"""Env worker processes (config key `env_workers`): `WorkerEnvPool` steps the run's envs in K processes.

Each worker holds a contiguous slice of the envs in an `EnvPool` of its own, so stepping, resetting a
finished env with its per-(env, reset) seed, and saving and restoring state are EnvPool's: the
transitions are the ones the in-process pool gives, and the state has EnvPool's format, so a checkpoint
resumes with any number of workers. Workers are spawned, not forked: the parent runs JAX/XLA threads,
which a fork would copy in an unknown state. They ignore SIGINT, so Ctrl-C reaches the training loop
alone (it finishes its step, checkpoints, then closes them), and they exit when their pipe's other end
closes, so a parent killed outright leaves none behind.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import pickle
import signal
import sys
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.envs.registration import EnvSpec

from softac.envs.make import (EnvError, EnvFailed, EnvPool, EnvSource, StepResult, copy_env, env_name, make_env,
                         resolve_env_id)
from softac.errors import SoftacError

CLOSE_WAIT_S = 2.0  # for a worker to finish its step and exit before it is terminated
STATE_KEYS = ("envs", "resets", "episode_return", "episode_length")  # EnvPool.get_state's per-env lists


# ---- what a worker makes its envs from -------------------------------------------

def env_recipe(source: EnvSource) -> bytes:
    """`source` pickled for the workers, as `copy_env` would remake it: an id's or an instance's Gymnasium
    spec (self-contained: the worker needs no registration), else the instance itself."""
    if isinstance(source, str):
        candidates = [gym.spec(resolve_env_id(source)), source]
    elif isinstance(source, EnvSpec):
        candidates = [source]
    else:
        candidates = [getattr(source, "spec", None), source]
    reasons = []
    for candidate in filter(None, candidates):
        try:
            return pickle.dumps(candidate)
        except Exception as exc:  # any pickling failure means: try the next way, else tell the user
            reasons.append(f"{type(exc).__name__}: {exc}")
    raise EnvError(f"env {env_name(source)} cannot be sent to env worker processes ({reasons[-1]}); register it "
                   "with gymnasium.register in a module and pass module:EnvId, or set env_workers=0")


def _make_from_recipe(source: Any) -> gym.Env:
    return copy_env(source) if isinstance(source, gym.Env) else make_env(source)


# ---- the worker process ------------------------------------------------------------

def _reset(pool: EnvPool, step: int) -> np.ndarray:
    return pool.reset(step)


def _step(pool: EnvPool, payload: tuple[np.ndarray, int]) -> tuple[StepResult, np.ndarray]:
    return pool.step(*payload), pool.obs


def _get_state(pool: EnvPool, _: Any) -> tuple[dict, dict[str, np.ndarray]]:
    return pool.get_state()


def _set_state(pool: EnvPool, payload: tuple[dict, dict[str, np.ndarray], int]) -> tuple[bool, np.ndarray]:
    return pool.set_state(*payload), pool.obs


def _apply(pool: EnvPool, fn: Any) -> list[Any]:
    results = pool.apply(fn)
    try:
        pickle.dumps(results)
    except Exception as exc:  # raised here, it is reported; raised by the reply's send, it would kill the worker
        raise TypeError(f"apply_to_envs: the function's results cannot be sent back from an env worker "
                        f"({type(exc).__name__}: {exc})") from None
    return results


COMMANDS = {"reset": _reset, "step": _step, "get_state": _get_state, "set_state": _set_state, "apply": _apply}


def serve(conn: Connection, recipe: bytes, name: str, seed: int, first_index: int, count: int) -> None:
    """A worker's main loop: make its envs, then answer commands until told to close or the parent is gone."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the training loop's, which then closes us
    try:
        source = pickle.loads(recipe)
        pool = EnvPool(lambda i: _make_from_recipe(source), count, seed, name, first_index)
    except Exception as exc:  # a bad env is reported to the parent, which raises it
        with contextlib.suppress(OSError):
            conn.send(("failed", f"env {name} cannot be made in an env worker process: {type(exc).__name__}: "
                                 f"{exc}".splitlines()[0]))
        return
    try:
        conn.send(("ok", (pool.obs.shape[1:], pool.obs.dtype.str)))
        while (request := conn.recv())[0] != "close":
            conn.send(_answer(pool, *request))
    except (EOFError, OSError):  # the parent is gone: nobody needs these envs any more
        pass
    finally:
        pool.close()
    # skip the interpreter's teardown, which takes most of a second with MuJoCo loaded: nothing is left to clean up
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


def _answer(pool: EnvPool, command: str, payload: Any) -> tuple[str, Any]:
    try:
        return "ok", COMMANDS[command](pool, payload)
    except EnvFailed as exc:
        return "failed", str(exc)
    except Exception as exc:  # anything else an env raised: the run fails with its message, not a hang
        return "failed", f"env {pool.name} raised in an env worker: {type(exc).__name__}: {exc}".splitlines()[0]


# ---- the parent's side ---------------------------------------------------------------

def split_evenly(n: int, parts: int) -> list[tuple[int, int]]:
    """`parts` contiguous (start, stop) slices of range(n), sizes differing by at most one."""
    bounds = [i * n // parts for i in range(parts + 1)]
    return list(zip(bounds[:-1], bounds[1:]))


class WorkerDied(EnvFailed):
    """An env worker process that exited or was killed (a crashing simulator, the OOM killer, kill -9)."""


@dataclass
class _Worker:
    process: multiprocessing.process.BaseProcess
    conn: Connection
    start: int
    stop: int
    name: str

    def send(self, message: tuple[str, Any], step: int | None) -> None:
        try:
            self.conn.send(message)
        except OSError:
            raise self.died(step) from None

    def receive(self, step: int | None) -> Any:
        try:
            status, value = self.conn.recv()
        except (EOFError, OSError):
            raise self.died(step) from None
        if status == "failed":
            raise EnvFailed(value)
        return value

    def died(self, step: int | None) -> WorkerDied:
        self.process.join(timeout=1.0)
        code = self.process.exitcode
        if code is None:
            how = "stopped answering"
        elif code < 0:
            how = f"was killed by {signal.Signals(-code).name}"
        else:
            how = f"exited with code {code}"
        when = f" at step {step}" if step is not None else ""
        envs = f"env {self.start}" if self.stop - self.start == 1 else f"envs {self.start}-{self.stop - 1}"
        return WorkerDied(f"env {self.name}: the env worker process {self.process.pid} ({envs}) {how}{when}")

    def ask_to_close(self) -> None:
        with contextlib.suppress(OSError):
            self.conn.send(("close", None))

    def wait_closed(self) -> None:
        self.process.join(timeout=CLOSE_WAIT_S)
        if self.process.is_alive():  # stuck in a slow step, or ignoring us
            self.process.terminate()
            self.process.join(timeout=CLOSE_WAIT_S)
        if self.process.is_alive():
            self.process.kill()
            self.process.join()
        self.conn.close()


class WorkerEnvPool:
    """EnvPool's interface over `workers` processes, each stepping a contiguous slice of the `n` envs."""

    def __init__(self, source: EnvSource, n: int, seed: int, name: str, workers: int):
        if not 1 <= workers <= n:
            raise SoftacError(f"env_workers must be between 1 and n_envs={n} here, got {workers}")
        recipe = env_recipe(source)
        self.name, self.n, self.seed = name, n, seed
        self.usable = True  # False once a command failed midway: the workers' replies are out of step
        self.workers: list[_Worker] = []
        context = multiprocessing.get_context("spawn")
        try:
            for start, stop in split_evenly(n, workers):
                parent_end, child_end = context.Pipe()
                process = context.Process(target=serve, args=(child_end, recipe, name, seed, start, stop - start),
                                          name=f"softac-env-worker-{start}-{stop - 1}", daemon=True)
                process.start()
                child_end.close()  # so the parent sees EOF when the worker dies
                self.workers.append(_Worker(process, parent_end, start, stop, name))
            obs_shape, obs_dtype = self._ready()
        except BaseException:
            self.close()
            raise
        self.pids = [worker.process.pid for worker in self.workers]
        self.obs = np.zeros((n, *obs_shape), np.dtype(obs_dtype))

    def _ready(self) -> tuple[tuple[int, ...], str]:
        """Each worker's observation shape and dtype once it has made its envs; a worker that could not is bad
        input."""
        try:
            dims = [worker.receive(None) for worker in self.workers]
        except WorkerDied as exc:
            raise EnvError(f"{exc} while starting; a script that trains with env_workers must keep its top level "
                           "under `if __name__ == \"__main__\":` (spawned workers import it)") from None
        except EnvFailed as exc:
            raise EnvError(f"{exc}; register it with gymnasium.register in a module and pass module:EnvId, "
                           "or set env_workers=0") from None
        return dims[0]

    def _ask_all(self, command: str, payloads: list[Any], step: int | None) -> list[Any]:
        """Send each worker its command, then collect the replies: the workers run meanwhile, side by side."""
        if not self.usable:
            raise EnvFailed(f"env {self.name}: its env worker processes failed or were closed earlier")
        try:
            for worker, payload in zip(self.workers, payloads):
                worker.send((command, payload), step)
            return [worker.receive(step) for worker in self.workers]
        except BaseException:
            self.usable = False
            raise

    def reset(self, step: int = 0) -> np.ndarray:
        self.obs = np.concatenate(self._ask_all("reset", [step] * len(self.workers), step))
        return self.obs

    def step(self, actions: np.ndarray, step: int) -> StepResult:
        replies = self._ask_all("step", [(actions[w.start:w.stop], step) for w in self.workers], step)
        results = [result for result, _ in replies]
        self.obs = np.concatenate([obs for _, obs in replies])
        finished = [episode._replace(env=worker.start + episode.env)
                    for worker, result in zip(self.workers, results) for episode in result.finished]
        return StepResult(np.concatenate([r.next_obs for r in results]), np.concatenate([r.rewards for r in results]),
                          np.concatenate([r.terminated for r in results]),
                          np.concatenate([r.truncated for r in results]), finished)

    def get_state(self) -> tuple[dict, dict[str, np.ndarray]]:
        """EnvPool.get_state's format, gathered from the workers' slices."""
        parts = self._ask_all("get_state", [None] * len(self.workers), None)
        meta: dict[str, list] = {key: [] for key in STATE_KEYS}
        arrays = {"obs": np.concatenate([part_arrays["obs"] for _, part_arrays in parts])}
        for worker, (part_meta, part_arrays) in zip(self.workers, parts):
            for key in STATE_KEYS:
                meta[key].extend(part_meta[key])
            for i in range(worker.stop - worker.start):
                if f"physics_{i}" in part_arrays:
                    arrays[f"physics_{worker.start + i}"] = part_arrays[f"physics_{i}"]
        return meta, arrays

    def set_state(self, meta: dict, arrays: dict[str, np.ndarray], step: int) -> bool:
        """Restore every env from EnvPool's format; False (fresh episodes) where that is impossible."""
        if len(meta["envs"]) != self.n:
            raise SoftacError(f"checkpoint has {len(meta['envs'])} envs but n_envs={self.n}")
        payloads = [(*_slice_state(meta, arrays, w.start, w.stop), step) for w in self.workers]
        replies = self._ask_all("set_state", payloads, step)
        self.obs = np.concatenate([obs for _, obs in replies])
        return all(exact for exact, _ in replies)

    def apply(self, fn: Any) -> list[Any]:
        """`fn(env)` for each env, in the workers, in env order; `fn` travels pickled, so it must be a
        module-level function (or a functools.partial of one), not a lambda or a closure."""
        try:
            pickle.dumps(fn)
        except Exception as exc:
            raise SoftacError(f"apply_to_envs with env_workers needs a function the worker processes can receive: "
                              f"a module-level function or a functools.partial of one, not a lambda or a closure "
                              f"({type(exc).__name__}: {exc})") from None
        parts = self._ask_all("apply", [fn] * len(self.workers), None)
        return [result for part in parts for result in part]

    def close(self) -> None:
        for worker in self.workers:  # all asked first, so they wind down side by side
            worker.ask_to_close()
        for worker in self.workers:
            worker.wait_closed()
        self.workers = []
        self.usable = False


def _slice_state(meta: dict, arrays: dict[str, np.ndarray], start: int, stop: int) -> tuple[dict, dict]:
    """The part of EnvPool's state that envs start..stop-1 hold, indexed from 0 as their worker's pool is."""
    part_meta = {key: meta[key][start:stop] for key in STATE_KEYS}
    part_arrays = {"obs": arrays["obs"][start:stop]}
    for i in range(start, stop):
        if f"physics_{i}" in arrays:
            part_arrays[f"physics_{i - start}"] = arrays[f"physics_{i}"]
    return part_meta, part_arrays
