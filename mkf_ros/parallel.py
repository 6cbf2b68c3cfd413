"""Where work units run: this machine's processes or a Dask cluster, behind one interface.

``mkf study`` and ``mkf process`` (several bags) hand their work units to a
:class:`concurrent.futures.Executor` and consume the results in the parent, which stays the only
writer of the study's files:

* :func:`local_pool` — worker processes on this machine (forked, so kernels compiled in the parent
  are inherited; they ignore Ctrl-C, which the parent handles);
* :class:`InlineExecutor` — one worker: the unit runs in the parent when it is submitted;
* :func:`connect` — a Dask cluster (``distributed.Client(address).get_executor()``), after
  checking that every worker runs the same mkf_ros as this process (:func:`code_version`); every
  task checks it again, so a worker that joins later with other code fails its task with a clear
  error instead of returning other numbers.

:func:`run_in_order` is the one submission loop: units go out in the given order (longest first),
at most ``in_flight`` at a time, and each result is handed to the caller as it arrives.

Dask (``pip install 'mkf_ros[cluster]'``) is imported only by :func:`connect`; nothing else here
needs it. ``python -m mkf_ros.kernels`` compiles (or loads) every kernel and prints the code
version: run it once on each worker machine (see ``docs/study/cluster.md``).
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import hashlib
import multiprocessing as mp
import signal
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")
R = TypeVar("R")

INSTALL_HINT = "pip install 'mkf_ros[cluster]' (Dask distributed)"
#: seconds to wait for the scheduler and for its first worker
CONNECT_TIMEOUT_S = 30.0


class ClusterError(Exception):
    """The cluster cannot be used (not reachable, no workers, other code): one line."""


class VersionMismatch(ClusterError):
    """A worker runs another mkf_ros than the client."""


# --------------------------------------------------------------------------- code version
@lru_cache(maxsize=1)
def code_version() -> str:
    """``mkf_ros`` version and a digest of its Python sources, e.g. ``0.1.0+src.1a2b3c4d5e6f``.

    Equal on two machines when they run the same package code (editable, wheel or colcon
    install alike); any edit of any module changes it, so the cluster never mixes code.
    """
    from mkf_ros._version import __version__

    root = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(path.relative_to(root).as_posix().encode() + b"\0")
        h.update(path.read_bytes())
    return f"{__version__}+src.{h.hexdigest()[:12]}"


def checked_call(expected: str, fn: Callable[..., R], *args: Any) -> R:
    """Run ``fn(*args)`` after checking that this process runs mkf_ros ``expected``."""
    mine = code_version()
    if mine != expected:
        raise VersionMismatch(f"a worker runs mkf_ros {mine}, the client {expected}: install "
                              "the same mkf_ros on every worker (docs/study/cluster.md)")
    return fn(*args)


# --------------------------------------------------------------------------- executors
class InlineExecutor(cf.Executor):
    """Runs each call in the caller when it is submitted (one worker, no processes).

    Exceptions of the call are stored in its future, except ``KeyboardInterrupt`` (and other
    non-``Exception`` errors), which propagate at once, as in a plain loop.
    """

    def submit(self, fn: Callable[..., R], /, *args: Any, **kwargs: Any) -> cf.Future[R]:
        f: cf.Future[R] = cf.Future()
        try:
            f.set_result(fn(*args, **kwargs))
        except Exception as e:
            f.set_exception(e)
        return f


def cores() -> int:
    """CPU cores this process may use."""
    import os

    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def local_pool(workers: int) -> cf.ProcessPoolExecutor:
    """``workers`` forked processes that ignore Ctrl-C (the parent stops them)."""
    return cf.ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("fork"),
                                  initializer=_ignore_sigint)


class WorkerDied(Exception):
    """A unit's process ended without a result (a crash: a signal such as SIGSEGV or SIGKILL
    from the out-of-memory killer, or ``os._exit``)."""


class ForkPerUnit(cf.Executor):
    """Each call in a forked process of its own, at most ``workers`` at a time.

    A call that kills its process (a segfault in native code, ``os._exit``, the OOM killer)
    fails only its own future, with :class:`WorkerDied` naming the signal or exit code; the
    other calls go on (a :class:`~concurrent.futures.ProcessPoolExecutor` is broken by one dead
    worker and fails every call in it). The children inherit the parent's memory (kernels
    compiled there) and ignore Ctrl-C; results and exceptions come back pickled. One waiting
    thread per call in flight.
    """

    def __init__(self, workers: int) -> None:
        import threading

        self._slots = threading.BoundedSemaphore(max(1, workers))
        self._lock = threading.Lock()
        self._procs: set[Any] = set()
        self._threads: list[Any] = []
        self._stopped = False

    def submit(self, fn: Callable[..., R], /, *args: Any, **kwargs: Any) -> cf.Future[R]:
        import threading

        if self._stopped:
            raise RuntimeError("cannot submit after shutdown")
        f: cf.Future[R] = cf.Future()
        t = threading.Thread(target=self._run, args=(f, fn, args, kwargs), daemon=True)
        self._threads.append(t)
        t.start()
        return f

    def _run(self, f: cf.Future, fn: Callable[..., Any], args: tuple, kwargs: dict) -> None:
        with self._slots:
            if self._stopped or not f.set_running_or_notify_cancel():
                return
            ctx = mp.get_context("fork")
            recv, send = ctx.Pipe(duplex=False)
            p = ctx.Process(target=_unit_child, args=(send, fn, args, kwargs), daemon=True)
            with self._lock:
                p.start()
                self._procs.add(p)
            send.close()
            try:
                kind, value = recv.recv()
            except (EOFError, OSError):
                kind, value = "died", None
            finally:
                recv.close()
            p.join()
            with self._lock:
                self._procs.discard(p)
            if kind == "ok":
                f.set_result(value)
            elif kind == "err":
                f.set_exception(value)
            else:
                f.set_exception(WorkerDied(_death(p.exitcode)))

    def terminate(self) -> None:
        """Kill the running units' processes (their futures fail with WorkerDied)."""
        self._stopped = True
        with self._lock:
            for p in list(self._procs):
                with contextlib.suppress(Exception):
                    p.terminate()

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self._stopped = self._stopped or cancel_futures
        if wait:
            for t in self._threads:
                t.join()


