"""`mkf study` on a real Dask cluster on this machine (scheduler and workers as separate processes
on 127.0.0.1): the same numbers as the local run, bit for bit; a worker killed mid-run loses
only its unit; a worker with other code is refused with one line."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from mkf_ros import parallel
from mkf_ros.cli.main import main
from mkf_ros.study import config as cfg
from mkf_ros.study import runner

pytestmark = pytest.mark.slow

# 8 cells over two rates; N_S = 10 gives 2 units per rate
SEL = ["--filters", "mekf,mukf", "--charts", "rp", "--updates", "cu,reset", "--R", "1e-4",
       "--rates", "100,500", "--no-progress", "--no-report"]
N_S = 10


def _parts(out: Path) -> dict[str, dict[str, np.ndarray]]:
    res = {}
    for p in sorted((out / runner.PARTS).glob("*.npz")):
        with np.load(p) as z:
            res[p.name] = {k: z[k] for k in z.files}
    return res


def assert_same_study(a: Path, b: Path) -> None:
    """Same cells.csv text and the same per-trajectory arrays, bit for bit."""
    assert (a / runner.CSV_NAME).read_text() == (b / runner.CSV_NAME).read_text()
    pa, pb = _parts(a), _parts(b)
    assert pa.keys() == pb.keys()
    for name in pa:
        assert pa[name].keys() == pb[name].keys()
        for k in pa[name]:
            assert np.array_equal(pa[name][k], pb[name][k]), (name, k)
    assert not list(a.rglob("*.tmp*")) and not list(b.rglob("*.tmp*"))


def test_study_on_the_cluster_equals_the_local_run(
        dask_cluster: parallel.LocalCluster, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    local, dask = tmp_path / "local", tmp_path / "dask"
    assert main(["study", "--n-s", str(N_S), *SEL, "--workers", "2", "--out", str(local)]) == 0
    capsys.readouterr()
    assert main(["study", "--n-s", str(N_S), *SEL, "--scheduler", dask_cluster.address,
                 "--out", str(dask)]) == 0
    err = capsys.readouterr().err
    assert f"Dask cluster {dask_cluster.address} (2 worker threads)" in err
    assert "8/8 cells finished" in err
    assert len(list((dask / runner.PARTS).glob("*.npz"))) == 4
    assert_same_study(local, dask)
    # a re-run on the cluster finds everything done and changes nothing
    assert main(["study", "--n-s", str(N_S), *SEL, "--scheduler", dask_cluster.address,
                 "--out", str(dask)]) == 0
    assert "(8 before, 0 now)" in capsys.readouterr().err
    assert_same_study(local, dask)


def test_a_worker_killed_mid_run_loses_only_its_unit(tmp_path: Path) -> None:
    """SIGKILL the worker that is running a unit when the first result arrives: Dask runs the
    lost unit again on the other worker; the study completes with the local run's numbers."""
    cells = cfg.cells(["mekf", "mukf"], ["rp"], ["cu", "reset"], [1e-4], [1000.0])
    n_s = 15  # 3 units of about a second
    ref = tmp_path / "ref"
    runner.run_study(cells, n_s, 2, ref, workers=2, progress=False)

    killed: list[tuple[str, list]] = []
    with parallel.local_cluster(2, tmp_path / "cluster") as lc, \
            parallel.cluster(lc.address) as c:
        names = {a: w["name"] for a, w in c.client.scheduler_info()["workers"].items()}

        def kill_a_busy_worker(unit: runner.Unit) -> None:
            if killed:
                return
            busy = {a: ks for a, ks in c.client.processing().items() if ks}
            assert busy, "no unit running when the first one finished"
            addr, keys = sorted(busy.items())[0]
            lc.kill_worker(names[addr])
            killed.append((names[addr], keys))

        rep = runner.run_study(cells, n_s, 2, tmp_path / "dask", workers=c.threads,
                               progress=False, executor=c.executor, on_unit=kill_a_busy_worker)
    assert killed and killed[0][1], "no worker was killed while running a unit"
    assert not rep.interrupted and rep.pending == 0 and len(rep.finished) == len(cells)
    assert_same_study(ref, tmp_path / "dask")


def test_a_worker_with_other_code_is_refused(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    """A worker whose mkf_ros differs by one comment: `mkf study --scheduler` stops with one
    line before any unit runs, and a task sent to it anyway fails with the same reason."""
    import mkf_ros

    other = tmp_path / "other"
    shutil.copytree(Path(mkf_ros.__file__).parent, other / "mkf_ros",
                    ignore=shutil.ignore_patterns("__pycache__"))
    with open(other / "mkf_ros" / "parallel.py", "a") as f:
        f.write("# edited on this worker only\n")
    out = tmp_path / "s"
    with parallel.local_cluster(1, tmp_path / "cluster",
                                worker_env={"PYTHONPATH": str(other)}) as lc:
        rc = main(["study", "--n-s", "4", *SEL, "--scheduler", lc.address, "--out", str(out)])
        err = capsys.readouterr().err
        assert rc == 2, err
        lines = err.strip().splitlines()
        assert len(lines) == 1, err
        line = lines[0]
        assert "runs mkf_ros 0.1.0+src." in line and f"this client {parallel.code_version()}" \
            in line and "install the same mkf_ros on every worker" in line
        assert not list((out / runner.PARTS).glob("*.npz"))
        # a worker that joins after the connection check: every task checks again
        import distributed

        with distributed.Client(lc.address, set_as_default=False) as client:
            fut = client.submit(parallel.checked_call, parallel.code_version(), sum, [1, 2])
            with pytest.raises(parallel.VersionMismatch, match="a worker runs mkf_ros"):
                fut.result(timeout=60)


def test_unreachable_scheduler_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    import socket

    monkeypatch.setattr(parallel, "CONNECT_TIMEOUT_S", 2.0)

    with socket.socket() as s:  # a port on this machine with nobody listening
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    rc = main(["study", "--n-s", "4", *SEL, "--scheduler", f"tcp://127.0.0.1:{port}",
               "--out", str(tmp_path / "s")])
    err = capsys.readouterr().err
    assert rc == 2 and f"cannot connect to the Dask scheduler at tcp://127.0.0.1:{port}" in err
    assert len(err.strip().splitlines()) == 1, err


def test_without_dask_the_scheduler_option_is_one_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    import sys

    monkeypatch.setitem(sys.modules, "distributed", None)  # `import distributed` fails
    out = tmp_path / "s"
    rc = main(["study", "--n-s", "4", *SEL, "--scheduler", "tcp://127.0.0.1:8786", "--out",
               str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and err.strip().splitlines() == [
        "mkf study: error: --scheduler needs Dask, which is not installed: "
        f"{parallel.INSTALL_HINT}"], err
    assert not list((out / runner.PARTS).glob("*.npz"))
