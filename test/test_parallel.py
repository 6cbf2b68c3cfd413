"""The one submission loop (`run_in_order`) and the executors of `mkf_ros.parallel`: order,
at most `in_flight` units out, failures handed back, Ctrl-C cancels what is queued, local worker
processes stopped at once, the code version."""

from __future__ import annotations

import concurrent.futures as cf
import os
import re
import threading
import time

import pytest

from mkf_ros import parallel


class Recorder:
    """A thread pool that records how many calls were out at once and the submission order."""

    def __init__(self, workers: int) -> None:
        self.pool = cf.ThreadPoolExecutor(workers)
        self.lock = threading.Lock()
        self.out = 0
        self.max_out = 0
        self.submitted: list[int] = []

    def fn(self, x: int) -> int:
        time.sleep(0.002 * (x % 3))
        if x == 13:
            raise ValueError("unlucky")
        return x * x

    def executor(self) -> cf.Executor:
        rec = self

        class Ex(cf.Executor):
            def submit(self, fn, /, *args, **kw):  # type: ignore[no-untyped-def]
                with rec.lock:
                    rec.out += 1
                    rec.max_out = max(rec.max_out, rec.out)
                    rec.submitted.append(args[0])
                f = rec.pool.submit(fn, *args, **kw)
                f.add_done_callback(lambda _: rec._done())
                return f

        return Ex()

    def _done(self) -> None:
        with self.lock:
            self.out -= 1


def test_units_go_out_in_order_at_most_in_flight_and_every_result_comes_back() -> None:
    rec = Recorder(4)
    got: dict[int, int] = {}
    errors: list[tuple[int, BaseException]] = []
    items = list(range(30))

    def on_error(x: int, e: BaseException) -> bool:
        errors.append((x, e))
        return True

    parallel.run_in_order(rec.executor(), rec.fn, items, 3, got.__setitem__, on_error)
    assert rec.submitted == items  # the caller's order (longest first) is kept
    assert rec.max_out <= 3
    assert got == {x: x * x for x in items if x != 13}
    assert [x for x, _ in errors] == [13] and isinstance(errors[0][1], ValueError)


def test_a_failure_can_stop_the_submission_but_running_units_are_kept() -> None:
    rec = Recorder(2)
    got: list[int] = []
    parallel.run_in_order(rec.executor(), rec.fn, list(range(10, 40)), 4,
                          lambda x, r: got.append(x), lambda x, e: False)
    assert 13 not in got and max(rec.submitted) <= 13 + 4  # nothing submitted after the failure
    assert set(got) == set(rec.submitted) - {13}  # every submitted unit was awaited


def test_an_interrupt_in_the_parent_cancels_the_queued_units() -> None:
    gate = threading.Event()

    def unit(x: int) -> int:
        if x:
            gate.wait(30)  # the first unit returns at once, the others wait
        return x

    def stop(x: int, r: int) -> None:
        raise KeyboardInterrupt

    futures: list[cf.Future] = []
    with cf.ThreadPoolExecutor(1) as pool:
        class Ex(cf.Executor):
            def submit(self, fn, /, *args, **kw):  # type: ignore[no-untyped-def]
                futures.append(pool.submit(fn, *args, **kw))
                return futures[-1]

        try:
            with pytest.raises(KeyboardInterrupt):
                parallel.run_in_order(Ex(), unit, list(range(8)), 4, stop, lambda x, e: True)
        finally:
            gate.set()
    assert len(futures) == 4  # never more than in_flight out
    assert futures[0].result() == 0  # the finished one; [1] may have started already
    assert all(f.cancelled() for f in futures[2:])  # queued behind the running one: cancelled


def test_inline_executor_keeps_errors_but_lets_ctrl_c_through() -> None:
    ex = parallel.InlineExecutor()
    f = ex.submit(int, "x")
    assert isinstance(f.exception(), ValueError)
    assert ex.submit(pow, 2, 5).result() == 32

    def interrupted() -> None:
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        ex.submit(interrupted)


def _sleep_forever(_: int) -> int:
    time.sleep(600)
    return 0


def test_stop_now_terminates_local_workers_at_once() -> None:
    pool = parallel.local_pool(2)
    futs = [pool.submit(_sleep_forever, i) for i in range(2)]
    time.sleep(0.5)
    pids = list(pool._processes)  # type: ignore[attr-defined]
    parallel.stop_now(pool)  # returns (rather than waiting the 600 s of the running calls)
    for f in futs:
        assert f.done()
    for pid in pids:
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)


def test_broken_pools_and_lost_dask_workers_count_as_worker_loss() -> None:
    from concurrent.futures.process import BrokenProcessPool

    from distributed.scheduler import KilledWorker

    assert parallel.is_worker_loss(BrokenProcessPool("a child died"))
    assert parallel.is_worker_loss(KilledWorker("task", "tcp://127.0.0.1:1", 3))
    assert not parallel.is_worker_loss(ValueError("a bug in the unit"))


def test_code_version_names_the_package_version_and_its_sources() -> None:
    import mkf_ros

    v = parallel.code_version()
    assert v.startswith(f"{mkf_ros.__version__}+src.") and len(v.split(".")[-1]) == 12
    with pytest.raises(parallel.VersionMismatch, match=re.escape(f"the client {v[:-1]}X")):
        parallel.checked_call(v[:-1] + "X", sum, [1])
    assert parallel.checked_call(v, sum, [1, 2]) == 3


@pytest.mark.slow
def test_the_local_cluster_listens_on_127_0_0_1_only(
        dask_cluster: parallel.LocalCluster) -> None:
    """Scheduler, nannies, workers and dashboards: every listening socket of every process of
    the test cluster is on the loopback address."""
    import psutil

    procs = [psutil.Process(p.pid) for p in (dask_cluster.scheduler,
                                             *dask_cluster.workers.values())]
    procs += [c for p in procs for c in p.children(recursive=True)]
    listening = [c.laddr for p in procs for c in p.net_connections("inet")
                 if c.status == psutil.CONN_LISTEN]
    assert len(listening) >= 1 + 2 * 2  # scheduler + (nanny, worker) per worker at least
    assert {a.ip for a in listening} == {"127.0.0.1"}, listening


def test_ctrl_c_on_another_thread_stops_the_wait() -> None:
    """A Ctrl-C that the kernel hands to a thread other than the main one (any thread may take
    a process's signal) sets Python's flag, but only the main thread runs the handler, and a
    wait with no timeout is not woken by it: ``mkf study`` sat 4 min after Ctrl-C while no unit
    finished. ``run_in_order`` must raise KeyboardInterrupt while the running call is still
    running (it ends only when the test lets it)."""
    import signal

    release = threading.Event()
    started = threading.Event()
    finished = threading.Event()

    def slow(_: int) -> int:
        started.set()
        release.wait(10)
        finished.set()
        return 0

    # Python's Ctrl-C handler, whatever this process inherited (a background job: ignored)
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    with cf.ThreadPoolExecutor(1) as ex:
        def interrupt() -> None:
            started.wait(60)
            signal.pthread_kill(threading.get_ident(), signal.SIGINT)  # on this helper thread

        helper = threading.Thread(target=interrupt)
        helper.start()
        try:
            with pytest.raises(KeyboardInterrupt):
                parallel.run_in_order(ex, slow, [1], 1, lambda i, r: None, lambda i, e: False)
            assert not finished.is_set()  # the call was still running: the wait was cut short
        finally:
            release.set()
            helper.join()
            signal.signal(signal.SIGINT, old)
