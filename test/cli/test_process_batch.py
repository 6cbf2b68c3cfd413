"""``mkf process`` over many bags (``--jobs``, ``--scheduler``): every output bag is the one the
one-bag command writes, message for message; a bad bag is reported and the others finish; a bag
that fails while being written leaves nothing behind; the same bags on a real Dask cluster give
the same bytes; without Dask, ``--scheduler`` is one line."""

from __future__ import annotations

import csv
import errno
import re
import sys
from pathlib import Path

import pytest

from mkf_ros import parallel
from mkf_ros.bags import BagReader
from mkf_ros.bags.synth import write_bag
from mkf_ros.bags.writer import BagWriter
from mkf_ros.cli.main import main
from mkf_ros.sim import simulate

# name below the input folder, scenario, storage
BAGS = [("sub0/b0", "slow_rotation", "mcap"), ("sub1/b1", "accel_bursts", "sqlite3"),
        ("sub0/b2", "slow_rotation", "mcap")]
OPTS = ["--use-mag", "--quiet"]


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder of three synthetic bags (with ground truth) in two sub-folders, and a truncated
    .mcap file that cannot be read."""
    root = tmp_path_factory.mktemp("bags") / "in"
    for i, (name, scenario, storage) in enumerate(BAGS):
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        write_bag(simulate(scenario, duration=5.0, rate=100.0, mag_rate=25.0, seed=i),
                  root / name, storage)
    good = next((root / "sub0/b0").glob("*.mcap")).read_bytes()
    (root / "sub1/trunc.mcap").write_bytes(good[: len(good) // 2])
    return root


def messages(bag: Path) -> list[tuple[str, int, bytes]]:
    """Every message of a bag: (topic, log time, CDR bytes), in log-time order."""
    with BagReader(bag) as br:
        return list(br.messages())


def one_by_one(bags: Path, ref: Path, capsys: pytest.CaptureFixture[str]
               ) -> dict[str, dict[str, float]]:
    """Each good bag through the one-bag ``mkf process``; the printed RMSEs per bag."""
    printed = {}
    for name, _, _ in BAGS:
        (ref / name).parent.mkdir(parents=True, exist_ok=True)
        assert main(["process", str(bags / name), "--out", str(ref / name), *OPTS,
                     "--no-plot"]) == 0
        m = re.search(r"total\s+([\d.]+)\s+heading\s+([\d.]+)\s+inclination\s+([\d.]+)",
                      capsys.readouterr().out)
        assert m
        printed[name] = dict(zip(("total", "heading", "inclination"), map(float, m.groups()),
                                 strict=True))
    return printed


def no_partial(folder: Path) -> None:
    assert not [p for p in folder.rglob("*") if ".partial-" in p.name]


def test_many_bags_equal_one_by_one_and_a_bad_bag_is_reported(
        bags: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ref = tmp_path / "ref"
    rmse = one_by_one(bags, ref, capsys)
    out = tmp_path / "out"
    rc = main(["process", str(bags), "--out", str(out), "--jobs", "2", *OPTS])
    text = capsys.readouterr().out
    assert rc == 1, text  # one bag failed
    for name, _, _ in BAGS:
        assert messages(out / name) == messages(ref / name), name
        assert (out / f"{name}.png").read_bytes()[:4] == b"\x89PNG"
    assert not (out / "sub1/trunc").exists() and not (out / "sub1/trunc.png").exists()
    no_partial(out)
    assert re.search(r"^sub1/trunc\s+FAILED .*cannot read bag .*trunc\.mcap: truncated", text,
                     re.M), text
    assert "4 bags: 3 processed, 1 failed" in text
    with open(out / "summary.csv") as f:
        rows = {r["bag"]: r for r in csv.DictReader(f)}
    assert sorted(rows) == sorted([n for n, _, _ in BAGS] + ["sub1/trunc"])
    assert rows["sub1/trunc"]["ok"] == "0" and "truncated" in rows["sub1/trunc"]["error"]
    for name, _, _ in BAGS:
        r = rows[name]
        assert r["ok"] == "1" and int(r["imu_msgs"]) == 501 and int(r["outputs"]) == 501
        for k, v in rmse[name].items():  # the one-bag command's scores
            assert float(r[f"rmse_{k}_deg"]) == pytest.approx(v, abs=6e-4), (name, k)
        line = re.search(rf"^{name}\s.*$", text, re.M)
        assert line and f"{rmse[name]['total']:.3f}" in line.group(0)
    assert "acc_implausible" in rows["sub1/b1"]["events"]  # the accelerometer bursts


def test_a_bag_failing_while_written_leaves_no_output(
        bags: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """The disk fills up while b1 is written (the forked workers inherit the patch): b1 is
    reported with the reason, nothing of it is left, the other bags are whole."""
    real = BagWriter.write_batch

    def full_disk(self: BagWriter, *a: object) -> None:
        real(self, *a)
        if self.path.name == "b1":
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(BagWriter, "write_batch", full_disk)
    out = tmp_path / "out"
    rc = main(["process", str(bags / "sub0/b0"), str(bags / "sub1/b1"), "--out", str(out),
               "--jobs", "2", "--no-plot", *OPTS])
    text = capsys.readouterr().out
    assert rc == 1
    assert re.search(r"^b1\s+FAILED .*No space left on device", text, re.M), text
    assert not (out / "b1").exists()
    no_partial(out)
    monkeypatch.setattr(BagWriter, "write_batch", real)
    assert main(["process", str(bags / "sub0/b0"), "--out", str(tmp_path / "ref"),
                 "--no-plot", *OPTS]) == 0
    assert messages(out / "b0") == messages(tmp_path / "ref")


@pytest.mark.parametrize("crash", ["segfault", "exit"])
def test_a_bag_that_crashes_its_worker_fails_alone(
        bags: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str], crash: str) -> None:
    """b1's worker process dies (SIGSEGV, as a crash in native code, or os._exit) while the
    other bags are running and queued (the forked workers inherit the patch): b1 is one
    FAILED line with the reason, b0 and b2 are the one-bag command's outputs, exit code 1."""
    import os
    import signal

    import mkf_ros.bags.process as proc

    real = proc.process_bag

    def crashing(bag: str, out: str, *a: object, **kw: object) -> object:
        if Path(bag).name == "b1":
            if crash == "segfault":
                os.kill(os.getpid(), signal.SIGSEGV)
            os._exit(3)
        return real(bag, out, *a, **kw)  # type: ignore[arg-type]

    ref = tmp_path / "ref"
    one_by_one(bags, ref, capsys)
    monkeypatch.setattr(proc, "process_bag", crashing)
    out = tmp_path / "out"
    rc = main(["process", *(str(bags / n) for n, _, _ in BAGS), "--out", str(out),
               "--jobs", "2", "--no-plot", *OPTS])
    text = capsys.readouterr().out
    assert rc == 1, text
    why = ("killed by SIGSEGV" if crash == "segfault" else "exited with code 3 without a result")
    assert re.search(rf"^b1\s+FAILED .*its worker process (was )?{why}$", text, re.M), text
    assert "3 bags: 2 processed, 1 failed" in text
    for name in ("b0", "b2"):
        assert messages(out / name) == messages(ref / f"sub0/{name}"), name
    assert not (out / "b1").exists()
    no_partial(out)


