"""CPU thread pools of one run: decide how many threads it may use, and apply that everywhere.

Several runs on one machine (a shell loop, the benchmark's workers, Ray tasks) must share its
cores. Left alone, every process starts a torch pool of one thread per core (plus OpenMP and
OpenBLAS pools of the same size), so eight runs on 16 cores keep more than 128 busy threads and
spend their time waiting for each other (issue #25: eight runs had not finished after 9 minutes;
with two threads each they finished in 4.3).

Precedence of the thread count (first one given wins):

1. the run's own setting: ``projo4d run --threads N`` or ``threads: N`` in its config
   (:attr:`toolkit.run_settings.RunSettings.threads`);
2. ``PROJO4D_THREADS=N`` in the environment (the benchmark's executors set it for each job);
3. the default: the cores this process may run on (its affinity mask, ``os.sched_getaffinity``;
   ``taskset`` and cpusets shrink it, a CPU quota does not) divided by
   ``PROJO4D_CONCURRENT_RUNS`` (the number of runs a parent started side by side; 1 when unset),
   at least 1 and at most :func:`default_cap` of the run's device: 8 on CUDA, **1 on a CPU
   device** (measured on 2 cores shared with other jobs, the test suite's tiny scene: one run
   with 1 thread took 7–13 s, with 2 threads 14–37 s, five runs each; probably OpenMP regions
   over tensors this small wait on descheduled threads more than they gain).

What is applied (:func:`apply_threads`): torch's intra-op pool (``torch.set_num_threads``, which
also sets OpenMP's count for torch's kernels), torch's inter-op pool (only possible once per
process, before it is first used), the OpenBLAS pools already loaded in this process (numpy's and
scipy's, through their ``*openblas_set_num_threads*`` entry points), and ``OMP_NUM_THREADS``,
``MKL_NUM_THREADS``, ``OPENBLAS_NUM_THREADS``, ``NUMEXPR_NUM_THREADS`` and ``PROJO4D_THREADS``
for child processes (``PROJO4D_THREADS`` only where a parent starts a child,
:func:`child_environment`). Warp has no CPU thread-pool knob: its CPU kernels run on the launching
thread (``wp.config.load_module_max_workers``, the parallel *compiler*, stays at its serial
default), so nothing is set for it.
"""

from __future__ import annotations

import ctypes
import logging
import os
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from typing import Iterator, Mapping, MutableMapping, Optional

__all__ = [
    "CHILD_ENV_VARS",
    "DEFAULT_CAP",
    "DEFAULT_CPU_CAP",
    "default_cap",
    "ENV_CONCURRENT",
    "ENV_THREADS",
    "ThreadChoice",
    "ThreadSettingError",
    "apply_threads",
    "available_cores",
    "blas_threads",
    "child_env",
    "child_environment",
    "configure_threads",
    "parse_count",
    "per_job_threads",
    "resolve_threads",
    "set_blas_threads",
]

log = logging.getLogger(__name__)

#: an explicit thread count for this process (set by the benchmark's executors for each job)
ENV_THREADS = "PROJO4D_THREADS"
#: how many runs a parent started side by side on this machine (divides the default)
ENV_CONCURRENT = "PROJO4D_CONCURRENT_RUNS"
#: the default never exceeds this on a GPU run: its CPU side (kernel launches, evaluation, BLAS)
#: gains little from more, and one run on a 128-core node should not take them all
DEFAULT_CAP = 8
#: ... and this on a CPU run (see the module docstring for the measurement)
DEFAULT_CPU_CAP = 1
#: thread-count variables that native libraries read when a (child) process starts
CHILD_ENV_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS")


class ThreadSettingError(ValueError):
    """A thread count that is not an integer >= 1 (the message names where it came from)."""


@dataclass(frozen=True)
class ThreadChoice:
    """The thread count of this process and why.

    Attributes:
        threads: CPU threads for torch intra-op, OpenMP and BLAS pools (>= 1).
        source: ``"settings"`` (flag/config), ``"env"`` (``PROJO4D_THREADS``) or ``"default"``.
        cores: cores in this process's affinity mask.
        concurrent: runs sharing those cores (``PROJO4D_CONCURRENT_RUNS``, else 1).
    """

    threads: int
    source: str
    cores: int
    concurrent: int

    def to_dict(self) -> dict:
        return asdict(self)