def _unit_child(send: Any, fn: Callable[..., Any], args: tuple, kwargs: dict) -> None:
    """In the forked process: run the unit, send ("ok", result) or ("err", exception)."""
    _ignore_sigint()
    try:
        msg: tuple[str, Any] = ("ok", fn(*args, **kwargs))
    except BaseException as e:  # sent to the parent, which raises it there
        msg = ("err", e)
    try:
        send.send(msg)
    except Exception as e:  # an unpicklable result or exception: its text
        send.send(("err", RuntimeError(f"{type(msg[1]).__name__}: {msg[1]} (cannot be sent "
                                       f"back: {e})")))
    send.close()


def _death(code: int | None) -> str:
    """One line for how a unit's process ended without a result."""
    if code is not None and code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        hint = " (out of memory?)" if -code == signal.SIGKILL else ""
        return f"its worker process was killed by {name}{hint}"
    return f"its worker process exited with code {code} without a result"


def stop_now(executor: cf.Executor) -> None:
    """Stop ``executor`` without waiting for running calls (after Ctrl-C or an error): local
    worker processes are terminated; on a cluster the queued and running tasks are cancelled."""
    if isinstance(executor, ForkPerUnit):
        executor.terminate()
        executor.shutdown(wait=True, cancel_futures=True)
    elif isinstance(executor, cf.ProcessPoolExecutor):
        terminate = getattr(executor, "terminate_workers", None)  # Python >= 3.14
        if terminate is not None:
            terminate()
        else:
            for p in list((getattr(executor, "_processes", None) or {}).values()):
                with contextlib.suppress(Exception):
                    p.terminate()
        executor.shutdown(wait=True, cancel_futures=True)
    else:
        executor.shutdown(wait=False)


