"""Pinning a process to CPUs no other softac process on this machine holds.

XLA sizes its CPU thread pool from the process's CPU affinity when its backend starts, and its sums
depend on that thread count. A process pinned to n CPUs therefore runs n XLA threads whatever runs
beside it: its numbers do not depend on the neighbours, and side-by-side runs stop competing for the
same cores (two sb3-preset trainings side by side on 2 cores: 1.24x faster pinned to one CPU each;
docs/performance.md). `softac sweep` pins each trial this way, `softac train --cpus N` a single run.
Also the one-line machine description that benchmarks and reports are labelled with.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path
from typing import Any, NamedTuple

# CPUs held by this user's pinned softac processes: one lock file per CPU (per node on a Ray cluster)
CPU_LOCKS = Path(tempfile.gettempdir()) / f"softac-cpus-{os.getuid() if hasattr(os, 'getuid') else 0}"

_held: list[Any] = []  # the locks of this process's own CPUs: open until it exits
_shared = False  # this process was pinned to CPUs another pinned softac process held (none were free)


def cpus_shared() -> bool:
    """Whether this process was pinned (`--cpus`, or as a sweep trial) to CPUs that another pinned softac
    process held when it started: its wall time then does not compare with undisturbed runs'. Recorded in the
    run's config.yaml (rundir.write_config)."""
    return _shared


def usable_cpus() -> list[int]:
    """The CPUs this process may run on ([] where the OS has no affinity API, e.g. macOS)."""
    try:
        return sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return []


class Claim(NamedTuple):
    cpus: list[int]  # [] where pinning is not possible
    locks: list[Any]  # open lock files to keep open while the CPUs are used (closing them releases the claim)
    shared: bool  # no n CPUs were free: these are shared with another pinned process


def _try_lock(path: Path, mode: int) -> Any | None:
    import fcntl

    try:
        lock = open(path, "a")
    except OSError:
        return None
    try:
        fcntl.flock(lock, mode | fcntl.LOCK_NB)
    except OSError:
        lock.close()
        return None
    return lock


def claim_cpus(n: int) -> Claim:
    """n CPUs to pin a process to, and the locks that hold them: CPUs no other pinned softac process on this
    machine uses (an exclusive lock on a file per CPU, released when the holder exits, even if killed), else
    any n of them, shared, so the thread count never depends on what else runs. A process that shares a CPU
    holds a shared lock on that CPU's second file, so that a later claim passes over that CPU while another is
    free (without it, a trial that had to share kept its CPU after the other was freed, and the next trial,
    finding no exclusive lock there, joined it: two trials on one core beside an idle one, measured)."""
    import fcntl

    allowed = usable_cpus()
    if not allowed:
        return Claim([], [], False)
    try:
        CPU_LOCKS.mkdir(exist_ok=True)
    except OSError:  # no writable temp dir: not pinned
        return Claim([], [], False)
    n = min(n, len(allowed))
    cpus: list[int] = []
    locks: list[Any] = []
    for cpu in allowed:
        if len(cpus) == n:
            break
        lock = _try_lock(CPU_LOCKS / f"cpu{cpu}.lock", fcntl.LOCK_EX)
        if lock is None:  # another process holds it
            continue
        sharers = _try_lock(CPU_LOCKS / f"cpu{cpu}.shared", fcntl.LOCK_EX)
        if sharers is None:  # a process that had to share runs there
            lock.close()
            continue
        sharers.close()
        cpus.append(cpu)
        locks.append(lock)
    if len(cpus) == n:
        return Claim(cpus, locks, False)
    for lock in locks:
        lock.close()
    # sharing: CPUs where no other process shares yet first (two trials that both found every CPU held, by
    # processes stopped or running, went to one core by their pids' parity while the other had one process:
    # measured), in an order that starts at a CPU picked by the pid, so that sharers spread
    start = os.getpid() % len(allowed)
    rotated = [allowed[(start + i) % len(allowed)] for i in range(len(allowed))]
    unshared = []
    for cpu in rotated:
        probe = _try_lock(CPU_LOCKS / f"cpu{cpu}.shared", fcntl.LOCK_EX)
        if probe is not None:
            probe.close()
            unshared.append(cpu)
    cpus = sorted((unshared + [cpu for cpu in rotated if cpu not in unshared])[:n])
    held = [_try_lock(CPU_LOCKS / f"cpu{cpu}.shared", fcntl.LOCK_SH) for cpu in cpus]
    return Claim(cpus, [lock for lock in held if lock is not None], True)


