"""What gets compiled, when, and how long it takes: the numba kernels of the filters.

How one kernel is compiled and where it is cached is :mod:`mkf_ros.core._jit`; this module decides
what is compiled and when:

* at install time, :func:`precompile` (``setup.py``'s ``build_py``, which ``pip install``,
  ``pip wheel`` and ``colcon build`` run; ``./run setup`` for an editable checkout) compiles the
  kernels of :data:`INSTALLED_ALGORITHMS` (the MEKF, the default) into the package
  (``mkf_ros/_kernels/``), from which each user's cache is seeded;
* at start-up, :func:`warmup` loads them (well under a second), or compiles them where the
  install-time compile did not run (:data:`FIRST_COMPILE_TIME`); the other algorithms' own
  kernels (the MUKF's update, the baselines') and the smoothers' loops (``estimate(...,
  smooth=...)``, :data:`INSTALLED_PARTS`) are compiled on their first use
  (:data:`FIRST_USE_COMPILE_TIME`), then cached like the rest.

The install-time compile runs :func:`compile_tasks` in processes of their own, side by side
(:func:`compile_jobs` at a time), then a check in a fresh process: :func:`warmup` on the
compiled cache, which loads everything and compiles whatever the tasks missed. Its cost on
both supported numba versions is in docs/estimator.md § Start-up
(``./run bench compile_time``).

``python -m mkf_ros.kernels`` compiles (or loads) every kernel, the study's too, and prints the
code version (a cluster worker's check, docs/study/cluster.md).
"""

from __future__ import annotations

import os
import resource
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mkf_ros.core import _jit

#: How long compiling the kernels takes where the install-time compile did not run
#: (``colcon build --symlink-install``, ``MKF_ROS_NO_PRECOMPILE=1``, a build environment whose
#: numba differs from the one at run time): the node's first start took 60 s on the 2-core
#: reference machine (``./run bench startup --installed --no-precompile``); the messages quote
#: it.
FIRST_COMPILE_TIME = "about a minute"
#: The algorithms whose kernels the install-time compile makes; the others' own kernels (the
#: MUKF's update, the baselines' update and conversions) are compiled on their first use
#: (:data:`FIRST_USE_COMPILE_TIME`), then loaded from the user cache like the rest.
INSTALLED_ALGORITHMS = ("mekf",)
#: What that first use costs (``./run bench compile_time``, its last columns).
FIRST_USE_COMPILE_TIME = "15-30 s"

#: The kernel families :func:`warmup` can prepare: :func:`mkf_ros.estimate`'s batch loop, its
#: smoothers (``smooth="rts"`` or ``"two-way"``), :class:`~mkf_ros.core.filter.AttitudeFilter`'s
#: step, and the streaming front end of the node and of ``mkf process``. They share the
#: filter's compile units (:mod:`.core._jit`).
WARMUP_PARTS = ("estimate", "smoother", "filter", "stream")
#: The parts the install-time compile makes: all but the smoothers, an option of the offline
#: front ends that the node never runs (their loops, the largest after the sensor step, are
#: compiled on their first use, as the other algorithms' kernels are).
INSTALLED_PARTS = ("estimate", "filter", "stream")