def is_worker_loss(e: BaseException) -> bool:
    """True for the errors of a worker that died or vanished (not of the task's own code)."""
    if isinstance(e, (cf.BrokenExecutor, WorkerDied)):
        return True
    return type(e).__name__ in ("KilledWorker", "CommClosedError", "FutureCancelledError")


#: How often :func:`run_in_order` wakes while it waits for calls (s): the latency of Ctrl-C.
WAIT_POLL_S = 0.2


def run_in_order(executor: cf.Executor, fn: Callable[[T], R], items: Iterable[T],
                 in_flight: int, on_result: Callable[[T, R], None],
                 on_error: Callable[[T, BaseException], bool]) -> None:
    """Submit ``fn(item)`` for ``items`` in their order, at most ``in_flight`` at a time, and
    call ``on_result(item, result)`` in this thread as each one finishes.

    A failed call (or a failed submission: a broken pool) goes to ``on_error(item, error)``;
    it returns whether to go on submitting (the calls already running are still awaited).
    Whatever the callbacks raise (e.g. ``KeyboardInterrupt``) cancels the calls not yet
    finished and propagates; the caller owns ``executor`` and stops it.
    """
    queue = iter(items)
    running: dict[cf.Future[R], T] = {}
    go_on = True

    def fill() -> None:
        nonlocal go_on
        while go_on and len(running) < max(1, in_flight):
            try:
                item = next(queue)
            except StopIteration:
                return
            try:
                running[executor.submit(fn, item)] = item
            except Exception as e:
                go_on = on_error(item, e)

    try:
        fill()
        while running:
            # woken at least every WAIT_POLL_S: CPython runs a signal's handler only in the
            # main thread, and a Ctrl-C that the kernel delivered to another thread (the
            # pool's) does not end a wait with no timeout; while no call finishes (workers
            # still compiling, or stuck), Ctrl-C was then never seen
            done, _ = cf.wait(running, timeout=WAIT_POLL_S, return_when=cf.FIRST_COMPLETED)
            for f in [f for f in running if f in done]:  # in submission order
                item = running.pop(f)
                try:
                    res = f.result()
                except Exception as e:
                    go_on = on_error(item, e) and go_on
                    continue
                on_result(item, res)
            fill()
    finally:
        for f in running:
            f.cancel()


# --------------------------------------------------------------------------- Dask
@dataclass
class Cluster:
    """A connected Dask client, its executor (version-checked) and its number of threads."""

    address: str
    client: Any
    executor: cf.Executor
    threads: int

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.executor.shutdown(wait=False)
        with contextlib.suppress(Exception):
            self.client.close()


class CheckedExecutor(cf.Executor):
    """Wraps a Dask executor: every call first checks the worker's :func:`code_version`."""

    def __init__(self, inner: cf.Executor) -> None:
        self.inner = inner
        self.version = code_version()

    def submit(self, fn: Callable[..., R], /, *args: Any, **kwargs: Any) -> cf.Future[R]:
        if kwargs:
            raise TypeError("keyword arguments are not forwarded to the cluster")
        return self.inner.submit(checked_call, self.version, fn, *args)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self.inner.shutdown(wait=wait)