# set by a sweep trial (softac.sweep.trial) for the process it starts, which applies them itself when it starts
TRIAL_CPUS_VAR = "SOFTAC_TRIAL_CPUS"  # the CPUs the trial claimed, e.g. "0,3"
TRIAL_PARENT_VAR = "SOFTAC_TRIAL_PARENT"  # the pid of the trial's Ray worker
TRIAL_SHARED_VAR = "SOFTAC_TRIAL_CPUS_SHARED"  # "1" where the trial's CPUs are shared (claim_cpus found none free)
# seconds a stopped trial's process may take to write its checkpoint and exit before it ends itself (SIGALRM)
TRIAL_STOP_DEADLINE_VAR = "SOFTAC_TRIAL_STOP_DEADLINE_S"
TRIAL_STOP_DEADLINE_S = 600


def trial_settings_env(cpus: list[int], parent_pid: int, shared: bool = False) -> dict[str, str]:
    """The variables that tell a trial's process its CPUs (and whether they are shared) and its parent (see
    adopt_trial_settings)."""
    return {TRIAL_CPUS_VAR: ",".join(map(str, cpus)), TRIAL_PARENT_VAR: str(parent_pid),
            **({TRIAL_SHARED_VAR: "1"} if shared else {})}


def adopt_trial_settings() -> None:
    """First thing in `python -m softac` and `python -m softac.peers` (before JAX starts its backend, which
    sizes its thread pool from the affinity): in a process a sweep trial started, pin to the trial's CPUs and
    ask for SIGTERM when the trial's Ray worker dies (PR_SET_PDEATHSIG), so that a stopped sweep's trial
    checkpoints and exits. Done here, after exec, not in a preexec_fn: Python code run between fork and exec
    in a Ray worker, whose other threads may hold locks at the fork, hung a trial's child for minutes (seen
    with two sweeps side by side), and Python's docs warn against preexec_fn with threads."""
    global _shared
    cpus = os.environ.pop(TRIAL_CPUS_VAR, None)
    parent = os.environ.pop(TRIAL_PARENT_VAR, None)
    _shared = os.environ.pop(TRIAL_SHARED_VAR, None) == "1" and bool(cpus)
    if cpus:
        try:
            os.sched_setaffinity(0, [int(c) for c in cpus.split(",")])
        except (AttributeError, OSError, ValueError):
            pass
    if parent and sys.platform.startswith("linux"):
        import ctypes
        import signal

        from softac.base.stop_signal import end_within_after_stop

        # a trial's process runs outside its Ray worker's process group (trial.py), which Ray would SIGKILL;
        # so that one stuck after a stop (a simulator hung in a step) is not left behind holding its run's lock
        try:
            deadline = float(os.environ.get(TRIAL_STOP_DEADLINE_VAR, TRIAL_STOP_DEADLINE_S))
        except ValueError:
            deadline = TRIAL_STOP_DEADLINE_S
        end_within_after_stop(deadline)
        # an ignored SIGTERM is inherited through exec (seen: from a process that had run a stopped training
        # in-process): the signal below must end this process until training installs its own handler
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        try:
            ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            return
        if str(os.getppid()) != parent:  # the worker died before the prctl: as if the signal had come
            os.kill(os.getpid(), signal.SIGTERM)


def pin_this_process(n: int) -> tuple[list[int], bool]:
    """Pin this process to n claimed CPUs, held until it exits: (the CPUs, whether they are shared with
    another pinned process). Call it before JAX starts its backend, which sizes its thread pool then."""
    global _shared
    claim = claim_cpus(n)
    if claim.cpus:
        os.sched_setaffinity(0, claim.cpus)
    _held.extend(claim.locks)
    _shared = claim.shared
    return claim.cpus, claim.shared


def cpu_flags() -> set[str]:
    """The CPU's feature flags as /proc/cpuinfo lists them (empty where there is none, e.g. macOS)."""
    try:
        return set(Path("/proc/cpuinfo").read_text().split())
    except OSError:
        return set()