def warmup(parts: Sequence[str] = WARMUP_PARTS,
           algorithms: Sequence[str] = ("mekf", "mukf")) -> None:
    """Compile (or load from the kernel cache) the kernels of ``parts`` (default: all, see
    :data:`WARMUP_PARTS`) for ``algorithms`` (default: the MEKF and the MUKF), so that the
    first real sample is not delayed. Loading takes well under a second; compiling (no cache
    of this version, e.g. an install without the install-time compile) takes
    :data:`FIRST_COMPILE_TIME` for all parts, and an algorithm not in
    :data:`INSTALLED_ALGORITHMS` :data:`FIRST_USE_COMPILE_TIME` on its first use."""
    from mkf_ros.api import estimate
    from mkf_ros.core.filter import AttitudeFilter
    from mkf_ros.core.params import ALGORITHMS, BASELINE_ALGORITHMS
    from mkf_ros.stream.adapter import StreamAdapter

    unknown = [p for p in parts if p not in WARMUP_PARTS]
    if unknown:
        raise ValueError(f"warmup: unknown part(s) {unknown}; expected some of {WARMUP_PARTS}")
    unknown = [a for a in algorithms if a not in ALGORITHMS]
    if unknown:
        raise ValueError(f"warmup: unknown algorithm(s) {unknown}; expected some of "
                         f"{ALGORITHMS}")
    _jit.share_inliner_memo()  # in case anything is compiled here
    n = 4
    gyr = np.zeros((n, 3))
    acc = np.tile([0.0, 0.0, 9.81], (n, 1))
    mag = np.tile([0.0, 20.0, -40.0], (n, 1))
    for algo in algorithms:
        if "estimate" in parts:
            estimate(gyr, acc, mag, dt=0.01, algorithm=algo, estimate_gyro_bias=True)
        if "smoother" in parts and algo not in BASELINE_ALGORITHMS:  # the MKFs' smoothers
            estimate(gyr, acc, mag, dt=0.01, algorithm=algo, smooth="two-way")
        if "filter" in parts:
            f = AttitudeFilter(algorithm=algo, use_mag=True)
            for k in range(n):
                f.step(0.01, gyr[k], acc[k], mag[k])
            _ = f.quaternion
        if "stream" in parts:
            s = StreamAdapter(algorithm=algo, use_mag=True)
            for k in range(n):
                s.on_mag(1.0 + 0.01 * k, mag[k])
                s.on_imu(1.0 + 0.01 * k, gyr[k], acc[k])


def warmup_installed() -> None:
    """Load (or compile) what the install-time compile makes: the kernels of
    :data:`INSTALLED_PARTS` for :data:`INSTALLED_ALGORITHMS`, and the simulator's (``mkf
    synth``). The install's last step (:data:`CHECK`) runs it on the compiled cache; after
    it, this compiles nothing."""
    from mkf_ros.sim.motion import integrate

    warmup(INSTALLED_PARTS, algorithms=INSTALLED_ALGORITHMS)
    integrate(np.array([1.0, 0.0, 0.0, 0.0]), np.zeros((2, 3)), 0.01)


def warm_all() -> str:
    """Compile (or load) every kernel: the filters' (:func:`warmup`), the simulator's and the
    study's; returns the code version (:func:`mkf_ros.parallel.code_version`)."""
    from mkf_ros.core.params import ALGORITHMS
    from mkf_ros.parallel import code_version
    from mkf_ros.sim.motion import integrate
    from mkf_ros.study.runner import warm_up

    warmup(algorithms=ALGORITHMS)
    integrate(np.array([1.0, 0.0, 0.0, 0.0]), np.zeros((2, 3)), 0.01)
    warm_up()
    return code_version()