def test_help_names_the_batch_options(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        main(["process", "--help"])
    text = capsys.readouterr().out
    assert e.value.code == 0
    assert "--jobs N" in text and "--scheduler ADDRESS" in text
    assert "10-25 % from" in " ".join(text.split())


def test_bad_batch_arguments_are_one_line(bags: Path, tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    def fails(argv: list[str], pattern: str) -> None:
        assert main(["process", *argv]) == 2
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and re.search(pattern, lines[0]), lines

    b0, b2 = str(bags / "sub0/b0"), str(bags / "sub0/b2")
    out = str(tmp_path / "o")
    fails([b0, b2, "--out", out, "--jobs", "0"], r"--jobs must be at least 1, got 0")
    fails([b0, str(bags / "sub0/../sub0/b0"), "--out", out], r"would both be written as b0")
    fails([b0, b2, "--out", str(bags / "sub0/b0")], r"is a bag; with several bags it must be")
    fails([b0, b2, "--out", str(bags / "sub0")], r"would write .*b0 over or into the input")
    assert not (tmp_path / "o").exists()


def test_without_dask_the_scheduler_option_is_one_line(
        bags: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setitem(sys.modules, "distributed", None)  # `import distributed` fails
    rc = main(["process", str(bags / "sub0/b0"), str(bags / "sub0/b2"), "--out",
               str(tmp_path / "o"), "--scheduler", "tcp://127.0.0.1:8786", *OPTS])
    err = capsys.readouterr().err
    assert rc == 2 and err.strip().splitlines() == [
        "mkf process: error: --scheduler needs Dask, which is not installed: "
        f"{parallel.INSTALL_HINT}"], err
    assert not list((tmp_path / "o").rglob("b*"))


@pytest.mark.slow
def test_many_bags_on_the_cluster_equal_the_local_run(
        dask_cluster: parallel.LocalCluster, bags: Path, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    local, dask = tmp_path / "local", tmp_path / "dask"
    assert main(["process", str(bags), "--out", str(local), "--jobs", "1", "--no-plot",
                 *OPTS]) == 1
    capsys.readouterr()
    assert main(["process", str(bags), "--out", str(dask), "--scheduler",
                 dask_cluster.address, "--no-plot", *OPTS]) == 1
    captured = capsys.readouterr()
    assert f"4 bags, Dask cluster {dask_cluster.address} (2 worker threads)" in captured.err
    for name, _, _ in BAGS:
        assert messages(dask / name) == messages(local / name), name
    no_partial(dask)

    def rows(out: Path) -> list[dict[str, str]]:  # all but the run time and the output path
        with open(out / "summary.csv") as f:
            return [{k: v for k, v in r.items() if k not in ("seconds", "output")}
                    for r in csv.DictReader(f)]

    assert rows(dask) == rows(local) and len(rows(local)) == 4