# the values XLA's --xla_cpu_max_isa takes on x86, lowest first (XLA matches them case-insensitively and ignores,
# with a warning, one it does not know); its bf16 matmul instructions are AVX512_BF16's and AMX's
XLA_MAX_ISAS = ("SSE4_2", "AVX", "AVX2", "AVX512", "AVX512_VNNI", "AVX512_BF16", "AMX", "AMX_FP16")


# each of XLA_MAX_ISAS and the /proc/cpuinfo flag that says the CPU has it, newest first
ISA_FLAGS = (("AMX_FP16", "amx_fp16"), ("AMX", "amx_bf16"), ("AVX512_BF16", "avx512_bf16"),
             ("AVX512_VNNI", "avx512_vnni"), ("AVX512", "avx512f"), ("AVX2", "avx2"), ("AVX", "avx"),
             ("SSE4_2", "sse4_2"))

# the label machine_description gives each of cpu_isa's answers (none below AVX2)
VECTOR_EXTENSIONS = {"AMX_FP16": "AMX", "AMX": "AMX", "AVX512_BF16": "AVX-512 BF16", "AVX512_VNNI": "AVX-512",
                     "AVX512": "AVX-512", "AVX2": "AVX2"}


def cpu_isa() -> str | None:
    """The newest of XLA_MAX_ISAS this CPU has (None where it has none of them, e.g. an ARM CPU, or no
    /proc/cpuinfo). Limiting XLA to it or to anything newer changes nothing: on an AVX2-only AMD EPYC every object
    file XLA compiled for the update was the same with --xla_cpu_max_isa=AVX2 as without (issue 64), so
    `make test-isa` skips there."""
    flags = cpu_flags()
    return next((isa for isa, flag in ISA_FLAGS if flag in flags), None)


def xla_limit_changes_code(limit: str) -> bool:
    """Whether --xla_cpu_max_isa=LIMIT makes XLA compile other code on this CPU than it does unlimited: only where
    the CPU has a newer instruction set than LIMIT (or where cpu_isa cannot tell, or XLA does not know LIMIT)."""
    isa, limit = cpu_isa(), limit.upper()
    return isa is None or limit not in XLA_MAX_ISAS or XLA_MAX_ISAS.index(isa) > XLA_MAX_ISAS.index(limit)


def xla_max_isa() -> str | None:
    """The newest ISA that XLA_FLAGS lets XLA's CPU code use (--xla_cpu_max_isa=...), or None where it sets no
    limit XLA knows. The last occurrence wins, as XLA parses the flags in order."""
    value = None
    for flag in os.environ.get("XLA_FLAGS", "").split():
        name, _, setting = flag.lstrip("-").partition("=")
        if name == "xla_cpu_max_isa":
            value = setting.upper()
    return value if value in XLA_MAX_ISAS else None


def cpu_has_bf16() -> bool:
    """AVX-512 BF16 or AMX, and XLA allowed to use them: the CPU runs bf16 matmuls fast (bench shows softac-bf16
    by default, and `matmul_dtype=auto` picks bf16 here). XLA_FLAGS=--xla_cpu_max_isa=AVX2 (or any ISA below
    AVX512_BF16) keeps XLA off those units, so bf16 matmuls would run converted, slower than float32."""
    flags, limit = cpu_flags(), xla_max_isa()
    allowed = len(XLA_MAX_ISAS) if limit is None else XLA_MAX_ISAS.index(limit) + 1  # how many of them XLA may use
    return (("avx512_bf16" in flags and "AVX512_BF16" in XLA_MAX_ISAS[:allowed])
            or ("amx_bf16" in flags and "AMX" in XLA_MAX_ISAS[:allowed]))


def vector_extensions() -> str:
    """The widest vector instructions the CPU has (what XLA's matmuls run on): two machines sold under one
    model name ("AMD EPYC") ran the same update 7x apart, one with AVX-512 BF16 and one without AVX-512."""
    return VECTOR_EXTENSIONS.get(cpu_isa() or "", "")


def machine_description() -> str:
    """CPU model (with its vector extensions), core count and Python version: the line every benchmark,
    report and run directory is labelled with."""
    import platform

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    extensions = vector_extensions()
    if extensions:
        cpu = f"{cpu} ({extensions})"
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}"