def parse_count(value, name: str, what: str = "a number of CPU threads") -> int:
    """``value`` as an integer >= 1, else :class:`ThreadSettingError` naming ``name`` (and ``what``
    it counts).

    Accepts ints and integer strings (``"4"``); rejects 0, negatives, ``True``/``False``, floats
    with a fraction and anything else.
    """
    if isinstance(value, bool):
        n = None
    elif isinstance(value, int):
        n = value
    elif isinstance(value, float) and value.is_integer():
        n = int(value)
    elif isinstance(value, str):
        try:
            n = int(value.strip())
        except ValueError:
            n = None
    else:
        n = None
    if n is None or n < 1:
        raise ThreadSettingError(f"{name} must be an integer >= 1 ({what}), got {value!r}")
    return n


def available_cores() -> int:
    """Cores this process may run on: the size of its affinity mask (``os.cpu_count()`` where
    the platform has none)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def per_job_threads(concurrent: int, cores: Optional[int] = None) -> int:
    """Threads for each of ``concurrent`` runs sharing ``cores`` (default: this affinity mask):
    ``cores // concurrent``, at least 1."""
    concurrent = parse_count(concurrent, "concurrent", "a number of runs")
    cores = available_cores() if cores is None else parse_count(cores, "cores", "a number of cores")
    return max(1, cores // concurrent)


def default_cap(device: Optional[str] = None) -> int:
    """Upper bound of the default thread count: :data:`DEFAULT_CPU_CAP` for ``"cpu"``, else
    :data:`DEFAULT_CAP` (``"cuda"``, ``"cuda:1"``, or ``None``: unknown)."""
    return DEFAULT_CPU_CAP if device == "cpu" else DEFAULT_CAP


def resolve_threads(explicit=None, *, environ: Optional[Mapping[str, str]] = None, cores: Optional[int] = None,
                    device: Optional[str] = None, cap: Optional[int] = None, name: str = "threads") -> ThreadChoice:
    """The thread count of this run (see the module docstring for the precedence).

    Args:
        explicit: the run's own setting (``None``: not given).
        environ: environment to read (default ``os.environ``).
        cores: cores of the affinity mask (default: :func:`available_cores`).
        device: the run's device (``"cpu"``, ``"cuda"``...); picks the default's cap.
        cap: upper bound of the *default* (an explicit count or ``PROJO4D_THREADS`` is honoured);
            ``None``: :func:`default_cap` of ``device``.
        name: how errors call ``explicit`` (e.g. ``"RunSettings.threads"``).

    Raises:
        ThreadSettingError: ``explicit``, ``PROJO4D_THREADS`` or ``PROJO4D_CONCURRENT_RUNS`` is not
            an integer >= 1.
    """
    env = os.environ if environ is None else environ
    cores = available_cores() if cores is None else parse_count(cores, "cores", "a number of cores")
    raw_conc = env.get(ENV_CONCURRENT)
    concurrent = (parse_count(raw_conc, f"environment variable {ENV_CONCURRENT}", "runs sharing this machine")
                  if raw_conc not in (None, "") else 1)
    if explicit is not None:
        return ThreadChoice(parse_count(explicit, name), "settings", cores, concurrent)
    raw = env.get(ENV_THREADS)
    if raw not in (None, ""):
        return ThreadChoice(parse_count(raw, f"environment variable {ENV_THREADS}"), "env", cores, concurrent)
    cap = default_cap(device) if cap is None else parse_count(cap, "cap")
    return ThreadChoice(max(1, min(cap, cores // concurrent)), "default", cores, concurrent)


def child_env(threads: int, concurrent: Optional[int] = None) -> dict[str, str]:
    """Environment variables that give a child process ``threads`` threads (and tell it how
    many runs share the machine)."""
    n = str(parse_count(threads, "threads"))
    env = {var: n for var in CHILD_ENV_VARS}
    env[ENV_THREADS] = n
    if concurrent is not None:
        env[ENV_CONCURRENT] = str(parse_count(concurrent, "concurrent", "a number of runs"))
    return env


@contextmanager
def child_environment(threads: int, concurrent: Optional[int] = None,
                      environ: Optional[MutableMapping[str, str]] = None) -> Iterator[dict[str, str]]:
    """Within the block, ``os.environ`` holds :func:`child_env` (for processes started there);
    afterwards the previous values come back."""
    env = os.environ if environ is None else environ
    new = child_env(threads, concurrent)
    saved = {k: env.get(k) for k in new}
    env.update(new)
    try:
        yield new
    finally:
        for k, v in saved.items():
            if v is None:
                env.pop(k, None)
            else:
                env[k] = v


def _loaded_openblas() -> list[str]:
    """Paths of the OpenBLAS libraries mapped into this process (Linux ``/proc/self/maps``)."""
    try:
        with open("/proc/self/maps") as f:
            paths = {line.split()[-1] for line in f if "openblas" in line.lower() and "/" in line}
    except OSError:
        return []
    return sorted(p for p in paths if ".so" in p)


_BLAS_SETTERS = ("openblas_set_num_threads", "scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads_64_",
                 "scipy_openblas_set_num_threads")
_BLAS_GETTERS = ("openblas_get_num_threads", "scipy_openblas_get_num_threads64_", "scipy_openblas_get_num_threads_64_",
                 "scipy_openblas_get_num_threads")


def _blas_entry_points() -> Iterator[tuple[str, object, object]]:
    """``(path, setter or None, getter or None)`` of each OpenBLAS loaded here."""
    for path in _loaded_openblas():
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        setter = next((getattr(lib, s) for s in _BLAS_SETTERS if hasattr(lib, s)), None)
        getter = next((getattr(lib, g) for g in _BLAS_GETTERS if hasattr(lib, g)), None)
        if setter is not None:
            setter.argtypes, setter.restype = [ctypes.c_int], None
        if getter is not None:
            getter.argtypes, getter.restype = [], ctypes.c_int
        yield path, setter, getter


def blas_threads() -> dict[str, int]:
    """``{library path: thread count}`` of every OpenBLAS loaded in this process (empty where
    none is, or without ``/proc/self/maps``)."""
    return {path: int(getter()) for path, _, getter in _blas_entry_points() if getter is not None}


def set_blas_threads(threads: int) -> dict[str, int]:
    """Set the thread count of every OpenBLAS already loaded here (numpy's, scipy's).

    Returns:
        :func:`blas_threads` afterwards. Libraries loaded later read ``OPENBLAS_NUM_THREADS`` /
        ``OMP_NUM_THREADS``, which :func:`apply_threads` sets.
    """
    n = parse_count(threads, "threads")
    for _, setter, _ in _blas_entry_points():
        if setter is not None:
            setter(n)
    return blas_threads()


def apply_threads(threads: int, *, environ: Optional[MutableMapping[str, str]] = None) -> dict:
    """Give this process ``threads`` CPU threads: torch intra-op (and its OpenMP), torch inter-op
    (when still possible), loaded OpenBLAS pools, and the variables child processes read.

    Returns:
        What took effect: ``{"torch_intra_op", "torch_inter_op", "blas"}`` (``blas``: library ->
        count, see :func:`set_blas_threads`).
    """
    import torch

    n = parse_count(threads, "threads")
    env = os.environ if environ is None else environ
    env.update({var: str(n) for var in CHILD_ENV_VARS})  # not PROJO4D_THREADS: a later run here resolves afresh
    torch.set_num_threads(n)
    if torch.get_num_interop_threads() != n:
        try:
            torch.set_num_interop_threads(n)
        except RuntimeError as err:  # the inter-op pool already started (or was set): keep it
            log.debug("torch inter-op threads stay at %d: %s", torch.get_num_interop_threads(), err)
    return {"torch_intra_op": torch.get_num_threads(), "torch_inter_op": torch.get_num_interop_threads(),
            "blas": set_blas_threads(n)}


def configure_threads(explicit=None, *, device: Optional[str] = None, name: str = "threads",
                      environ: Optional[MutableMapping[str, str]] = None, cores: Optional[int] = None) -> ThreadChoice:
    """Resolve this run's thread count (:func:`resolve_threads`) and apply it (:func:`apply_threads`).

    Call it once at the start of a run, before heavy work: afterwards ``torch.get_num_threads()``
    equals ``choice.threads``.
    """
    choice = resolve_threads(explicit, environ=environ, cores=cores, device=device, name=name)
    applied = apply_threads(choice.threads, environ=environ)
    log.info("CPU threads: %d (%s; %d cores, %d concurrent run(s)); torch inter-op %d", choice.threads, choice.source,
             choice.cores, choice.concurrent, applied["torch_inter_op"])
    return choice