# --- the install-time compile ----------------------------------------------------------------
def _entry_calls(part: str) -> list[tuple[Any, tuple]]:
    """The compiled loops of ``part`` (:data:`WARMUP_PARTS`) with arguments of the types the
    front ends call them with. They take the filter's compile units as an array of addresses,
    so they compile without them (a zero table: they are compiled here, never run)."""
    from mkf_ros.core import filter as kf
    from mkf_ros.core import smoother as sm
    from mkf_ros.stream import kernel as sk

    table = np.zeros(len(kf.KERNEL_TABLE_ORDER), dtype=np.int64)
    arrays = kf.AttitudeFilter().kernel_arrays()
    v3, m33, rows = np.zeros(3), np.zeros((3, 3)), np.zeros((1, 3))
    if part == "estimate":
        return [(kf.run_batch, (table, *arrays, np.zeros(1), rows, rows, rows,
                                kf.new_batch_outputs(1)))]
    if part == "smoother":
        out = kf.new_batch_outputs(1)
        rec = kf.new_records(sm.RECORD, 1)
        q4, m133 = np.zeros((1, 4)), np.zeros((1, 3, 3))
        return [(sm.forward_recorded, (table, *arrays, np.zeros(1), rows, rows, rows, out, rec,
                                       0)),
                (sm.backward, (arrays.cfg, rec, 0, sm.new_smooth_outputs(1))),
                (sm.fuse_tilt_rows, (q4, np.zeros((1, 2)), q4, m133, m133, q4, m133))]
    if part == "filter":
        return [(kf.sensor_step, (table, *arrays, 0.0, v3, v3, v3)),
                (kf.world_output, (table, arrays.cfg, arrays.st, np.zeros(4), m33)),
                (kf.to_canonical_entry, (table, arrays.cfg, arrays.st)),
                (kf.from_canonical_entry, (table, arrays.cfg, arrays.st))]
    # "stream": the records of a StreamAdapter (mkf_ros.stream.adapter)
    npar, ts, acnt = kf.new_records(sk.NODE), kf.new_records(sk.STREAM), \
        kf.new_records(sk.ADAPTER_COUNTER_RECORD)
    return [(sk.run_events, (table, tuple(arrays), npar, ts, acnt, kf.new_records(sm.RECORD, 0),
                             np.zeros(4, dtype=np.int64), kf.new_records(sk.EVENT),
                             kf.new_records(sk.OUTPUT), 0, 1)),
            (sk.covariance_rows, (np.zeros((1, 9)), 0.0, np.zeros((0, 9)))),
            (sk.published_batch, (npar, np.zeros((1, 4)), np.zeros((1, 3, 3)),
                                  np.zeros(1, dtype=np.bool_)))]


def _units() -> dict[str, _jit.Unit]:
    import mkf_ros.api  # noqa: F401  (imports every module that defines a unit)

    return {f"{u.__module__}.{u.__qualname__}": u for u in _jit.UNITS}


#: The compiled loops of each :data:`WARMUP_PARTS` part and their compile CPU time on the
#: reference machine (``./run bench compile_time --tasks``; orders the tasks, the largest first).
_ENTRY_COSTS = {"estimate": 2.0, "smoother": 9.0, "filter": 1.4, "stream": 9.0}
#: The last step of the install-time compile, in a fresh process on the compiled cache.
CHECK = "check"
#: Tasks that compile in less CPU time than this (s, their costs) share one process: a process
#: of its own costs each about half a second of start-up (Python, NumPy, numba, the package)
#: and the compile of the small kernels they all call.
SMALL_TASK = 4.0


def _first_use_units() -> set:
    """The units in no kernel table of :data:`INSTALLED_ALGORITHMS`
    (:func:`~mkf_ros.core.filter.table_units`): the other algorithms' own (the MUKF's update,
    the baselines'), compiled on their first use."""
    from mkf_ros.core.filter import KERNEL_TABLE_ORDER, table_units
    from mkf_ros.core.params import ALGORITHMS

    installed = {u for a in INSTALLED_ALGORITHMS for u in table_units(ALGORITHMS.index(a))}
    return set(KERNEL_TABLE_ORDER) - installed


def compile_tasks() -> list[str]:
    """The install-time compile's tasks, independent of each other, the largest first (so that
    the processes end together): every :class:`~mkf_ros.core._jit.Unit`
    (``"unit:MODULE.NAME"``) and the compiled loops that take them (``"entries:PART"``,
    :func:`_entry_calls`, of :data:`INSTALLED_PARTS`); the small ones (:data:`SMALL_TASK`)
    together, as one task (their names separated by spaces). Each runs in a fresh process:
    sharing one across the large tasks saves no time (a kernel two tasks call is loaded from
    the cache by the second) and keeps every compiled library in memory."""
    first_use = _first_use_units()
    costs = {f"unit:{name}": u.cost for name, u in _units().items() if u not in first_use}
    costs.update({f"entries:{part}": c for part, c in _ENTRY_COSTS.items()
                  if part in INSTALLED_PARTS})
    small = sorted(t for t, c in costs.items() if c < SMALL_TASK)
    if len(small) > 1:
        costs[" ".join(small)] = sum(costs.pop(t) for t in small)
    return sorted(costs, key=lambda t: -costs[t])


#: The compiling processes' garbage collector: objects that survive this many allocations are
#: checked for cycles (Python's default: 700). numba's compiler allocates millions of small
#: objects (it copies a function's IR for every call it inlines), which the default makes the
#: collector scan over and over: about a sixth of a unit's compile CPU time, measured.
COMPILE_GC_THRESHOLD = 20000