def connect(address: str, timeout: float | None = None) -> Cluster:
    """Connect to the Dask scheduler at ``address`` (``tcp://HOST:8786``), wait for a worker
    (``timeout`` s each, default :data:`CONNECT_TIMEOUT_S`), and check that every worker runs
    this mkf_ros (:class:`ClusterError` otherwise)."""
    timeout = CONNECT_TIMEOUT_S if timeout is None else timeout
    try:
        import distributed
    except ImportError:
        raise ClusterError(f"--scheduler needs Dask, which is not installed: {INSTALL_HINT}") \
            from None
    try:
        client = distributed.Client(address, timeout=timeout, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as e:
        raise ClusterError(f"cannot connect to the Dask scheduler at {address}: "
                           f"{str(e).splitlines()[0] if str(e) else type(e).__name__}") from None
    try:
        try:
            client.wait_for_workers(1, timeout=timeout)
        except TimeoutError:
            raise ClusterError(f"the Dask scheduler at {address} has no worker (waited "
                               f"{timeout:g} s); start some with: dask worker {address} "
                               "--nthreads 1 --nworkers auto") from None
        try:
            versions = client.run(code_version)
        except Exception as e:
            raise ClusterError(f"a worker of {address} cannot run mkf_ros ({type(e).__name__}: "
                               f"{e}); install the same environment on every worker") from None
        mine = code_version()
        bad = {w: v for w, v in sorted(versions.items()) if v != mine}
        if bad:
            w, v = next(iter(bad.items()))
            more = f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""
            raise VersionMismatch(f"worker {w}{more} runs mkf_ros {v}, this client {mine}: "
                                  "install the same mkf_ros on every worker "
                                  "(docs/study/cluster.md)")
        threads = sum(client.nthreads().values())
        executor = CheckedExecutor(client.get_executor(pure=False))
    except BaseException:
        client.close()
        raise
    return Cluster(address, client, executor, threads)


@contextlib.contextmanager
def cluster(address: str, timeout: float | None = None) -> Iterator[Cluster]:
    """:func:`connect`, closed afterwards."""
    c = connect(address, timeout)
    try:
        yield c
    finally:
        c.close()


@dataclass
class LocalCluster:
    """A Dask scheduler and workers started as separate processes on 127.0.0.1 (tests and
    benchmarks: a real cluster, on this machine only)."""

    address: str
    scheduler: Any  #: subprocess.Popen
    workers: dict[str, Any]  #: name -> subprocess.Popen (each the leader of its own session)

    def kill_worker(self, name: str) -> None:
        """SIGKILL one worker (nanny and worker process), as a machine that dies."""
        import os

        p = self.workers[name]
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGKILL)
        p.wait(timeout=30)


@contextlib.contextmanager
def local_cluster(n_workers: int, directory: str | Path, *, timeout: float = 120.0,
                  worker_env: dict[str, str] | None = None) -> Iterator[LocalCluster]:
    """``dask scheduler`` and ``n_workers`` × ``dask worker --nthreads 1`` on 127.0.0.1 (every
    port, dashboards included), logs in ``directory``; every process is killed on exit. Returns
    once all workers are registered (``TimeoutError`` after ``timeout`` s)."""
    import os
    import subprocess
    import sys
    import time

    import distributed

    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    sfile = d / "scheduler.json"
    sfile.unlink(missing_ok=True)
    local = ["--host", "127.0.0.1", "--dashboard-address", "127.0.0.1:0"]
    procs: list[subprocess.Popen] = []

    def start(args: list[str], log: str, env: dict[str, str] | None = None) -> Any:
        with open(d / log, "wb") as f:
            p = subprocess.Popen([sys.executable, "-m", "dask", *args], stdout=f,
                                 stderr=subprocess.STDOUT, start_new_session=True,
                                 env=dict(os.environ, **(env or {})), cwd=d)
        procs.append(p)
        return p

    try:
        sched = start(["scheduler", *local, "--port", "0", "--scheduler-file", str(sfile),
                       "--idle-timeout", "3600"], "scheduler.log")
        deadline = time.monotonic() + timeout
        address = ""
        while not address:
            if sched.poll() is not None or time.monotonic() > deadline:
                raise TimeoutError(f"dask scheduler did not start (log: {d / 'scheduler.log'})")
            with contextlib.suppress(OSError, ValueError, KeyError):
                import json

                address = json.loads(sfile.read_text())["address"]
            time.sleep(0.1)
        workers = {}
        for i in range(n_workers):
            name = f"w{i}"
            workers[name] = start(["worker", "--scheduler-file", str(sfile), *local,
                                   "--nthreads", "1", "--name", name, "--local-directory",
                                   str(d / name), "--death-timeout", "120"],
                                  f"{name}.log", worker_env)
        with distributed.Client(address, timeout=timeout, set_as_default=False) as c:
            c.wait_for_workers(n_workers, timeout=max(1.0, deadline - time.monotonic()))
        yield LocalCluster(address, sched, workers)
    finally:
        for p in reversed(procs):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGTERM)
        for p in reversed(procs):
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)
                p.wait(timeout=10)
