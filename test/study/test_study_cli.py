"""`mkf study` from the command line: a tiny end-to-end run and the one-line errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from mkf_ros.cli.main import main

TINY = ["--filters", "mekf", "--charts", "rp", "--updates", "cu", "--R", "1e-4",
        "--rates", "50", "--no-progress", "--workers", "1"]


def test_end_to_end_with_report(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "s"
    docs = tmp_path / "docs"
    rc = main(["study", "--n-s", "3", *TINY, "--out", str(out), "--no-speed",
               "--docs", str(docs)])
    assert rc == 0, capsys.readouterr().err
    for p in ("cells.csv", "summary.md", "study.json", "figures/fig5_charts.png",
              "figures/fig6_mekf_vs_mukf.png"):
        assert (out / p).is_file(), p
    assert (docs / "README.md").read_text() == (out / "summary.md").read_text()
    assert (docs / "figures" / "fig5_charts.png").is_file()
    text = (out / "summary.md").read_text()
    assert "mkf study --n-s 3" in text and "## The paper's three questions" in text
    # report-only rebuilds from the folder
    assert main(["study", "--report-only", "--out", str(out), "--no-speed"]) == 0


@pytest.mark.parametrize("args, needle", [
    (["--filters", "ekf"], "unknown filter 'ekf'"),
    (["--charts", "rp,xyz"], "unknown chart 'xyz'"),
    (["--rates", "0"], "rate must be positive"),
    (["--rates", "-5"], "rate must be positive"),
    (["--rates", "abc"], "rate must be a number"),
    (["--n-s", "1"], "--n-s must be at least 2"),
    (["--R", "0"], "R must be positive"),
    (["--mukf-scaling", "wrong"], "unknown MUKF scaling"),
])
def test_bad_input_is_one_line_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                      args: list[str], needle: str) -> None:
    rc = main(["study", *TINY, "--out", str(tmp_path / "o"), *args])
    err = capsys.readouterr().err
    assert rc == 2
    assert needle in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "o" / "cells.csv").exists()


def test_unwritable_output_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    rc = main(["study", "--n-s", "2", *TINY, "--out", str(blocker / "out")])
    err = capsys.readouterr().err
    assert rc == 2 and "cannot write to output folder" in err
    assert len(err.strip().splitlines()) == 1, err


def test_ctrl_c_keeps_finished_units_and_a_rerun_resumes(tmp_path: Path) -> None:
    """SIGINT to a running `mkf study` (2 workers): exit 130, finished work kept, no temporary
    files; the same command again finishes the study."""
    import os
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "s"
    cmd = [sys.executable, "-c", "import sys; from mkf_ros.cli.main import main; "
           "sys.exit(main(sys.argv[1:]))", "study", "--n-s", "60", "--filters", "mukf",
           "--charts", "rp", "--updates", "cu", "--R", "1e-4", "--rates", "1000",
           "--workers", "2", "--no-progress", "--no-report", "--out", str(out)]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    p = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True, env=env)
    # event-driven: wait for the first finished unit (or the process's end, a failure); no
    # deadline of its own, the test's pytest-timeout bounds a hang (a cold numba cache first
    # compiles the kernels)
    try:
        while not list((out / "parts").glob("*.npz")):
            assert p.poll() is None, p.stderr.read() if p.stderr else ""
            time.sleep(0.05)
    except BaseException:
        p.kill()
        p.communicate()
        raise
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130, err
    assert "interrupted" in err
    n_parts = len(list((out / "parts").glob("*.npz")))
    assert 1 <= n_parts < 12  # 60 trajectories = 12 units of 5
    assert not list(out.rglob("*.tmp*"))
    assert not (out / "cells.csv").exists()  # the only cell needs all 12 units
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr
    assert len(list((out / "parts").glob("*.npz"))) == 12
    assert len((out / "cells.csv").read_text().splitlines()) == 2