#: Set in a compiling process once its task has succeeded (:func:`_exit_at_once`).
_TASK_DONE: list[bool] = []


def _exit_at_once() -> None:
    """At the exit of a compiling process whose task succeeded: end it here (``os._exit``),
    without the interpreter's teardown, which frees every object the compiler left, one by
    one (about a quarter of a CPU-second per process, measured). Its result has been sent
    (the pool's result queue writes to the pipe before the worker returns) and its kernels
    written to the cache; a failed task exits the usual way, with its exit status."""
    if _TASK_DONE:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)


def _compiler_process() -> None:
    """Set up a process of the install-time compile: the package imported, its objects left
    out of the garbage collector's scans (:func:`gc.freeze`), the collector run less often
    (:data:`COMPILE_GC_THRESHOLD`), and the process ended without the interpreter's teardown
    once its task has succeeded (:func:`_exit_at_once`); no effect on what is compiled."""
    import atexit
    import gc

    _units()
    _jit.share_inliner_memo()
    gc.freeze()
    gc.set_threshold(COMPILE_GC_THRESHOLD, 10, 10)
    atexit.register(_exit_at_once)


def run_compile_task(task: str) -> tuple[str, float, float, int]:
    """One task of :func:`compile_tasks` (or :data:`CHECK`: :func:`warmup_installed`; several,
    separated by spaces, one after the other) in this process: ``(task, wall s, CPU s, peak RSS
    of this process in KiB)``."""
    t0, c0 = time.perf_counter(), time.process_time()
    for part in task.split():
        kind, _, name = part.partition(":")
        if kind == "unit":
            _ = _units()[name].compiled
        elif kind == "entries":
            if not _jit.JIT_DISABLED:
                import numba

                for dispatcher, args in _entry_calls(name):
                    dispatcher.compile(tuple(numba.typeof(a) for a in args))
        elif part == CHECK:
            warmup_installed()
        else:
            raise ValueError(f"unknown compile task {part!r}")
    _TASK_DONE.append(True)
    return (task, time.perf_counter() - t0, time.process_time() - c0,
            resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)


def compile_jobs() -> int:
    """Processes of the install-time compile: ``$MKF_ROS_COMPILE_JOBS``, else the CPUs this
    process may use, at most 2 (each takes up to ~0.7 GB)."""
    env = os.environ.get("MKF_ROS_COMPILE_JOBS", "")
    if env.strip().isdigit() and int(env) > 0:
        return int(env)
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover (not Linux)
        n = os.cpu_count() or 1
    return max(1, min(2, n))


def precompile(root: Path, jobs: int | None = None,
               report: Callable[[tuple[str, float, float, int]], object] | None = None) -> None:
    """Compile the install's kernels into ``root/numba-<hash>/`` (the install-time step; see the
    module docstring), dropping other kernel versions there: :func:`compile_tasks`, each in a fresh
    process whose cache is ``root``, ``jobs`` at a time (:func:`compile_jobs`), then
    :data:`CHECK` in another. ``report`` receives each task's result (:func:`run_compile_task`)."""
    import concurrent.futures
    import multiprocessing

    jobs = jobs or compile_jobs()
    saved = {k: os.environ.get(k) for k in ("MKF_ROS_CACHE_DIR", "PYTHONWARNINGS")}
    os.environ.update(MKF_ROS_CACHE_DIR=str(root), PYTHONWARNINGS="ignore")
    try:
        for phase, workers in ((compile_tasks(), jobs), ([CHECK], 1)):
            with concurrent.futures.ProcessPoolExecutor(
                    max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                    max_tasks_per_child=1, initializer=_compiler_process) as pool:
                for result in pool.map(run_compile_task, phase):
                    if report is not None:
                        report(result)
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    _jit.prune_old_caches(root, keep_days=0.0)


if __name__ == "__main__":  # pragma: no cover - run by hand on cluster workers
    print(f"mkf_ros {warm_all()}: kernels ready")
